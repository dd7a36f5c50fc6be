"""PNG figures: deformed tissue, needle insertion, plan and study (the calibration figures
are in `calibration_plots`).

Every figure names its scenario and its key figure (exit error, probe displacement, fit
residual) in the title, draws the tissue outline, clamps, loads and probes where they apply,
keeps legends below the data, uses one colour scale per figure and units on every axis.
Each plot function returns its (closed) matplotlib figure so tests can read it back. The
shared drawing pieces live in `plot_elements`.
"""

from __future__ import annotations

import io
import math
from collections import Counter
from pathlib import Path

import numpy as np

from ..errors import InputError
from .files import write_bytes
from .plot_elements import (
    CMAP,
    SAVED_DPI,
    draw_clamps,
    draw_loads,
    draw_outline,
    draw_regions,
    draw_probes,
    frame,
    label_mm,
    legend_below,
    literal,
    magnitude_norm,
    pyplot,
    readable_log_axis,
    title_above,
)


def save(fig, path: str | Path) -> None:
    """Write the figure as PNG to `path` as given: the writers of io.reports and friends hand
    the plots the temporaries of their OutputSet, which renames them only when all succeeded.
    Cropped to its tight box at the PNG's dpi (the figures are made at it, SAVED_DPI), padded
    as savefig's bbox_inches="tight" pads it, measured without the draw of the whole figure
    that "tight" makes first (the same PNG byte for byte, benchmarks/command_overlap.py). Its
    Software text names the package's version and the SHA-256 of its sources, as the run's
    other records do: a figure kept alone still says which code drew it."""
    import matplotlib
    import matplotlib.pyplot as plt

    from .. import __version__, source_sha256

    software = f"stitchplan {__version__} (sources SHA-256 {source_sha256()})"
    buffer = io.BytesIO()  # drawn in memory, so that a failed write names its file (files.write_bytes)
    try:
        box = fig.get_tightbbox(fig.canvas.get_renderer()).padded(matplotlib.rcParams["savefig.pad_inches"])
        fig.savefig(buffer, dpi=SAVED_DPI, bbox_inches=box, format="png", metadata={"Software": software})
    finally:
        plt.close(fig)
    write_bytes(path, buffer.getbuffer())


def shown_name(scenario, fallback: str) -> str:
    return literal(getattr(scenario, "name", "")) or fallback


# --- deform ---------------------------------------------------------------------------------

# The largest enlargement of the displacements in deformed.png (deform --plot-scale). A
# micrometre drawn a million times enlarged is a metre, ten times a 100 mm slab: more draws
# nothing a reader can use, and near 1e308 the drawn positions and the axis limits overflow.
MAX_PLOT_SCALE = 1e6


def check_plot_scale(scale: float) -> None:
    """InputError naming --plot-scale unless 0 < scale <= MAX_PLOT_SCALE (nan refused)."""
    if not 0 < scale <= MAX_PLOT_SCALE:
        raise InputError(f"--plot-scale: got {scale!r}, expected a positive number of at most {MAX_PLOT_SCALE:g} "
                         "(1 = true scale)")


