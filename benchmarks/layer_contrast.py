"""Accuracy across a material interface against its contrast: `stitchplan deform` on two-layer
slabs laid out as configs/skin_layered.yaml (60 x 30 mm, 10 mm thick, a 2 mm top layer over
y = 28, clamped along the bottom, 2 N pulling the right edge across both layers), the layers'
moduli in ratios 1, 4, 30 and 1000, the stiff layer on top (skin over fat) and below (a soft
top layer), each against a fine scikit-fem solution.

The layers are St. Venant-Kirchhoff (the reference implements only it; skin_layered's are
neo-Hookean): the soft one the thesis's phantom (lambda 0.189151, mu 0.147688 MPa), the stiff
one `ratio` times its moduli. The reference is benchmarks/skfem_reference.solve_skfem_shape:
Q2 quadrilaterals of side REFERENCE_H with a mesh line on the interface (the kink between
elements) and graded toward every vertex (the interface's ends are corners of two materials);
its own refinement change is the probe change from side 2 REFERENCE_H. stitchplan runs at the
default spacing (1.5 mm, min(W, H)/20), half and a quarter of it, and with the particles graded
toward the interface (discretization.interface_levels 1) at the default spacing and half of it
for the contrasts above 1. Error = max over the probes of |u - u_ref| / max |u_ref|; rate =
log(e1/e2)/log(h1/h2).

Writes benchmarks/results/layer_contrast.{csv,md,png} and prints the table; about 3 minutes on
two quiet cores, 5 on a shared machine.
Run from the repository root:  python benchmarks/layer_contrast.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import math  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

import _common as common  # noqa: E402
from skfem_reference import solve_skfem_shape  # noqa: E402
from stitchplan.config.scenario import parse_scenario, with_discretization  # noqa: E402
from stitchplan.tissue.deform import run_deform  # noqa: E402

PHANTOM = (0.189151, 0.147688)  # lame_lambda, lame_mu (MPa): the soft layer
RATIOS = (1.0, 4.0, 30.0, 1000.0)
PLACEMENTS = ("stiff on top", "soft on top")
REFINEMENTS = (1, 2, 4)  # spacing = default / r
GRADED = {"levels": 1, "refinements": (1, 2)}  # interface_levels and the spacings they run at
REFERENCE_H = 1.0  # mm, Q2 element side (from 2 mm its probes change by the table's last column)
# skin_layered's probes (the needle's entry and exit, one between, the interface below the entry,
# the loaded edge's top and middle) and where the interface meets the loaded edge
PROBES = [[30.0, 30.0], [21.12, 30.0], [12.24, 30.0], [30.0, 28.0], [60.0, 30.0], [60.0, 15.0], [60.0, 28.0]]


def scene(ratio: float, placement: str):
    soft = {"model": "saint-venant-kirchhoff", "lame_lambda": PHANTOM[0], "lame_mu": PHANTOM[1]}
    stiff = {**soft, "lame_lambda": ratio * PHANTOM[0], "lame_mu": ratio * PHANTOM[1]}
    top, bottom = (stiff, soft) if placement == "stiff on top" else (soft, stiff)
    return parse_scenario({
        "name": f"two layers, {placement}, ratio {ratio:g}",
        "tissue": {"size": [60.0, 30.0], "thickness": 10.0, "material": bottom, "clamped": ["bottom"],
                   "regions": [{"polygon": [[0.0, 28.0], [60.0, 28.0], [60.0, 30.0], [0.0, 30.0]],
                                "material": top}]},
        "loads": [{"segment": [[60.0, 0.0], [60.0, 30.0]], "force": [2.0, 0.0]}],
        "probes": PROBES})


def cases() -> list[tuple[float, str]]:
    return [(ratio, placement) for ratio in RATIOS for placement in PLACEMENTS
            if ratio > 1.0 or placement == PLACEMENTS[0]]  # ratio 1: one material, once


def rates(spacings: list[float], errors: list[float]) -> list[float]:
    return [math.log(errors[k] / errors[k + 1]) / math.log(spacings[k] / spacings[k + 1])
            for k in range(len(errors) - 1)]


def main() -> None:
    rows, table = [], []
    for ratio, placement in cases():
        scenario = scene(ratio, placement)
        default = scenario.discretization.spacing
        print(f"{placement}, ratio {ratio:g}: skfem reference h = {REFERENCE_H:g} mm ...", flush=True)
        reference = solve_skfem_shape(scenario, REFERENCE_H)
        change = common.max_probe_error(solve_skfem_shape(scenario, 2 * REFERENCE_H).probe_displacements,
                                        reference.probe_displacements)
        scale = float(np.linalg.norm(reference.probe_displacements, axis=1).max())
        rows.append({"ratio": ratio, "placement": placement, "grading": "reference", "spacing": 0.0,
                     "particles": reference.dofs, "seconds": reference.seconds, "error": change, "worst": "",
                     "probes": reference.probe_displacements})
        runs = {"uniform": (0, REFINEMENTS)}
        if ratio > 1.0:
            runs[f"interface_levels {GRADED['levels']}"] = (GRADED["levels"], GRADED["refinements"])
        for grading, (levels, refinements) in runs.items():
            errors, spacings = [], []
            for r in refinements:
                spacing = default / r
                result = run_deform(with_discretization(scenario, spacing=spacing, interface_levels=levels))
                per_probe = np.linalg.norm(result.probe_displacements - reference.probe_displacements, axis=1) / scale
                errors.append(float(per_probe.max()))
                spacings.append(spacing)
                worst = PROBES[int(np.argmax(per_probe))]
                rows.append({"ratio": ratio, "placement": placement, "grading": grading, "spacing": spacing,
                             "particles": result.model.n_particles, "seconds": result.wall_seconds,
                             "error": errors[-1], "worst": f"({worst[0]:g}, {worst[1]:g})",
                             "probes": result.probe_displacements})
                print(f"  {grading}, spacing {spacing:g} mm: {result.model.n_particles} particles, error "
                      f"{100 * errors[-1]:.3f} % (worst at {rows[-1]['worst']}), {result.wall_seconds:.1f} s",
                      flush=True)
            table.append([placement, f"{ratio:g}", grading,
                          *(f"{100 * e:.3f} % ({row['particles']})" for e, row in zip(errors, rows[-len(errors):])),
                          *([""] * (len(REFINEMENTS) - len(errors))),
                          ", ".join(f"{q:.2f}" for q in rates(spacings, errors)), rows[-1]["worst"],
                          f"{scale:.4f}", f"{100 * change:.4f} %"])

    header = ["placement", "ratio", "grading", *(f"error at default/{r} (particles)" for r in REFINEMENTS),
              "rates", "worst probe at the finest", "max \\|u_ref\\| (mm)", "reference change from h 2 mm"]
    text = "\n".join([
        "# Accuracy across a material interface against its contrast",
        "",
        "`stitchplan deform` (default discretization; spacing 1.5 mm, half and a quarter of it) on a "
        "60 x 30 mm slab with a 2 mm top layer (configs/skin_layered.yaml's layout, load and probes, "
        "St. Venant-Kirchhoff layers: the soft one the thesis's phantom, the stiff one `ratio` times its "
        "moduli), uniform, and with the particles graded toward the interface "
        f"(`discretization.interface_levels: {GRADED['levels']}`: spacing / 2 at the interface at the default "
        "spacing, one level more per halving), against scikit-fem Q2 on a mesh with a line on the "
        f"interface, h {REFERENCE_H:g} mm, graded toward every vertex (`solve_skfem_shape`). Error = max over "
        "the probes of |u - u_ref| / max |u_ref|; rates = log(e1/e2)/log(h1/h2) between successive spacings. "
        f"Probes: {PROBES}. The CSV has every run's probe displacements (the reference's in its rows of "
        "spacing 0, whose error column is the reference's own change from h 2 mm).",
        "",
        common.markdown_table(header, table),
        "",
        "Times (s, the solve from the loaded scenario, a machine shared with other jobs) are in the CSV.",
        "",
        f"Machine: {common.machine_note()}.",
        "",
    ])
    common.write_csv(common.results_path("layer_contrast.csv"),
                     ["placement", "ratio", "grading", "spacing_mm", "particles_or_dofs", "wall_seconds",
                      "max_probe_error_rel", "worst_probe",
                      *[f"{c}({x:g},{y:g})" for x, y in PROBES for c in ("ux", "uy")]],
                     [[r["placement"], r["ratio"], r["grading"], r["spacing"], r["particles"], r["seconds"],
                       r["error"], r["worst"], *np.asarray(r["probes"]).ravel()] for r in rows])
    common.results_path("layer_contrast.md").write_text(text)
    print(text)
    chart(rows)


def chart(rows: list[dict]) -> None:
    figure, axes = plt.subplots(1, 2, figsize=(10, 4.8), sharey=True)
    colours = dict(zip(RATIOS, ("grey", "tab:blue", "tab:orange", "tab:red")))
    for axis, placement in zip(axes, PLACEMENTS):
        for ratio in RATIOS:
            for grading, style in (("uniform", "o-"), (f"interface_levels {GRADED['levels']}", "s--")):
                chosen = [r for r in rows if (r["placement"] == placement or r["ratio"] == 1.0)
                          and r["ratio"] == ratio and r["grading"] == grading]
                if chosen:
                    axis.loglog([r["spacing"] for r in chosen], [100 * r["error"] for r in chosen], style,
                                color=colours[ratio], label=f"ratio {ratio:g}, {grading}")
        axis.set_title(f"{placement} (2 mm top layer)")
        axis.set_xlabel("particle spacing (mm)")
        axis.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        axis.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        axis.set_xticks([1.5, 0.75, 0.375])
        axis.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("max probe error vs scikit-fem (% of max |u|)")
    common.panels_legend(figure, axes, ncol=4)
    common.save_figure(figure, common.results_path("layer_contrast.png"), (0, 0.12, 1, 1))


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
