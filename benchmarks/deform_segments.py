"""Load segments against an independent FEM: `deform` on displacement and force segments
whose ends fall on, or between, the grid lines of the default spacing.

The problem (the user report behind "Accuracy you can trust"): a 100 x 60 mm slab of the
thesis's phantom (SVK, lambda 0.189151, mu 0.147688 MPa, t = 10 mm), right edge clamped,
20 load steps, loaded on the left edge by
  * displacement (-8, 6) mm on y in [24, 36] (segment ends on the 3 mm grid lines),
  * displacement (-8, 6) mm on y in [23.3, 37.1] (ends between them),
  * force (-3, 1) N on y in [23.3, 37.1].
Reference: scikit-fem Q2 quadrilaterals (benchmarks/skfem_reference.solve_skfem) with mesh
lines through the segment ends and geometric grading toward them; its own convergence is
checked between two mesh levels (h halved). stitchplan runs at spacings 6, 4, 3 (the default,
min(W, H)/20), 2 and 1.5 mm; the error is max over the probes of |u - u_ref| / max |u_ref|,
and the observed rate is the least-squares log-log slope of error against spacing. On
displacement segments the table also gives max |u - g| / |g| over 201 points of the segment
(u = g holds to round-off at the particles on it; between them u - g is the interpolation
error of the RK field).

Writes benchmarks/results/deform_segments.{md,csv,png} and prints the tables.
Run from the repository root:  python benchmarks/deform_segments.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import _common as common  # noqa: E402
from skfem_reference import solve_skfem  # noqa: E402
from stitchplan.config import default_spacing  # noqa: E402
from stitchplan.config.scenario import parse_scenario, with_discretization  # noqa: E402
from stitchplan.tissue.deform import interpolate, run_deform  # noqa: E402

DESCRIPTION = (
    "A 100 x 60 mm slab of the thesis's phantom (SVK, lambda 0.189151, mu 0.147688 MPa, t = 10 mm), "
    "right edge clamped, 20 load steps, loaded on the left edge by a displacement (-8, 6) mm on "
    "y in [24, 36] (segment ends on the 3 mm grid lines) or on y in [23.3, 37.1] (ends between "
    "them), or by a force (-3, 1) N on y in [23.3, 37.1]. Reference: scikit-fem Q2 quadrilaterals "
    "(benchmarks/skfem_reference.solve_skfem) with mesh lines through the segment ends and four "
    "levels of geometric grading toward them; its own convergence is the probe change between "
    "its two meshes (h halved). Error = max over the probes of |u - u_ref| / max |u_ref|; observed "
    "rate = least-squares log-log slope of error against spacing. On displacement segments the "
    "table also gives max norm(u - g) / norm(g) over 201 points of the segment: u = g holds to "
    "round-off at the particles on it (the transformation method); between them u - g is the "
    "interpolation error of the RK field, largest next to the segment ends.")
PROBES = [[0.0, 45.0], [0.0, 15.0], [10.0, 30.0], [25.0, 30.0], [50.0, 45.0], [75.0, 15.0]]
PROBLEMS = {  # name: (kind, y range of the left-edge segment, value)
    "displacement, ends on grid lines": ("displacement", (24.0, 36.0), (-8.0, 6.0)),
    "displacement, ends between grid lines": ("displacement", (23.3, 37.1), (-8.0, 6.0)),
    "force, ends between grid lines": ("force", (23.3, 37.1), (-3.0, 1.0)),
}
SPACINGS = (6.0, 4.0, 3.0, 2.0, 1.5)
FEM_LEVELS = ((25, 4), (50, 4))  # Q2 cells per side, geometric grading levels: coarse, reference


def scenario(kind: str, span: tuple[float, float], value: tuple[float, float]):
    raw = {"tissue": {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"],
                      "material": {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151,
                                   "lame_mu": 0.147688}},
           "loads": [{"segment": [[0.0, span[0]], [0.0, span[1]]], kind: list(value)}],
           "load_steps": 20, "probes": PROBES}
    return parse_scenario(raw)


def main() -> None:
    rows, fem_rows, slopes = [], [], {}
    for name, (kind, span, value) in PROBLEMS.items():
        base = scenario(kind, span, value)
        default = default_spacing(base.tissue, None)
        print(f"{name}: scikit-fem reference ...", flush=True)
        fem = [solve_skfem(base, "Q2-quad", cells, grading) for cells, grading in FEM_LEVELS]
        reference = fem[-1].probe_displacements
        fem_change = common.max_probe_error(fem[0].probe_displacements, reference)
        for run, (cells, grading) in zip(fem, FEM_LEVELS):
            fem_rows.append([name, f"Q2, {cells} cells per side + {grading} graded levels", run.dofs,
                             f"{100 * common.max_probe_error(run.probe_displacements, reference):.4f} %"
                             if run is not fem[-1] else "reference",
                             f"{run.reactions[0][0]:.4f}", f"{run.reactions[0][1]:.4f}"])
        print(f"  FEM change between its two levels: {100 * fem_change:.4f} %", flush=True)
        errors = []
        for spacing in SPACINGS:
            start = time.perf_counter()
            result = run_deform(with_discretization(base, spacing=spacing))
            seconds = time.perf_counter() - start
            error = common.max_probe_error(result.probe_displacements, reference)
            errors.append(error)
            held = np.nan  # max |u - g| / |g| along a displacement segment (201 points)
            if kind == "displacement":
                along = np.column_stack([np.zeros(201), np.linspace(*span, 201)])
                gap = interpolate(result.model, result.coefficients, along) - np.asarray(value)
                held = float(np.linalg.norm(gap, axis=1).max() / np.linalg.norm(value))
            rows.append({"problem": name, "spacing": spacing, "default": spacing == default,
                         "particles": result.model.n_particles, "seconds": seconds, "error": error,
                         "reaction": result.reactions[0], "fem_reaction": fem[-1].reactions[0],
                         "fem_change": fem_change, "probes": result.probe_displacements,
                         "held": held})
            print(f"  spacing {spacing:g} mm: {result.model.n_particles} particles, error "
                  f"{100 * error:.3f} %, reaction {result.reactions[0]} N ({seconds:.1f} s)", flush=True)
        slopes[name] = common.loglog_slope(SPACINGS, errors)

    header = ["problem", "spacing_mm", "default", "particles", "seconds", "max_probe_error_rel",
              "segment_deviation_rel",
              "reaction_x_N", "reaction_y_N", "fem_reaction_x_N", "fem_reaction_y_N",
              *[f"{c}({x:g},{y:g})" for x, y in PROBES for c in ("ux", "uy")]]
    common.write_csv(common.results_path("deform_segments.csv"), header, [
        [r["problem"], r["spacing"], r["default"], r["particles"], r["seconds"], r["error"], r["held"],
         *r["reaction"], *r["fem_reaction"], *r["probes"].ravel()] for r in rows])

    table = common.markdown_table(
        ["problem", "spacing (mm)", "particles", "max probe error", "max norm(u - g) / norm(g) on the segment",
         "reaction (N)", "FEM reaction (N)", "time (s)"],
        [[r["problem"], f"{r['spacing']:g}" + (" (default)" if r["default"] else ""), r["particles"],
          f"{100 * r['error']:.3f} %", "-" if np.isnan(r["held"]) else f"{100 * r['held']:.3f} %", f"({r['reaction'][0]:.4f}, {r['reaction'][1]:.4f})",
          f"({r['fem_reaction'][0]:.4f}, {r['fem_reaction'][1]:.4f})", r["seconds"]] for r in rows])
    fem_table = common.markdown_table(
        ["problem", "mesh", "dofs", "probe change to the reference", "reaction x (N)", "reaction y (N)"],
        fem_rows)
    slope_table = common.markdown_table(
        ["problem", "observed rate (slope of log error vs log spacing)", "error at the default"],
        [[name, f"{slope:.2f}", f"{100 * next(r['error'] for r in rows if r['problem'] == name and r['default']):.3f} %"]
         for name, slope in slopes.items()])
    common.write_report("deform_segments.md", [
        "# Load segments against scikit-fem",
        "",
        DESCRIPTION,
        "",
        f"Probes: {PROBES}.",
        "",
        "## Reference (scikit-fem)",
        "",
        fem_table,
        "",
        "## stitchplan deform",
        "",
        table,
        "",
        slope_table,
        "",
        "Time = the whole `run_deform` call (discretization, solve, probes, reactions) on a machine "
        "shared with other jobs.",
        "",
        f"Machine: {common.machine_note()}.",
        "",
    ])

    figure, axis = plt.subplots(figsize=(6, 4.5))
    for name, marker in zip(PROBLEMS, ("o-", "s-", "^-")):
        chosen = [r for r in rows if r["problem"] == name]
        axis.loglog([r["spacing"] for r in chosen], [100 * r["error"] for r in chosen], marker,
                    label=f"{name} (rate {slopes[name]:.2f})")
    h = np.array([SPACINGS[0], SPACINGS[-1]])
    axis.loglog(h, 0.5 * (h / 3.0) ** 1.5, "k:", lw=0.8, label="slope 1.5 through 0.5 % at 3 mm")
    axis.axhline(0.5, color="grey", lw=0.8, ls="--")
    axis.axvline(3.0, color="grey", lw=0.8, ls=":")
    axis.set_xlabel("particle spacing (mm)")
    axis.set_ylabel("max probe error vs scikit-fem Q2 (%)")
    axis.set_title("100 x 60 slab, left-edge load segment")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(common.results_path("deform_segments.png"), dpi=120)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