def plot_deformed(path: str | Path, result, scale: float = 1.0):
    """deformed.png of `stitchplan deform`: particles where the loads moved them, coloured by
    |u|; the outline at rest and deformed, clamps, loads and probes. Positions are drawn with
    the displacements `scale` times enlarged (at most MAX_PLOT_SCALE); colours and numbers
    stay true."""
    from ..tissue.deform import interpolate

    check_plot_scale(scale)
    plt = pyplot()
    scenario = result.scenario
    tissue, domain = scenario.tissue, scenario.tissue.domain
    particles, u = result.model.particles, result.particle_displacements  # (NP, 2)
    size = float(max(domain.size))
    magnitude = np.linalg.norm(u, axis=1)
    fig, ax = plt.subplots(figsize=(7.5, 7.0), dpi=SAVED_DPI)
    draw_outline(ax, domain, particles, u, scale)
    draw_regions(ax, tissue)
    moved = particles + scale * u
    dots = ax.scatter(*moved.T, s=8, c=magnitude, cmap=CMAP, norm=magnitude_norm(u), zorder=2)
    # the bar as tall as the tissue's drawn box (not the figure's), so the legend below both stays clear of it
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    fig.colorbar(dots, cax=make_axes_locatable(ax).append_axes("right", size="3%", pad=0.15),
                 label="|u| displacement (mm)")

    def move(points):
        return points + scale * interpolate(result.model, result.coefficients, points)

    ends = draw_loads(ax, scenario.loads, domain, 0.15 * size, move)
    probes_moved = result.probes + scale * result.probe_displacements
    draw_probes(ax, result.probes, probes_moved, size)
    frame(ax, np.vstack([particles, moved, ends, probes_moved]), margin=0.08)
    draw_clamps(ax, tissue, 0.025 * size)
    label_mm(ax)
    loads = len(scenario.loads)
    title = (f"{shown_name(scenario, 'deform')}: deformed under {loads} load{'s' if loads != 1 else ''}"
             f" ({scenario.load_steps} load steps)\nlargest |u| {magnitude.max():.3g} mm")
    if len(result.probes):
        at_probes = np.linalg.norm(result.probe_displacements, axis=1)
        k = int(np.argmax(at_probes))
        title += f"; probes: |u| up to {at_probes[k]:.3g} mm (P{k + 1})"
    if scale != 1.0:
        title += f"\ndisplacements drawn {scale:g}x enlarged (colours and numbers true)"
    ax.set_title(title, fontsize=10)
    legend = legend_below(fig, [ax], columns=3)
    if len(result.probes):
        rows = [f"P{k + 1} ({x:g}, {y:g}): u = ({ux:.4g}, {uy:.4g}) mm, |u| = {np.hypot(ux, uy):.4g} mm"
                for k, ((x, y), (ux, uy)) in enumerate(zip(result.probes, result.probe_displacements))]
        fig.canvas.draw()
        below = legend.get_window_extent().transformed(fig.transFigure.inverted()).y0
        fig.text(0.5, below - 0.01, "probes (reference point: displacement)\n" + "\n".join(rows),
                 ha="center", va="top", fontsize=8, family="monospace")
    save(fig, path)
    return fig


# --- needle insertion -----------------------------------------------------------------------


# The legend entry of the study's front; one entry for both panels, which ring the same runs.
PARETO_LABEL = "Pareto front on deviation_mm (study.csv pareto)"


# the right panel's runs of another number of needle steps than the reference: their spatial exit
# is of another needle state
SPATIAL_APART_LABEL = "squared: not as many needle steps as the finest run"


def plot_speed_accuracy(path: str | Path, study):
    """Wall time against exit-point deviation from the study's finest run (log-log), one
    series per method family; failed runs drawn as crosses at the right edge (deviation
    unknown). Left: `deviation_mm` (largest of the spatial, material and exit-error
    deviations); right: the spatial achieved exit alone.

    The Pareto front is the study's own (the runs flagged `pareto`, as in study.csv and
    study.json, found on `deviation_mm`): ringed on both panels and joined on the left.
    The right panel does not look for a front of its own, which would be another set of
    runs under the same name."""
    plt = pyplot()
    runs = [r for r in study.runs if r is not study.reference]
    families = list(dict.fromkeys(r.family for r in runs))
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, 2, figsize=(13.0, 5.8), dpi=SAVED_DPI)
    panels = (("deviation_mm", ("exit-point deviation from the finest run (mm)\n"
               "largest of spatial (if as many needle steps), material and exit-error vector")),
              ("exit_deviation_mm", "achieved exit (spatial) deviation from the finest run (mm)"))
    accuracy = getattr(study.auto, "accuracy", None)
    for ax, (key, xlabel) in zip(axes, panels):
        _speed_accuracy_panel(ax, key, xlabel, runs, families, colours, accuracy)
    axes[0].set_title("exit point: spatial, material and exit-error vector", fontsize=9)
    axes[1].set_title("achieved exit, spatial position only (achieved_exit_def)\n"
                      "ringed: the study's front, found on deviation_mm (left)", fontsize=9)
    title_above(fig, list(axes), _speed_accuracy_headline(study, runs))
    legend_below(fig, list(axes), columns=6)
    save(fig, path)
    return fig


