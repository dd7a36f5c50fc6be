"""Figures of needle runs: insertion.png (simulate) and plan.png (plan), with the deformed
tissue, the needle, the tip paths and zooms on each run's exit error."""


from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from .plot_elements import (
    CMAP,
    DEFORMED,
    SAVED_DPI,
    deformed_loops,
    draw_clamps,
    draw_outline,
    draw_regions,
    frame,
    label_mm,
    legend_below,
    literal,
    magnitude_norm,
    pyplot,
    title_above,
)
from .plots import save, shown_name

PARTICLES_LABEL = "particles, coloured by |u| (the bar)"


def _needle_body(geometry, center, rotation: float) -> np.ndarray:
    """The needle's arc (80, 2): from the tip back over `arc` rad along the circle."""
    back = np.linspace(rotation, max(rotation - geometry.arc, rotation - 2 * np.pi), 80)
    angles = geometry.start_angle + geometry.sense * back
    return np.asarray(center) + geometry.radius * np.column_stack([np.cos(angles), np.sin(angles)])


def _tip_path(run, step: int | None = None) -> np.ndarray:
    """Tip positions (k, 2), spatial: the entry, each step's tip, and the exit when reached."""
    step = len(run.steps) if step is None else step
    tips = [np.asarray(run.geometry.entry, dtype=float)] + [s.tip_spatial for s in run.steps[:step]]
    if step == len(run.steps) and run.achieved_exit_def is not None:
        tips.append(np.asarray(run.achieved_exit_def))
    return np.asarray(tips, dtype=float).reshape(-1, 2)


def _state(run, step: int) -> tuple[np.ndarray, float]:
    """Needle centre and rotation after `step` steps (step 0: at entry)."""
    if step == 0:
        return np.asarray(run.center_after(0)), 0.0
    record = run.steps[step - 1]
    return np.asarray(record.center), float(record.rotation)


def _interpolant(model, displacement: np.ndarray):
    """u(X) at any reference points from the particle displacements u(X_I): the RK
    coefficients d solve u(X_I) = sum_J N_J(X_I) d_J (a sparse, square system)."""
    from scipy.sparse.linalg import splu

    values = model.particle_shape_values().tocsc()  # (NP, NP)
    coefficients = splu(values).solve(np.ascontiguousarray(displacement, dtype=float))  # (NP, 2)
    return lambda points: model.shape_functions_at(points).values @ coefficients


def _boundary_near(domain, point: np.ndarray, reach: float) -> list[np.ndarray]:
    """Pieces (k, 2) of the reference outline within `reach` of `point`, densely sampled."""
    from .plot_elements import outline_loops

    pieces = []
    for loop in outline_loops(domain):
        closed = np.vstack([loop, loop[:1]])
        for a, b in itertools.pairwise(closed):
            edge = b - a
            length = float(np.hypot(*edge))
            middle = float((point - a) @ edge) / length**2  # the nearest edge point's parameter
            low, high = max(middle - reach / length, 0.0), min(middle + reach / length, 1.0)
            if low >= high:
                continue
            line = a + np.linspace(low, high, 201)[:, None] * edge  # (201, 2)
            line = line[np.linalg.norm(line - point, axis=1) <= reach]
            if len(line) > 1:
                pieces.append(line)
    return pieces


