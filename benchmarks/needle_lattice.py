"""Exit error against where the needle track lies in the particle lattice.

The particles near the needle sit on a regular lattice of the needle spacing h_n; the track
crosses it wherever the entry puts it. Shifting the entry along its edge by k h_n / 10,
k = 0..10, moves the physics a little and smoothly (the exit moves with the entry), but k = 0
and k = 10 put the track at the same place in the lattice. What the exit error does between
them beyond the straight line through those two is the discretization's dependence on the
track's position in the lattice ("aliasing"): on a refinement ladder that is what makes the
exit error go up and down instead of converging monotonically
(benchmarks/results/needle_coupling.md).

Per scene and variant (needle_coupling.py's coupling names: `shipped` the scene's file as it
is; on the files as they were, `fixed` the multiplier elements' least length fixed in mm,
`ramp` the cutting force ramped in, `d=...` the kernel dilation, `q=...` Gauss points per
direction per background cell): the eleven exit errors, the largest deviation from that line
as a share of their mean, and the seconds of a run. `shipped` runs at h, h/2 and h/4 on every
SH 1/2 block and needle20_entry30: the swing beside the changes between those levels
(benchmarks/results/needle_coupling.md).

Writes benchmarks/results/needle_lattice.{csv,md,png}. About 15 minutes. `--scenes`,
`--variants`, `--factors` run a part (its rows replace the CSV's rows of the same scene,
variant and spacing); `--report` only rewrites the table and chart from the CSV.
Run from the repository root:  python benchmarks/needle_lattice.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import _common as common  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import needle_coupling  # noqa: E402
import numpy as np  # noqa: E402

from stitchplan.config.scenario import with_discretization  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402

SCENES = ("sh12_100x50", "sh12_100x100", "needle20_entry30")
VARIANTS = ("mortar", "mortar q=4", "mortar ramp fixed", "mortar ramp fixed d=2.5", "mortar ramp fixed d=2.8",
            "mortar ramp fixed d=3", "mortar ramp fixed d=3.5")
FACTORS = (1.0, 0.5)  # the default spacing and half of it
HALF_VARIANTS = ("mortar", "mortar ramp fixed d=3")  # the ones also run at half the spacing
SHIPPED = needle_coupling.SHIPPED_COUPLING
SHIPPED_SCENES = ("sh12_100x100", "sh12_100x100_mid", "sh12_100x50", "sh12_100x40", "sh12_100x30", "needle20_entry30")
SHIPPED_FACTORS = (1.0, 0.5, 0.25)
OFFSETS = 11  # k h_n / 10, k = 0..10
FIELDS = ("scene", "variant", "factor", "needle_spacing_mm", "offsets_mm", "exit_errors_mm", "aliasing",
          "seconds_per_run")


def lattice_sweep(name: str, variant: str, factor: float) -> dict:
    """The exit errors with the entry shifted through one needle spacing."""
    base = needle_coupling.scene(name, variant)
    base = with_discretization(base, spacing=base.discretization.spacing * factor)
    needle_spacing = base.discretization.needle_spacing
    offsets = needle_spacing * np.arange(OFFSETS) / (OFFSETS - 1)
    errors, start = [], time.perf_counter()
    for offset in offsets:
        entry = (base.needle.entry[0], base.needle.entry[1] + offset)
        errors.append(run_insertion(replace(base, needle=replace(base.needle, entry=entry))).exit_error_mm)
    seconds = (time.perf_counter() - start) / OFFSETS
    errors = np.array(errors)
    line = errors[0] + (errors[-1] - errors[0]) * np.arange(OFFSETS) / (OFFSETS - 1)
    row = {"scene": name, "variant": variant, "factor": f"{factor:.4f}", "needle_spacing_mm": f"{needle_spacing:.4f}",
           "offsets_mm": " ".join(f"{o:.4f}" for o in offsets), "exit_errors_mm": " ".join(f"{e:.6f}" for e in errors),
           "aliasing": f"{np.abs(errors - line).max() / errors.mean():.5f}", "seconds_per_run": f"{seconds:.2f}"}
    print(row["scene"], row["variant"], row["factor"], "aliasing", row["aliasing"], flush=True)
    return row


def markdown(rows: list[dict]) -> str:
    lines = ["# Exit error against the track's place in the particle lattice", "",
             "`python benchmarks/needle_lattice.py` (results/needle_lattice.csv holds the exit errors).",
             "The entry shifted along its edge by k/10 of the needle spacing h_n, k = 0..10: k = 0 and",
             "k = 10 put the track at the same place in the lattice. Aliasing: the largest deviation of",
             "the eleven exit errors from the straight line through those two, as a share of their",
             "mean. Variants as in needle_coupling.py (`ramp`, `fixed`, `d=` the dilation, 2 by",
             "default; `q=4` four Gauss points per direction per background cell instead of two).", "",
             "Reading: on the SH 1/2 blocks the default's exit error swings periodically with the needle",
             "spacing, by 1.0-1.6 % (1.1-1.2 % at half the spacing); more Gauss points leave it, a wider",
             "kernel support takes it down to 0.15-0.36 % at dilation 2.8-3 (0.11-0.15 % at half the",
             "spacing). On needle20_entry30 the exit error rises by 8 % over the 2.5 mm shift and the",
             "deviation from the line (0.8-1.2 %) is that rise's curvature and a step between the first",
             "two shifts, not a periodic swing; the dilation does not change it.", "",
             "The files as shipped (`shipped`, 0.888 mm at the needle on the SH 1/2 blocks): 0.2-1.1 % at h",
             "(0.85 % on sh12_100x100_mid, 1.08 % on sh12_100x50), 0.2-0.4 % at h/2, 0.07-0.2 % at h/4,",
             "against changes between needle_coupling.md's levels of 0.02-0.6 % on the three blocks whose",
             "h, h/sqrt2, h/2 is not monotone: those ladders go up and down within the swing. The 20 mm",
             "needle's 0.8-1.1 % at every level is its exit error's rise with the entry (8 %), as above.", "",
             "| scene | variant | spacing | h_n (mm) | exit error, mean (mm) | range (mm) | aliasing | s per run |",
             "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        errors = np.array(row["exit_errors_mm"].split(), dtype=float)
        spacing = "h" if float(row["factor"]) == 1.0 else f"h x {float(row['factor']):g}"
        lines.append(f"| {row['scene']} | {row['variant']} | {spacing} | {float(row['needle_spacing_mm']):.3f} | "
                     f"{errors.mean():.4f} | {errors.min():.4f}-{errors.max():.4f} | "
                     f"{100 * float(row['aliasing']):.2f} % | {float(row['seconds_per_run']):.2f} |")
    return "\n".join(lines) + "\n"


def chart(rows: list[dict], path) -> None:
    """One panel per scene (columns) and spacing (rows: h, h/2)."""
    scenes = list(dict.fromkeys(row["scene"] for row in rows))
    factors = sorted({row["factor"] for row in rows}, key=lambda f: -float(f))
    figure, axes = plt.subplots(len(factors), len(scenes), figsize=(4.8 * len(scenes), 3.6 * len(factors)),
                                squeeze=False)
    variants = list(dict.fromkeys(row["variant"] for row in rows))
    panels = [(name, factor) for factor in factors for name in scenes]
    for axis, (name, factor) in zip(axes.ravel(), panels):
        for row in rows:
            if (row["scene"], row["factor"]) != (name, factor):
                continue
            errors = np.array(row["exit_errors_mm"].split(), dtype=float)
            shift = np.arange(OFFSETS) / (OFFSETS - 1)
            axis.plot(shift, errors, "o-", ms=3, color=f"C{variants.index(row['variant'])}", label=row["variant"])
        axis.set_title(f"{name}, spacing h x {float(factor):g}", fontsize=9)
        axis.set_xlabel("entry shift / needle spacing", fontsize=8)
        axis.set_ylabel("exit error (mm)", fontsize=8)
    common.panels_legend(figure, axes, ncol=4)
    figure.suptitle("Unplanned exit error as the track moves through one needle spacing of the lattice")
    common.save_figure(figure, path, (0, 0.08, 1, 0.96))


def sweeps() -> list[tuple[str, str, float]]:
    """Every (scene, variant, factor) of the full run."""
    older = [(name, variant, factor) for name in SCENES for factor in FACTORS
             for variant in (VARIANTS if factor == 1.0 else HALF_VARIANTS)]
    return older + [(name, SHIPPED, factor) for name in SHIPPED_SCENES for factor in SHIPPED_FACTORS]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*")
    parser.add_argument("--variants", nargs="*")
    parser.add_argument("--factors", nargs="*", type=float)
    parser.add_argument("--report", action="store_true", help="only rewrite the table and chart from the CSV")
    options = parser.parse_args()
    logging.disable(logging.WARNING)
    csv_path = common.results_path("needle_lattice.csv")
    rows = common.csv_rows(csv_path) if csv_path.exists() else []
    if not options.report:
        chosen = [(name, variant, factor) for name, variant, factor in sweeps()
                  if (options.scenes is None or name in options.scenes)
                  and (options.variants is None or variant in options.variants)
                  and (options.factors is None or factor in options.factors)]
        for name, variant, factor in chosen:
            new = lattice_sweep(name, variant, factor)
            same = [i for i, row in enumerate(rows)
                    if all(row[key] == new[key] for key in ("scene", "variant", "factor"))]
            if same:
                rows[same[0]] = new
            else:
                rows.append(new)
            common.write_csv(csv_path, FIELDS, [[row[key] for key in FIELDS] for row in rows])
    common.publish("needle_lattice", markdown(rows), chart, rows)


if __name__ == "__main__":
    main()
