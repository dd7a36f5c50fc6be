"""The figures of `stitchplan calibrate`: cost_surface.png and marker_residuals.png of the
material fit (appendix A.2), forces.png of the needle fit (section 5.2). Like `plots`, each
returns its (closed) figure; the shared drawing pieces live in `plot_elements`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .plot_elements import (
    CMAP,
    SAVED_DPI,
    draw_clamps,
    draw_loads,
    draw_outline,
    draw_regions,
    frame,
    label_mm,
    legend_below,
    literal,
    pyplot,
    readable_log_axis,
    title_above,
)
from .plots import save


def plot_cost_surface(path: str | Path, lame_lambda: np.ndarray, lame_mu: np.ndarray,
                      cost: np.ndarray, grid_best: tuple[float, float], optimum: tuple[float, float],
                      refinement: np.ndarray | None = None, log_axes: bool = True, name: str = "",
                      residual: tuple[float, float] | None = None,
                      uncertainty: tuple[float | None, float | None] = (None, None), identifiable: bool = True,
                      note: str = ""):
    """Marker misfit f(lambda, mu) (eq. A.3) on the calibration grid, cost (n_lambda, n_mu) in
    mm^2 with nan where the solve failed; the grid's best point, the least-squares path and
    the optimum marked. `residual`: mean and standard deviation of the marker distances at the
    optimum (mm), shown in the title with the fitted moduli and their `uncertainty`, and
    whether the moduli are `identifiable` (the command's summary line flags them alike);
    `note`: a further title line (the regions whose moduli were fitted too)."""
    from matplotlib import patheffects
    from matplotlib.colors import LogNorm

    def edges(centres: np.ndarray) -> np.ndarray:
        """Cell edges halfway between grid points (geometric halfway on log axes)."""
        t = np.log(centres) if log_axes else centres
        middle = 0.5 * (t[1:] + t[:-1])
        e = np.concatenate([[2 * t[0] - middle[0]], middle, [2 * t[-1] - middle[-1]]])
        return np.exp(e) if log_axes else e

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 5.4), dpi=SAVED_DPI)
    masked = np.ma.masked_invalid(cost.T)  # rows: mu, columns: lambda
    positive = masked.compressed()
    positive = positive[positive > 0]
    norm = LogNorm(vmin=positive.min(), vmax=positive.max()) if len(positive) > 1 else None
    mesh = ax.pcolormesh(edges(lame_lambda), edges(lame_mu), masked, shading="flat", cmap=CMAP, norm=norm)
    bar = fig.colorbar(mesh, ax=ax, label="misfit f = sum |p - q|² (mm²)")
    if norm is not None:
        readable_log_axis(bar.ax.yaxis)
    outlined = [patheffects.withStroke(linewidth=3.0, foreground="black")]
    failed = np.argwhere(~np.isfinite(cost))
    if len(failed):
        ax.plot(lame_lambda[failed[:, 0]], lame_mu[failed[:, 1]], "x", color="0.4",
                label="not solved (too soft for the loads)")
    if refinement is not None and len(refinement):
        ax.plot(refinement[:, 0], refinement[:, 1], ".-", color="white", lw=1.0, ms=4,
                path_effects=outlined, label="least-squares evaluations")
    ax.plot(*grid_best, "s", mfc="none", mec="white", mew=1.5, ms=11, path_effects=outlined,
            label="grid best (start)")
    ax.plot(*optimum, "*", color="red", mec="black", ms=15, label="fitted")
    if log_axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        readable_log_axis(ax.xaxis)
        readable_log_axis(ax.yaxis)
    ax.set_xlabel("lame_lambda (MPa)")
    ax.set_ylabel("lame_mu (MPa)")

    def value(x: float, u: float | None) -> str:
        return f"{x:.4g}" + (f" ± {u:.2g}" if u is not None else "")

    title = (f"{literal(name) or 'calibrate material'}: marker misfit over the moduli\nfitted lambda = "
             f"{value(optimum[0], uncertainty[0])} MPa, mu = {value(optimum[1], uncertainty[1])} MPa")
    if note:
        title += f"\n{note}"
    if residual is not None:
        title += f"\nmarker residual {residual[0]:.3g} ± {residual[1]:.2g} mm"
    if not identifiable:
        title += "\nNOT identifiable: see the fitted YAML's warnings"
    ax.set_title(title, fontsize=10, color="black" if identifiable else "darkred")
    legend_below(fig, [ax], columns=2)
    save(fig, path)
    return fig


def plot_marker_residuals(path: str | Path, tissue, experiments, simulated: list[np.ndarray],
                          name: str = ""):
    """One panel per experiment: the tissue with its clamps and loads, measured (p) and
    simulated (q) marker positions with the residual p - q drawn as arrows, magnified (the
    same factor in every panel) so the largest is ~8 % of the tissue size."""
    plt = pyplot()
    n = len(experiments)
    columns = min(n, 3)
    rows = -(-n // columns)
    width, height = tissue.domain.size
    size = max(width, height)
    panel_height = 5.0 * max(height / width, 0.5)
    fig, axes = plt.subplots(rows, columns, figsize=(5.2 * columns, panel_height * rows + 1.0), dpi=SAVED_DPI,
                             squeeze=False)
    residuals = [p - q for p, q in zip((e.measured for e in experiments), simulated)]
    distances = np.concatenate([np.linalg.norm(r, axis=1) for r in residuals])
    largest = float(distances.max()) if len(distances) else 0.0
    magnify = 0.08 * size / largest if largest > 0 else 1.0
    used, extents = [], []
    for k, ax in enumerate(axes.ravel()):
        if k >= n:
            ax.axis("off")
            continue
        used.append(ax)
        experiment, q = experiments[k], simulated[k]
        p = experiment.measured
        draw_outline(ax, tissue.domain)
        draw_regions(ax, tissue)
        ends = draw_loads(ax, experiment.loads, tissue.domain, 0.15 * size)
        ax.plot(*experiment.markers.T, ".", color="0.7", ms=4, label="marker at rest")
        ax.plot(*q.T, "o", mfc="none", mec="tab:blue", ms=6, label="simulated q (fitted moduli)")
        ax.plot(*p.T, ".", color="black", ms=4, label="measured p")
        ax.quiver(*q.T, *(p - q).T, angles="xy", scale_units="xy", scale=1.0 / magnify, color="tab:orange",
                  width=0.004, label=f"residual p - q, drawn {magnify:.3g}x")
        rms = float(np.sqrt(np.mean(np.sum((p - q) ** 2, axis=1))))
        extents.append(np.vstack([[[0.0, 0.0], [width, height]], ends, p, q]))
        label_mm(ax)
        ax.set_title(f"{literal(experiment.name) or f'experiments[{k}]'}: rms residual {rms:.3g} mm", fontsize=9)
    for ax in used:  # the same frame in every panel
        frame(ax, np.vstack(extents), margin=0.06)
        draw_clamps(ax, tissue, 0.025 * size)
    title_above(fig, used, f"{literal(name) or 'calibrate material'}: marker residuals at the fitted moduli, "
                f"mean {distances.mean():.3g} mm, largest {largest:.3g} mm")
    legend_below(fig, used, columns=4)
    save(fig, path)
    return fig


def plot_needle_forces(path: str | Path, result):
    """forces.png of `calibrate needle` (section 5.2). Left: both recordings (angle, force)
    and the background line. Right: tissue force minus background against inserted length,
    with the fitted cutting force + friction x length."""
    plt = pyplot()
    air, tissue = result.air, result.tissue
    background = result.background
    fig, (left, right) = plt.subplots(1, 2, figsize=(11.0, 4.8), dpi=SAVED_DPI)
    angles = np.linspace(min(air[0, 0], tissue[0, 0]), max(air[-1, 0], tissue[-1, 0]), 50)
    left.plot(*air.T, ".", ms=3, color="0.5", label="needle in air")
    left.plot(*tissue.T, ".", ms=3, color="tab:blue", label="needle into tissue")
    left.plot(angles, background.intercept + background.slope * angles, "-", color="black",
              label=f"background {background.intercept:.3g} N + {background.slope:.3g} N/rad x angle")
    left.set_xlabel("needle rotation (rad)")
    left.set_ylabel("force (N)")
    left.set_title("force recordings", fontsize=9)
    length = np.linspace(0.0, result.inserted_length.max(), 50)
    right.plot(result.inserted_length, result.corrected, ".", ms=3, color="tab:blue",
               label="into tissue minus background")
    right.plot(length, result.cutting_force + result.friction * length, "-", color="tab:red",
               label=f"fit {result.cutting_force:.4g} N + {result.friction:.4g} N/mm x length")
    right.set_xlabel(f"inserted length = radius {result.radius:g} mm x angle (mm)")
    right.set_ylabel("force minus background (N)")
    right.set_title("cutting force (intercept) and friction (slope)", fontsize=9)
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8, frameon=False)
    u = result.standard_uncertainty
    sources = " / ".join(literal(Path(s).name) for s in result.sources if s) or "recordings"
    fig.suptitle(f"calibrate needle ({sources}): friction {result.friction:.4g} ± {u[0]:.2g} N/mm, "
                 f"cutting force {result.cutting_force:.4g} ± {u[1]:.2g} N "
                 f"(R² {result.tissue_fit.r_squared:.4f})", fontsize=10)
    save(fig, path)
    return fig