def _exit_zoom(ax, run, norm, colour: str, who: str, marker: str, desired_colour: str | None = None,
               outline: dict | None = None, outline_label: str = "tissue outline, deformed",
               exit_labels: tuple[str, str] | None = None) -> None:
    """The exit seen closely, in mm from the run's desired exit (deformed): the tissue there
    (the RK interpolant, not a polyline), the tip's last path, the desired and achieved exit
    (legend entries `exit_labels`, where no other panel draws them) and the error between
    them. The window is sized to the error."""
    desired, achieved = np.asarray(run.desired_exit_def), np.asarray(run.achieved_exit_def)
    error = float(run.exit_error_mm)
    half = max(1.3 * error, 2e-3)
    centre = 0.5 * (desired + achieved) - desired
    particles = run.model.particles
    displacement = run.displacements[-1]
    moved = particles + displacement - desired
    near = np.all(np.abs(moved - centre) <= 1.5 * half, axis=1)
    ax.scatter(*moved[near].T, s=40, c=np.linalg.norm(displacement[near], axis=1), cmap=CMAP, norm=norm,
               label=PARTICLES_LABEL)  # one legend entry with the main panel's: a dot here is a particle
    pieces = _boundary_near(run.scenario.tissue.domain, np.asarray(run.desired_exit), 6 * half + 1e-9)
    interpolant = _interpolant(run.model, displacement) if pieces else None
    for k, piece in enumerate(pieces):
        edge = piece + interpolant(piece) - desired
        ax.plot(*edge.T, **(outline or DEFORMED), label=outline_label if k == 0 else None)
    tips = _tip_path(run) - desired
    ax.plot(*tips.T, ".-", color=colour, lw=1.2, ms=4)
    ax.plot([0.0, achieved[0] - desired[0]], [0.0, achieved[1] - desired[1]], ":", color=colour, lw=1.2)
    desired_label, achieved_label = exit_labels or (None, None)
    ax.plot(0.0, 0.0, "x", color=desired_colour or colour, ms=11, mew=2.5, label=desired_label)
    ax.plot(*(achieved - desired), marker, mfc="none", mec=colour, ms=11, mew=1.8, label=achieved_label)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=4))  # long labels of a narrow zoom (0.004 mm) side by side
    ax.tick_params(labelsize=7)
    ax.set_xlabel("x - x desired exit (mm)", fontsize=8)
    ax.set_ylabel("y - y desired exit (mm)", fontsize=8)
    ax.set_title(f"{who} exit: error {error:.3g} mm\n(zoom, {2 * half:.2g} mm wide)", fontsize=9, color=colour)


def _needle_frame(runs_and_steps) -> np.ndarray:
    """Points the needle views must hold: needle bodies, tip paths and exits."""
    points = []
    for run, step in runs_and_steps:
        center, rotation = _state(run, step)
        points += [_needle_body(run.geometry, center, rotation), _tip_path(run, step),
                   np.asarray(run.desired_exit).reshape(1, 2)]
        if run.desired_exit_def is not None:
            points.append(np.asarray(run.desired_exit_def).reshape(1, 2))
        # holes and the outline's corners near the needle belong in the view: they shape the
        # tissue around it (a wound's bottom below the needle)
        domain = run.scenario.tissue.domain
        for hole in getattr(domain, "holes", ()):
            gap = np.linalg.norm(np.asarray(hole) - run.geometry.center, axis=1).min()
            if gap < 1.5 * run.geometry.radius:
                points.append(np.asarray(hole))
        corners = np.asarray(getattr(domain, "outline", np.empty((0, 2))))
        points.append(corners[np.linalg.norm(corners - run.geometry.center, axis=1) < 1.5 * run.geometry.radius])
    return np.vstack(points)


