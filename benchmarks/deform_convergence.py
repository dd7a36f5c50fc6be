"""Mesh-convergence study of `stitchplan deform` on configs/slab_edge_load.yaml.

Runs the 10-step static solve at particle spacings 10 ... 1 mm (dilation 2, default
quadrature) and compares the probe displacements with the finest run:

    error = max_i |u_i - u_i(finest)| / max_i |u_i(finest)|

Writes benchmarks/results/deform_convergence.{csv,md,png} and prints the table.
Run from the repository root:  python benchmarks/deform_convergence.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it (and for both codes compared):
# the numerics are sparse and small-dense, and BLAS threads only compete on 2 cores
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.config.scenario import with_discretization  # noqa: E402
from stitchplan.tissue.deform import run_deform  # noqa: E402

SPACINGS = (10.0, 5.0, 4.0, 2.5, 2.0, 1.25, 1.0)
DILATION = 2.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3,
                        help="minimum timed runs per spacing (cheap spacings get more, up to ~3 s "
                             "of runs); the table shows the median wall time")
    args = parser.parse_args()

    base = common.load_slab_scenario()
    probes = np.asarray(base.probes)
    run_deform(with_discretization(base, spacing=SPACINGS[0], dilation=DILATION))  # warm-up
    runs = []
    for spacing in SPACINGS:
        scenario = with_discretization(base, spacing=spacing, dilation=DILATION)
        results = [run_deform(scenario)]
        repeats = common.repeats_for(results[0].wall_seconds, args.repeats)
        results += [run_deform(scenario) for _ in range(repeats - 1)]
        result = results[-1]
        runs.append({
            "spacing": spacing,
            "grid_spacing": result.model.spacing,
            "particles": result.model.n_particles,
            "iterations": result.report.iterations,
            "u": result.probe_displacements,
            "wall": statistics.median(r.wall_seconds for r in results),
            "runs": len(results),
        })
        print(f"spacing {spacing:5.2f} mm: {result.model.n_particles:6d} particles, "
              f"{runs[-1]['wall']:.3f} s (median of {len(results)})", flush=True)

    reference = runs[-1]["u"]
    scale = float(np.linalg.norm(reference, axis=1).max())
    for run in runs:
        run["error"] = common.max_probe_error(run["u"], reference)
        run["change"] = None
    for coarse, fine in zip(runs[:-1], runs[1:]):
        fine["change"] = common.max_probe_error(fine["u"], coarse["u"])

    # observed order: fit error ~ C h^p over the runs at least twice as coarse as the finest
    # (closer to the reference, the error against it is biased low)
    finest = runs[-1]["spacing"]
    fit = [r for r in runs if r["spacing"] >= 2 * finest and r["error"] > 0]
    rate = common.loglog_slope([r["spacing"] for r in fit], [r["error"] for r in fit])
    rate_all = common.loglog_slope([r["spacing"] for r in runs[:-1]], [r["error"] for r in runs[:-1]])

    probe_columns = [f"{c}({x:g},{y:g})" for x, y in probes for c in ("ux", "uy", "abs_u")]
    header = ["spacing_mm", "particles", *probe_columns, "max_probe_error_rel",
              "change_from_previous_rel", "newton_iterations", "wall_seconds_median", "timed_runs"]
    rows = [[r["spacing"], r["particles"],
             *np.column_stack([r["u"], np.linalg.norm(r["u"], axis=1)]).ravel(), r["error"],
             r["change"] if r["change"] is not None else "", r["iterations"], r["wall"], r["runs"]]
            for r in runs]
    common.write_csv(common.results_path("deform_convergence.csv"), header, rows)

    md_rows = [[r["spacing"], r["particles"], *(f"{v:.4f}" for v in np.linalg.norm(r["u"], axis=1)),
                f"{100 * r['error']:.3f} %" if r["error"] > 0 else "(reference)",
                r["wall"]] for r in runs]
    md_header = ["spacing (mm)", "particles", *[f"\\|u\\| ({x:g},{y:g}) mm" for x, y in probes],
                 "max probe error", "wall s (median)"]
    table = common.markdown_table(md_header, md_rows)
    summary = (
        f"Observed rate: error ~ h^{rate:.2f} (fit over spacings >= {2 * finest:g} mm, "
        f"i.e. at least twice the reference spacing); h^{rate_all:.2f} over all spacings "
        f"except the reference."
    )
    text = "\n".join([
        "# stitchplan deform: convergence on configs/slab_edge_load.yaml",
        "",
        f"Dilation {DILATION:g}, default quadrature (2x2 Gauss per background cell), 10 load "
        f"steps. Error = max over probes of |u - u_ref| / max |u_ref|, with u_ref the "
        f"{finest:g} mm run (largest probe displacement {scale:.4f} mm). Wall time = "
        f"`DeformResult.wall_seconds` (discretization + solve), median of "
        f"{min(r['runs'] for r in runs)}-{max(r['runs'] for r in runs)} runs (more for the cheap "
        f"spacings) after one untimed warm-up run.",
        "",
        table,
        "",
        summary,
        "",
        f"Machine: {common.machine_note()}",
        "",
    ])
    common.results_path("deform_convergence.md").write_text(text)
    print()
    print(table)
    print()
    print(summary)

    figure, axis = plt.subplots(figsize=(5.5, 4.2))
    h = np.array([r["spacing"] for r in runs[:-1]])
    e = np.array([r["error"] for r in runs[:-1]])
    axis.loglog(h, 100 * e, "o-", label=f"stitchplan (vs {finest:g} mm run)")
    slope, intercept = np.polyfit(np.log([r["spacing"] for r in fit]), np.log([r["error"] for r in fit]), 1)
    axis.loglog(h, 100 * np.exp(intercept) * h**slope, "k--", lw=0.8, label=f"fit: h^{rate:.2f}")
    axis.axhline(1.0, color="grey", lw=0.8, ls=":")
    axis.set_xticks(h)
    axis.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    axis.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axis.set_xlabel("particle spacing h (mm)")
    axis.set_ylabel("max probe error (% of largest |u|)")
    axis.set_title("slab_edge_load: probe convergence")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend()
    figure.tight_layout()
    figure.savefig(common.results_path("deform_convergence.png"), dpi=120)


if __name__ == "__main__":
    main()