def _speed_accuracy_panel(ax, key: str, xlabel: str, runs, families: list[str], colours,
                          accuracy: float | None) -> None:
    """One panel of speed_accuracy.png: each family's runs, wall time against the deviation
    `key` (deviations of 0 drawn at a floor below the least one), its failed runs as crosses
    at the right edge, the study's front ringed (and, on `deviation_mm`, joined), the auto
    target's accuracy; log axes over the successful runs' wall times."""
    failures = [r for r in runs if not r.ok]
    done = [r for r in runs if r.ok and key in r.deviations]
    values = [r.deviations[key] for r in done]
    floor = min([v for v in values if v > 0] or [1e-3]) / 3.0
    top = max(values or [1.0]) * 3.0
    times = [r.wall_seconds for r in done] or [r.wall_seconds for r in runs]
    low, high = min(times) / 1.5, max(times) * 1.5

    def x_of(run):
        return max(run.deviations[key], floor)

    for k, family in enumerate(families):
        members = sorted((r for r in done if r.family == family), key=lambda r: r.spacing, reverse=True)
        if members:
            ax.plot([x_of(r) for r in members], [r.wall_seconds for r in members], label=literal(family),
                    **_family_style(family, colours(k % 10)))
        failed = [r for r in failures if r.family == family]
        if failed:  # times clipped to the successful runs' range (failures before a solve are instant)
            times = [min(max(r.wall_seconds, low), high) for r in failed]
            ax.plot([top] * len(failed), times, "x", color=colours(k % 10), ms=8, mew=2, clip_on=False,
                    label=f"{literal(family)}: {len(failed)} failed (deviation unknown)")
            # crosses at one time (failures before a solve, clipped alike) are counted beside them
            for time, count in Counter(round(math.log10(t), 1) for t in times).items():
                if count > 1:
                    ax.annotate(f"{count}x", (top, 10.0 ** time), xytext=(7, 0), textcoords="offset points",
                                fontsize=7, color=colours(k % 10), va="center", annotation_clip=False)
    apart = [r for r in done if not r.deviations.get("spatial_compared", True)]
    if apart and key == "exit_deviation_mm":  # deviation_mm leaves these out (exit_deviations)
        ax.plot([x_of(r) for r in apart], [r.wall_seconds for r in apart], "s", mfc="none", mec="0.45", ms=15,
                mew=0.8, zorder=3, label=SPATIAL_APART_LABEL)  # around the front's ring, not under it
    front = sorted((r for r in done if r.pareto), key=lambda r: r.wall_seconds)
    if front and key == "deviation_mm":  # a staircase only on the measure the front is found on
        ax.step([x_of(r) for r in front], [r.wall_seconds for r in front], where="pre", color="black",
                lw=1.2, alpha=0.6)
    if front:
        ax.plot([x_of(r) for r in front], [r.wall_seconds for r in front], "o", mfc="none", mec="black",
                ms=11, label=PARETO_LABEL)
    if accuracy is not None and key == "deviation_mm":
        ax.axvline(accuracy, color="crimson", ls="--", lw=1, label=f"auto target {accuracy:g} mm")
    if failures:
        ax.axvline(top, color="0.6", lw=0.8, ls=":")
    _log_log_axes(ax, xlabel, (low, high))


def _family_style(family: str, colour) -> dict:
    """A method family's markers: the accuracy-driven discretization (`auto`) a lone star."""
    if family == "auto":
        return {"color": "crimson", "marker": "*", "ms": 16, "ls": "none"}
    return {"color": colour, "marker": "o", "ms": 5, "lw": 0.8}


def _log_log_axes(ax, xlabel: str, wall_times: tuple[float, float]) -> None:
    """Log scales with readable tick labels, the wall-time range, the axis labels and a grid."""
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(*wall_times)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("wall time (s)")
    ax.grid(alpha=0.3, which="both")
    ax.get_xlim()  # settles the automatic x limits before the tick labels are chosen
    readable_log_axis(ax.xaxis)
    readable_log_axis(ax.yaxis)


def _speed_accuracy_headline(study, runs) -> str:
    """speed_accuracy.png's title: the scenario, the runs and failures, the finest run and the
    fastest one with its deviation."""
    import math

    reference = study.reference
    failures = [r for r in runs if not r.ok]
    done = [r for r in runs if r.ok]
    counts = f"{len(runs) + 1} runs" + (f", {len(failures)} failed (crosses at the right)" if failures else "")
    best = min(done, key=lambda r: r.wall_seconds) if done else None
    headline = (f"{shown_name(study.scenario, 'study')}: speed against accuracy of the needle insertion, {counts}\n"
                f"deviations from the finest run {literal(reference.label)}: {reference.particles} particles, "
                f"{reference.wall_seconds:.2f} s")
    if best is not None:
        headline += (f"; fastest run: {literal(best.label)}, {best.wall_seconds:.2f} s, "
                     f"deviation {best.deviations.get('deviation_mm', math.nan):.3g} mm")
    return headline