def plot_insertion(path: str | Path, result, steps: list[int] | None = None, estimate_mm: float | None = None,
                   center_path: str | None = None):
    """insertion.png of `stitchplan simulate`: the deformed tissue, needle and tip path at the
    chosen steps (default: the last), one colour scale for all, and a zoom on the exit.
    `estimate_mm`: the discretization error estimate of the exit point, for the title;
    `center_path`: the trajectory file a replay's centre followed (`--center-path`)."""
    plt = pyplot()
    last = len(result.steps)
    # steps past the run's end draw its last step, once (the command's note says so)
    chosen = list(dict.fromkeys(min(max(int(s), 0), last) for s in (steps or [last])))
    n = len(chosen)
    fig = plt.figure(figsize=(4.4 * n + 5.0, 5.0), dpi=SAVED_DPI)
    grid = fig.add_gridspec(1, n + 2, width_ratios=[1.0] * n + [0.12, 0.85], wspace=0.12)
    panels = [fig.add_subplot(grid[0, 0])]
    panels += [fig.add_subplot(grid[0, k], sharex=panels[0], sharey=panels[0]) for k in range(1, n)]
    zoom = fig.add_subplot(grid[0, n + 1])  # column n: room for the zoom's axis labels
    axes = [[*panels, zoom]]
    particles, geometry, tissue = result.model.particles, result.geometry, result.scenario.tissue
    norm = magnitude_norm(*(result.displacements[s] for s in chosen), result.displacements[-1])
    view = _needle_frame([(result, s) for s in chosen])
    for ax, step in zip(panels, chosen):
        displacement = result.displacements[step]
        draw_outline(ax, tissue.domain, particles, displacement)
        draw_regions(ax, tissue)
        dots = ax.scatter(*(particles + displacement).T, s=6, c=np.linalg.norm(displacement, axis=1),
                          cmap=CMAP, norm=norm, zorder=2, label=PARTICLES_LABEL)
        center, rotation = _state(result, step)
        ax.plot(*_needle_body(geometry, center, rotation).T, "-", color="crimson", lw=2.2, label="needle")
        tips = _tip_path(result, step)
        ax.plot(*tips.T, ".-", color="orange", ms=3, lw=1, label="tip path")
        ax.plot(*result.desired_exit, "x", color="0.4", ms=8, mew=2, label="desired exit, at rest")
        if step == last:
            ax.plot(*result.desired_exit_def, "x", color="blue", ms=10, mew=2.5, label="desired exit, deformed")
            ax.plot(*result.achieved_exit_def, "o", mfc="none", mec="crimson", ms=10, mew=1.8,
                    label="achieved exit")
        frame(ax, view, margin=0.08)
        draw_clamps(ax, tissue, 0.1 * geometry.radius)
        ax.set_xlabel("x (mm)")
        if ax is panels[0]:
            ax.set_ylabel("y (mm)")
        else:
            ax.tick_params(labelleft=False)
        ax.set_title(f"step {step} of {last}, needle rotated {rotation:.2f} rad", fontsize=9)
    # the exits' entries come from the last step's panel, or the zoom where no panel shows it
    _exit_zoom(zoom, result, norm, "crimson", "simulated", "o", desired_colour="blue",
               exit_labels=("desired exit, deformed", "achieved exit"))
    fig.colorbar(dots, ax=list(axes[0]), label="|u| displacement (mm)", shrink=0.8, pad=0.02)
    how = "without planning" if center_path is None else f"along the centre path of {literal(Path(center_path).name)}"
    title_above(fig, axes[0], f"{shown_name(result.scenario, 'simulate')}: needle insertion {how}\n"
                f"exit error {result.exit_error_mm:.3g} mm (material point "
                f"{result.exit_error_material_mm:.3g} mm), {last} steps, "
                f"{result.model.n_particles} particles"
                + (f"\ndiscretization error of the exit about {estimate_mm:.2g} mm" if estimate_mm is not None
                   else ""))
    legend_below(fig, panels + [zoom], columns=5)
    save(fig, path)
    return fig


# --- plan -----------------------------------------------------------------------------------


def _exit_direction(run) -> np.ndarray:
    """Unit vector of the tip's last move: out of the tissue at the exit."""
    tips = _tip_path(run)
    move = tips[-1] - tips[-2]
    length = float(np.hypot(*move))
    return move / length if length > 0 else np.array([-1.0, 0.0])


def _label_offsets(runs, outward: np.ndarray) -> dict[str, np.ndarray]:
    """Where each run's exit-error label goes, in points from its desired exit: outside the
    tissue (along `outward`) and, for two runs, apart along the boundary, the run whose
    desired exit lies further along the boundary on that side."""
    tangent = np.array([-outward[1], outward[0]])
    order = np.argsort([np.asarray(run.desired_exit_def) @ tangent for run, *_ in runs])
    sides = np.linspace(-1.0, 1.0, len(runs)) if len(runs) > 1 else np.zeros(1)
    if abs(tangent[1]) > abs(tangent[0]):  # an exit on a side edge: one label above the other
        return {runs[k][1]: 30.0 * outward + sides[rank] * 16.0 * tangent for rank, k in enumerate(order)}
    # on the top or bottom edge: side by side they would need more width than the axes have,
    # so each leans to its own side, the second one row further out
    return {runs[k][1]: (30.0 + 40.0 * rank) * outward + sides[rank] * 8.0 * tangent
            for rank, k in enumerate(order)}


def _alignment(offset: np.ndarray) -> dict[str, str]:
    """A label's anchor: the side of the text that faces the point it is `offset` from."""
    return {"ha": "right" if offset[0] < -5 else "left" if offset[0] > 5 else "center",
            "va": "top" if offset[1] < -5 else "bottom" if offset[1] > 5 else "center"}


def _label_box(offset: np.ndarray, width: float = 110.0, height: float = 34.0) -> np.ndarray:
    """Corners (4, 2), in points from the labelled point, of a two-line label at `offset`."""
    anchor = _alignment(offset)
    x0 = offset[0] - {"right": width, "left": 0.0, "center": width / 2}[anchor["ha"]]
    y0 = offset[1] - {"top": height, "bottom": 0.0, "center": height / 2}[anchor["va"]]
    return np.array([[x0, y0], [x0 + width, y0], [x0, y0 + height], [x0 + width, y0 + height]])


