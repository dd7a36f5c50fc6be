"""PNG figures: deformed tissue, needle paths, trajectories, calibration and studies."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .files import atomic_path


def _figure(width: float = 6.0, height: float = 6.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(width, height))


def save(fig, path: str | Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as temporary:
        fig.savefig(temporary, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)


def plot_deformed(path: str | Path, particles: np.ndarray, displacements: np.ndarray,
                  title: str = "", ax=None, fig=None) -> None:
    """Particles in the reference (grey) and deformed (coloured by |u|) configurations."""
    if ax is None:
        fig, ax = _figure()
    magnitude = np.linalg.norm(displacements, axis=1)
    deformed = particles + displacements
    ax.scatter(particles[:, 0], particles[:, 1], s=3, c="0.85", label="reference")
    points = ax.scatter(deformed[:, 0], deformed[:, 1], s=5, c=magnitude, cmap="viridis",
                        label="deformed")
    fig.colorbar(points, ax=ax, label="|u| (mm)", shrink=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    save(fig, path)


def plot_cost_surface(path: str | Path, lame_lambda: np.ndarray, lame_mu: np.ndarray,
                      cost: np.ndarray, grid_best: tuple[float, float], optimum: tuple[float, float],
                      refinement: np.ndarray | None = None, log_axes: bool = True) -> None:
    """Marker misfit f(lambda, mu) (eq. A.3) on the calibration grid, cost (n_lambda, n_mu) in
    mm^2 with nan where the solve failed; the grid's best point, the least-squares path and
    the optimum marked."""
    from matplotlib.colors import LogNorm

    def edges(centres: np.ndarray) -> np.ndarray:
        """Cell edges halfway between grid points (geometric halfway on log axes)."""
        t = np.log(centres) if log_axes else centres
        middle = 0.5 * (t[1:] + t[:-1])
        e = np.concatenate([[2 * t[0] - middle[0]], middle, [2 * t[-1] - middle[-1]]])
        return np.exp(e) if log_axes else e

    fig, ax = _figure(6.5, 5.0)
    masked = np.ma.masked_invalid(cost.T)  # rows: mu, columns: lambda
    positive = masked.compressed()
    positive = positive[positive > 0]
    norm = LogNorm(vmin=positive.min(), vmax=positive.max()) if len(positive) > 1 else None
    mesh = ax.pcolormesh(edges(lame_lambda), edges(lame_mu), masked, shading="flat", cmap="viridis",
                         norm=norm)
    fig.colorbar(mesh, ax=ax, label="f = sum |p - q|^2 (mm^2)")
    failed = np.argwhere(~np.isfinite(cost))
    if len(failed):
        ax.plot(lame_lambda[failed[:, 0]], lame_mu[failed[:, 1]], "x", color="0.4",
                label="not solved (too soft for the loads)")
    if refinement is not None and len(refinement):
        ax.plot(refinement[:, 0], refinement[:, 1], ".-", color="white", lw=0.8, ms=3,
                label="least-squares evaluations")
    ax.plot(*grid_best, "s", mfc="none", mec="white", ms=10, label="grid best")
    ax.plot(*optimum, "*", color="red", ms=14, label="fitted")
    if log_axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel("lame_lambda (MPa)")
    ax.set_ylabel("lame_mu (MPa)")
    ax.set_title(f"marker misfit: fitted lambda = {optimum[0]:.4g}, mu = {optimum[1]:.4g} MPa")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8, frameon=False)
    save(fig, path)


def plot_marker_residuals(path: str | Path, size: tuple[float, float], markers: list[np.ndarray],
                          measured: list[np.ndarray], simulated: list[np.ndarray],
                          segments: list[list], titles: list[str]) -> None:
    """One panel per experiment: measured (p) and simulated (q) marker positions with the
    residual p - q drawn as arrows, magnified so the largest is ~8 % of the tissue size."""
    import matplotlib.pyplot as plt

    n = len(markers)
    columns = min(n, 3)
    rows = -(-n // columns)
    width, height = size
    panel_height = 5.0 * max(height / width, 0.5)
    fig, axes = plt.subplots(rows, columns, figsize=(5.0 * columns, panel_height * rows), squeeze=False)
    largest = max(float(np.linalg.norm(p - q, axis=1).max()) for p, q in zip(measured, simulated))
    magnify = 0.08 * max(size) / largest if largest > 0 else 1.0
    for k, ax in enumerate(axes.ravel()):
        if k >= n:
            ax.axis("off")
            continue
        p, q = measured[k], simulated[k]
        ax.add_patch(plt.Rectangle((0, 0), width, height, fill=False, ec="0.6", lw=0.8))
        for start, end in segments[k]:
            ax.plot([start[0], end[0]], [start[1], end[1]], "-", color="tab:red", lw=3)
        ax.plot(markers[k][:, 0], markers[k][:, 1], ".", color="0.75", ms=4, label="rest")
        ax.plot(q[:, 0], q[:, 1], "o", mfc="none", mec="tab:blue", ms=6, label="simulated q")
        ax.plot(p[:, 0], p[:, 1], ".", color="black", ms=4, label="measured p")
        ax.quiver(q[:, 0], q[:, 1], p[:, 0] - q[:, 0], p[:, 1] - q[:, 1], angles="xy",
                  scale_units="xy", scale=1.0 / magnify, color="tab:orange", width=0.004,
                  label=f"p - q (x {magnify:.3g})")
        rms = float(np.sqrt(np.mean(np.sum((p - q) ** 2, axis=1))))
        ax.set_title(f"{titles[k]}: rms residual {rms:.3g} mm", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=4, fontsize=7, frameon=False)
    save(fig, path)


def plot_needle_forces(path: str | Path, air: np.ndarray, tissue: np.ndarray, background_offset: float,
                       background_slope: float, inserted_length: np.ndarray, corrected: np.ndarray,
                       friction: float, cutting_force: float) -> None:
    """Left: both recordings (angle, force) and the background line. Right: tissue force
    minus background against inserted length, with the fitted cutting force + friction x length."""
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11.0, 4.5))
    angles = np.linspace(min(air[0, 0], tissue[0, 0]), max(air[-1, 0], tissue[-1, 0]), 50)
    left.plot(air[:, 0], air[:, 1], ".", ms=3, color="0.5", label="in air")
    left.plot(tissue[:, 0], tissue[:, 1], ".", ms=3, color="tab:blue", label="into tissue")
    left.plot(angles, background_offset + background_slope * angles, "-", color="black",
              label=f"background {background_offset:.3g} + {background_slope:.3g} angle")
    left.set_xlabel("needle rotation (rad)")
    left.set_ylabel("force (N)")
    left.legend(fontsize=8)
    left.set_title("recordings")
    length = np.linspace(0.0, inserted_length.max(), 50)
    right.plot(inserted_length, corrected, ".", ms=3, color="tab:blue", label="tissue - background")
    right.plot(length, cutting_force + friction * length, "-", color="tab:red",
               label=f"{cutting_force:.4g} N + {friction:.4g} N/mm x length")
    right.set_xlabel("inserted length radius x angle (mm)")
    right.set_ylabel("force (N)")
    right.legend(fontsize=8)
    right.set_title("cutting force (intercept) and friction (slope)")
    fig.tight_layout()
    save(fig, path)


def _needle_arc(ax, center, radius, start_angle, sense, rotation, arc, **style):
    """The needle body: the arc from the tip back over `arc` rad (clipped at the start)."""
    back = np.linspace(rotation, max(rotation - arc, rotation - 2 * np.pi), 80)
    angles = start_angle + sense * back
    ax.plot(center[0] + radius * np.cos(angles), center[1] + radius * np.sin(angles), **style)


def plot_insertion(path: str | Path, result, steps: list[int] | None = None, ax=None, fig=None,
                   title: str | None = None) -> None:
    """Deformed particles, needle and tip path at the chosen steps (default: the last)."""
    chosen = steps or [len(result.steps)]
    chosen = [min(max(int(s), 0), len(result.steps)) for s in chosen]
    if ax is None:
        fig, _ = _figure(5.5 * len(chosen), 5.5)
        fig.clf()
        axes = [fig.add_subplot(1, len(chosen), i + 1) for i in range(len(chosen))]
    else:
        axes = [ax]
    geometry = result.geometry
    particles = result.model.particles
    for ax, step in zip(axes, chosen):
        displacement = result.displacements[step]
        magnitude = np.linalg.norm(displacement, axis=1)
        deformed = particles + displacement
        points = ax.scatter(deformed[:, 0], deformed[:, 1], s=4, c=magnitude, cmap="viridis")
        fig.colorbar(points, ax=ax, label="|u| (mm)", shrink=0.7)
        record = result.steps[step - 1] if step > 0 else None
        center = record.center if record is not None else geometry.center
        rotation = record.rotation if record is not None else 0.0
        _needle_arc(ax, center, geometry.radius, geometry.start_angle, geometry.sense, rotation,
                    geometry.arc, color="crimson", lw=2, label="needle")
        tips = np.array([s.tip_spatial for s in result.steps[:step]]) if step else np.zeros((0, 2))
        if len(tips):
            ax.plot(tips[:, 0], tips[:, 1], ".-", color="orange", ms=3, lw=1, label="tip path")
        ax.plot(*result.desired_exit, "x", color="k", ms=9, mew=2, label="desired exit (reference)")
        if step == len(result.steps):
            ax.plot(*result.desired_exit_def, "+", color="blue", ms=11, mew=2, label="desired exit, deformed")
            ax.plot(*result.achieved_exit_def, "o", mfc="none", color="crimson", ms=9, label="achieved exit")
        zoom = 1.8 * geometry.radius
        middle = geometry.center
        ax.set_xlim(middle[0] - zoom, middle[0] + zoom)
        ax.set_ylim(middle[1] - zoom, middle[1] + zoom)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title or f"step {step}, rotation {rotation:.2f} rad")
        ax.legend(loc="upper right", fontsize=7)
    save(fig, path)


def plot_plan(path: str | Path, result) -> None:
    """Planned and unplanned needle paths over the deformed tissue, desired exit marked
    (thesis figures 5.9-5.15), and the centre trajectory O(t)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    planned, unplanned = result.planned, result.unplanned
    geometry = planned.geometry
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 5.5))
    particles = planned.model.particles
    deformed = particles + planned.displacements[-1]
    magnitude = np.linalg.norm(planned.displacements[-1], axis=1)
    points = left.scatter(deformed[:, 0], deformed[:, 1], s=4, c=magnitude, cmap="viridis")
    fig.colorbar(points, ax=left, label="|u| planned (mm)", shrink=0.7)
    tips = np.array([s.tip_spatial for s in planned.steps] + [planned.achieved_exit_def])
    left.plot(tips[:, 0], tips[:, 1], "-", color="crimson", lw=2, label="planned tip path")
    if unplanned is not None:
        tips_u = np.array([s.tip_spatial for s in unplanned.steps] + [unplanned.achieved_exit_def])
        left.plot(tips_u[:, 0], tips_u[:, 1], "--", color="orange", lw=2, label="unplanned tip path")
        left.plot(*unplanned.achieved_exit_def, "s", mfc="none", color="orange", ms=8,
                  label=f"unplanned exit ({unplanned.exit_error_mm:.3f} mm off)")
    last = planned.steps[-1]
    _needle_arc(left, last.center, geometry.radius, geometry.start_angle, geometry.sense, last.rotation,
                geometry.arc, color="crimson", lw=1, alpha=0.5)
    left.plot(*planned.desired_exit_def, "x", color="k", ms=10, mew=2, label="desired exit (deformed)")
    left.plot(*planned.achieved_exit_def, "o", mfc="none", color="crimson", ms=9,
              label=f"planned exit ({planned.exit_error_mm:.3f} mm off)")
    zoom = 1.8 * geometry.radius
    left.set_xlim(geometry.center[0] - zoom, geometry.center[0] + zoom)
    left.set_ylim(geometry.center[1] - zoom, geometry.center[1] + zoom)
    left.set_aspect("equal")
    left.set_xlabel("x (mm)")
    left.set_ylabel("y (mm)")
    left.set_title(f"{planned.scenario.name or 'plan'}: planned vs unplanned")
    left.legend(loc="upper right", fontsize=7)
    centers = result.center_trajectory
    rotation = np.arange(len(centers)) * geometry.step
    right.plot(rotation, centers[:, 0] - centers[0, 0], label="O_x(t) - O_x(0)")
    right.plot(rotation, centers[:, 1] - centers[0, 1], label="O_y(t) - O_y(0)")
    right.set_xlabel("needle rotation (rad)")
    right.set_ylabel("centre offset (mm)")
    right.set_title("planned needle-centre trajectory O(t)")
    right.grid(alpha=0.3)
    right.legend()
    save(fig, path)