# each run's deformed outline: the planned run's as every figure draws it, the unplanned one's dotted
RUN_OUTLINES = {"planned": DEFORMED, "unplanned": {"color": "darkorange", "ls": ":", "lw": 1.5}}


def plot_plan(path: str | Path, result):
    """plan.png of `stitchplan plan`: planned and unplanned paths over the planned run's
    deformed tissue, each run's desired exit with its own error, zooms on both exits, and the
    centre trajectory O(t) (thesis figures 5.9-5.15)."""
    plt = pyplot()
    planned, unplanned = result.planned, result.unplanned
    runs = [(planned, "planned", "crimson", "o")]
    if unplanned is not None:
        runs.append((unplanned, "unplanned", "darkorange", "s"))
    fig = plt.figure(figsize=(15.0, 6.4), dpi=SAVED_DPI)
    grid = fig.add_gridspec(2, 3, width_ratios=[2.1, 1.0, 1.5], wspace=0.35, hspace=0.45)
    main = fig.add_subplot(grid[:, 0])
    zooms = [fig.add_subplot(grid[k, 1]) for k in range(len(runs))]
    trajectory = fig.add_subplot(grid[:, 2])
    norm = magnitude_norm(*(run.displacements[-1] for run, *_ in runs))
    dots = _draw_planned_tissue(main, planned, unplanned, norm)
    _draw_runs_over_tissue(fig, main, runs)
    fig.colorbar(dots, ax=main, label="|u| displacement (mm): planned run; zooms: each run", shrink=0.8,
                 pad=0.02)
    for ax, (run, who, colour, marker) in zip(zooms, runs):
        _exit_zoom(ax, run, norm, colour, who, marker, outline=RUN_OUTLINES[who],
                   outline_label=f"tissue outline, {who} run")
    _draw_center_trajectory(trajectory, result)
    title_above(fig, [main, *zooms, trajectory], _plan_headline(result), fontsize=11)
    # one legend under all panels, the trajectory's curves in it: two legends side by side ran into each other
    legend_below(fig, [main, *zooms, trajectory], columns=5)
    save(fig, path)
    return fig


def _draw_planned_tissue(ax, planned, unplanned, norm):
    """The planned run's deformed tissue (its outline, regions and particles coloured by |u|)
    and the unplanned run's outline; returns the particles' scatter, for the colour bar."""
    tissue, particles = planned.scenario.tissue, planned.model.particles
    displacement = planned.displacements[-1]
    draw_outline(ax, tissue.domain, particles, displacement, deformed_label="tissue outline, planned run")
    draw_regions(ax, tissue)
    if unplanned is not None:
        for k, loop in enumerate(deformed_loops(tissue.domain, particles, unplanned.displacements[-1])):
            ax.plot(*loop.T, **RUN_OUTLINES["unplanned"], label="tissue outline, unplanned run" if k == 0 else None)
    return ax.scatter(*(particles + displacement).T, s=6, c=np.linalg.norm(displacement, axis=1),
                      cmap=CMAP, norm=norm, zorder=2, label=PARTICLES_LABEL)


def _draw_runs_over_tissue(fig, ax, runs) -> None:
    """Each run's tip path, needle, desired and achieved exit and its exit error's label, the
    desired exit at rest, then the frame widened to hold the labels, and the clamps."""
    planned = runs[0][0]
    offsets = _label_offsets(runs, _exit_direction(planned))
    for run, who, colour, marker in runs:
        style = "-" if who == "planned" else "--"
        ax.plot(*_tip_path(run).T, style, color=colour, lw=2, label=f"{who} tip path")
        center, rotation = _state(run, len(run.steps))
        ax.plot(*_needle_body(run.geometry, center, rotation).T, style, color=colour, lw=1, alpha=0.5,
                label=f"{who} run: needle at its last step")
        ax.plot(*run.desired_exit_def, "x", color=colour, ms=10, mew=2.5, label=f"{who} run: desired exit (deformed)")
        ax.plot(*run.achieved_exit_def, marker, mfc="none", mec=colour, ms=10, mew=1.8,
                label=f"{who} run: achieved exit")
        offset = offsets[who]
        ax.annotate(f"{who} exit error\n{run.exit_error_mm:.3g} mm", run.desired_exit_def, xytext=offset,
                    textcoords="offset points", fontsize=8, color=colour, zorder=6, **_alignment(offset),
                    bbox={"boxstyle": "round", "fc": "white", "ec": colour, "alpha": 0.85},
                    arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.8})
    ax.plot(*planned.desired_exit, "+", color="0.4", ms=9, mew=1.5, label="desired exit, at rest")
    _frame_with_labels(fig, ax, runs, offsets)
    draw_clamps(ax, planned.scenario.tissue, 0.1 * planned.geometry.radius)
    label_mm(ax)
    ax.set_title("tip paths over the planned run's deformed tissue", fontsize=9)