def plot_speed_accuracy(path: str | Path, study) -> None:
    """Wall time against exit-point deviation from the study's finest run (log-log), one
    series per method family, the Pareto front joined and ringed; failed runs drawn as
    crosses at the right edge (deviation unknown). Left: `deviation_mm` (largest of the
    spatial, material and exit-error deviations); right: the spatial achieved exit alone."""
    import math

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in study.runs if r is not study.reference]
    families = list(dict.fromkeys(r.family for r in runs))
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, 2, figsize=(13.0, 5.5))
    panels = (("deviation_mm", "exit-point deviation from the finest run (mm)\n"
               "largest of spatial, material and exit-error vector"),
              ("exit_deviation_mm", "achieved exit (spatial) deviation from the finest run (mm)"))
    accuracy = getattr(study.auto, "accuracy", None)
    for ax, (key, xlabel) in zip(axes, panels):
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
            style = dict(color=colours(k % 10))
            if family == "auto":
                style = dict(color="crimson", marker="*", ms=16, ls="none")
            else:
                style.update(marker="o", ms=5, lw=0.8)
            if members:
                ax.plot([x_of(r) for r in members], [r.wall_seconds for r in members], label=family, **style)
            failed = [r for r in runs if r.family == family and not r.ok]
            if failed:  # times clipped to the successful runs' range (failures before a solve are instant)
                ax.plot([top] * len(failed), [min(max(r.wall_seconds, low), high) for r in failed], "x",
                        color=colours(k % 10),
                        ms=8, mew=2, clip_on=False,
                        label=f"{family}: {len(failed)} failed" if not members else None)
        ordered = sorted(done, key=lambda r: (r.wall_seconds, r.deviations[key]))
        front, best = [], math.inf
        for run in ordered:
            if run.deviations[key] < best:
                front.append(run)
                best = run.deviations[key]
        ax.step([x_of(r) for r in front], [r.wall_seconds for r in front], where="pre", color="black",
                lw=1.2, alpha=0.6)
        ax.plot([x_of(r) for r in front], [r.wall_seconds for r in front], "o", mfc="none", mec="black",
                ms=11, label="Pareto front")
        if accuracy is not None and key == "deviation_mm":
            ax.axvline(accuracy, color="crimson", ls="--", lw=1, label=f"auto target {accuracy:g} mm")
        if any(not r.ok for r in runs):
            ax.axvline(top, color="0.6", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(low, high)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("wall time (s)")
        ax.grid(alpha=0.3, which="both")
    reference = study.reference
    axes[0].set_title(f"{study.scenario.name or 'study'}: speed against accuracy\n"
                      f"finest run: {reference.label}, {reference.particles} particles, "
                      f"{reference.wall_seconds:.1f} s (crosses at the right: failed runs)", fontsize=9)
    axes[1].set_title("achieved exit, spatial position only (achieved_exit_def)", fontsize=9)
    axes[0].legend(loc="upper center", bbox_to_anchor=(1.1, -0.16), ncol=5, fontsize=8, frameon=False)
    save(fig, path)