def _frame_with_labels(fig, ax, runs, offsets: dict[str, np.ndarray]) -> None:
    """Frame the needles, tip paths and exits, then widen the frame until the exit-error
    labels (sized in points, so their size in mm follows the frame) fit inside."""
    view = _needle_frame([(run, len(run.steps)) for run, *_ in runs])
    frame(ax, view, margin=0.08)
    for _ in range(2):
        ax.apply_aspect()
        points_per_mm = ax.get_window_extent().width / np.ptp(ax.get_xlim()) * 72.0 / fig.dpi
        labels = [np.asarray(run.desired_exit_def) + corner / points_per_mm
                  for run, who, *_ in runs for corner in _label_box(offsets[who])]
        frame(ax, np.vstack([view, *labels]), margin=0.08)


def _draw_center_trajectory(ax, result) -> None:
    """The planned needle centre's offset from the entry centre against the needle rotation."""
    planned = result.planned
    centers = result.center_trajectory
    rotation = np.arange(len(centers)) * planned.geometry.step
    # colours of their own: matplotlib's second default orange is the unplanned run's in the shared legend
    ax.plot(rotation, centers[:, 0] - centers[0, 0], color="tab:blue", label="O_x(t) - O_x(0)")
    ax.plot(rotation, centers[:, 1] - centers[0, 1], "--", color="tab:green", label="O_y(t) - O_y(0)")
    ax.set_xlabel("needle rotation (rad)")
    ax.set_ylabel("centre offset from the entry centre (mm)")
    lean = planned.geometry.tilt  # O(0) leaning from the orthogonal entry's centre (planner.aim_entry_tilt)
    ax.set_title("planned needle-centre trajectory O(t)" + (
        f"\nthe needle leaning {lean:.3g} rad ({math.degrees(lean):.2g}°) at entry" if lean else ""), fontsize=9)
    ax.grid(alpha=0.3)


def _plan_headline(result) -> str:
    """plan.png's title: the scenario, both runs' exit errors, the steps and particles, across
    a wound both runs' bites, and the accuracy checks that ran (the discretization error
    estimate, the refined replay)."""
    planned, unplanned = result.planned, result.unplanned
    headline = f"exit error {planned.exit_error_mm:.3g} mm planned"
    verification = getattr(result, "verification", None)
    if verification is not None and verification.aimed_by != "none":  # the planning model's bias offset
        headline += " (aimed for the refined model)"
    if unplanned is not None:
        headline += f" vs {unplanned.exit_error_mm:.3g} mm unplanned"
    headline += f" ({len(planned.steps)} steps, {planned.model.n_particles} particles)"
    checks = []
    if planned.bites:  # a stitch across a wound: the bites a surgeon sees
        checks.append(f"bites (entry / exit side) {planned.bites['entry_side_mm']:.3f} / "
                      f"{planned.bites['exit_side_mm']:.3f} mm planned"
                      + (f" vs {unplanned.bites['entry_side_mm']:.3f} / {unplanned.bites['exit_side_mm']:.3f} mm "
                         "unplanned" if unplanned is not None and unplanned.bites else ""))
    estimate = getattr(result, "estimate", None)
    if estimate is not None:
        checks.append(f"discretization error of the exit about {estimate.estimate_mm:.2g} mm")
    if verification is not None and verification.result is not None:
        bites = verification.result.bites  # a stitch across a wound
        checks.append(f"trajectory replayed on a refined model (spacing {verification.spacing_mm:.3g} mm): "
                      f"exit error {verification.result.exit_error_mm:.3g} mm"
                      + (f", bites differ by {bites['difference_mm']:+.2g} mm" if bites else ""))
    return f"{shown_name(planned.scenario, 'plan')}: {headline}" + "".join(f"\n{c}" for c in checks)


# --- study ----------------------------------------------------------------------------------
