"""The outputs of `stitchplan plan --uncertainty`: the summary's `uncertainty` block
(README, "Planning under uncertainty"), the run log's `uncertainty` group, the lines printed, and uncertainty.png
(exit clouds of the unplanned, nominal and robust paths on the held-out samples with 95 %
ellipses, and the sensitivities). The plan's own files are io.reports' (the exported plan)."""

from __future__ import annotations

import json

import math
from pathlib import Path

import numpy as np

from ..config.uncertainty import unit_of
from ..uncertainty.robust import LABELS, SENSITIVITY_STEP, Z_95, UncertaintyResult, ellipse_95, exit_statistics
from .plot_elements import SAVED_DPI, label_with_multiplier, legend_below, literal, pyplot, title_above
from .plots import save

SENSITIVITY_METHOD = (f"central finite differences of the exit error vector (achieved - desired exit, deformed), "
                      f"the nominal plan's centre path replayed at the scenario's value +- {SENSITIVITY_STEP:g} std "
                      "(at most half the value), the other parameters at the scenario's values")
ROBUST_DESIGN = ("the nominal plan re-aimed with the mean exit shift: planner passes aiming the exit error at -s "
                 "(minus the refined model's offset where verified), s = mean over the training samples of (exit "
                 "error of the nominal path - the nominal plan's own exit error); statistics on the held-out samples "
                 "where every path ran")
STATISTICS_MODEL = {
    True: ("the sampled runs replay on the planning model; the nominal and robust paths' exit error vectors with "
           "refined_offset_mm added (on the refined model to first order), the unplanned path's as they are"),
    False: "the sampled runs replay on the planning model (not verified: no refined offset)",
}
COLOURS = {"unplanned": "tab:red", "nominal": "tab:blue", "robust": "tab:green"}


def per_unit(name: str) -> str:
    """The units of a sensitivity to parameter `name`: mm/MPa, mm/(N/mm), ..."""
    unit = unit_of(name)
    return f"mm/({unit})" if "/" in unit else f"mm/{unit}"


def _vector(value) -> list[float] | None:
    return None if value is None else [float(v) for v in value]


def uncertainty_summary(result: UncertaintyResult) -> dict:
    """The summary's `uncertainty` block (the format's keys first, then how it was made) and
    its `sensitivity` again at the top level."""
    stats = result.statistics
    exported = stats[result.exported]
    # the robust plan where the nominal one was exported instead: `robust` is the exported plan's
    candidate = result.exported != "robust" and result.robust is not None
    training_ok = [run for run in result.training if run.ok]
    samples = result.uncertainty.samples
    block = {
        # the format's counts, of the held-out samples the statistics below are over (as many
        # train the robust plan); each set's own counts follow
        "samples": samples,
        "failed_samples": result.failed_held_out_samples,
        "held_out_samples": samples,
        "failed_held_out_samples": result.failed_held_out_samples,
        "training_samples": len(result.training),
        "failed_training_samples": result.failed_training_samples,
        "unplanned": stats["unplanned"],
        "nominal": stats["nominal"],
        "robust": exported,  # the exported plan
        "sensitivity": {s.name: _vector(s.exit_error) for s in result.sensitivities},
        "exported": result.exported,
        "robust_candidate": stats["robust"] if candidate else None,
        "evaluated_samples": int(result.evaluated.sum()),
        "held_out_mean_exit_error_mm": {  # keyed as the statistics above
            **{label: _held_out_mean(result, result.exported if label == "robust" else label) for label in LABELS},
            **({"robust_candidate": _held_out_mean(result, "robust")} if candidate else {})},
        "robust_design": ROBUST_DESIGN,
        "statistics_model": STATISTICS_MODEL[result.refined_offset is not None],
        "refined_offset_mm": _vector(result.refined_offset),
        "mean_shift_mm": _vector(result.shift),
        "robust_aim_mm": _vector(result.aim),
        "mean_shift_t2": result.shift_significance,  # Hotelling T^2; None: not defined (< 3 runs, singular)
        "mean_shift_t2_threshold": result.shift_threshold,  # its 95 % quantile; the robust plan re-aims above
        "training_prediction": result.training_prediction(),
        "training": {"samples": len(result.training), "failed": len(result.training) - len(training_ok),
                     "nominal_path": exit_statistics(result.on_refined_model(
                         np.array([run.exit_error for run in training_ok]).reshape(-1, 2), "nominal"))},
        "sensitivity_method": SENSITIVITY_METHOD,
        "sensitivity_units": {s.name: per_unit(s.name) for s in result.sensitivities},
        "sensitivity_step": {s.name: s.step for s in result.sensitivities},
        "sensitivity_achieved_exit": {s.name: _vector(s.achieved_exit) for s in result.sensitivities},
        "spread_1sigma_mm": {s.name: None if s.exit_error is None else s.spread_mm for s in result.sensitivities},
        "dominant_parameter": getattr(result.dominant(), "name", None),
        "dominance": result.dominance_line(),
        "distributions": result.uncertainty.as_record(),
        "design": {**result.design.as_record(), "seed": result.uncertainty.seed,
                   "training_indices": "accepted points 0 .. samples-1",
                   "held_out_indices": "accepted points samples .. 2 samples-1"},
        "failures": result.failures(),
        "executor": result.where,
        "sample_wall_seconds_mean": _mean_wall(result),
        "notes": list(result.notes),
    }
    block = finite_only(block)
    # the format's "adds to the summary `uncertainty`: ...; and `sensitivity`: ..." reads
    # either way: the sensitivities are in the block and, the same values, beside it
    return {"uncertainty": block, "sensitivity": block["sensitivity"]}


def finite_only(block: dict) -> dict:
    """The block with every non-finite number (inf, nan: no JSON value) written as null and
    named in a note, so that summary.json stays valid JSON and nothing is dropped silently."""
    replaced: list[str] = []

    def clean(value, where: str):
        if isinstance(value, dict):
            return {key: clean(item, f"{where}.{key}" if where else str(key)) for key, item in value.items()}
        if isinstance(value, (list, tuple, np.ndarray)):
            return [clean(item, f"{where}[{k}]") for k, item in enumerate(value)]
        if isinstance(value, (float, np.floating)) and not math.isfinite(value):
            replaced.append(f"{where} ({float(value)})")
            return None
        return value.item() if isinstance(value, np.generic) else value

    cleaned = clean(block, "")
    if replaced:
        cleaned["notes"].append("not finite, written as null: " + ", ".join(replaced))
    return cleaned


def _held_out_mean(result: UncertaintyResult, label: str) -> list[float] | None:
    """The mean exit error vector of a path's held-out runs where every path ran (mm)."""
    return _vector(result.errors(label).mean(axis=0)) if result.evaluated.any() else None


def _mean_wall(result: UncertaintyResult) -> float | None:
    walls = [run.wall_seconds for group in [result.training, *result.held_out.values()] for run in group if run.ok]
    return float(np.mean(walls)) if walls else None


def uncertainty_datasets(result: UncertaintyResult) -> tuple[dict, dict]:
    """The run log's `uncertainty/...` groups and their units: parameters drawn, exit points,
    error vectors and failures of every sampled run, the sensitivities."""
    names = result.design.names
    parameter_units = ",".join(unit_of(name) for name in names)
    groups = {"uncertainty": {
        "parameter_names": "\n".join(names),
        "nominal_values": result.design.nominal,
        "std": result.uncertainty.std,
        "correlation": result.uncertainty.correlation,
        "training_parameters": result.design.train,
        "held_out_parameters": result.design.held_out,
        "sensitivity": np.array([s.exit_error if s.exit_error is not None else [np.nan, np.nan]
                                 for s in result.sensitivities]),
        "sensitivity_step": np.array([s.step for s in result.sensitivities]),
        "mean_shift": result.shift,
        # how the samples were drawn and which plan trajectory.csv holds (held_out/robust below is
        # the robust plan's runs, also where the nominal one was exported instead)
        "samples": result.uncertainty.samples,
        "seed": result.uncertainty.seed,
        "exported": result.exported,
        "mean_shift_t2": np.nan if result.shift_significance is None else result.shift_significance,
        "mean_shift_t2_threshold": np.nan if result.shift_threshold is None else result.shift_threshold,
        "uncertainty_file": result.uncertainty.path,
        "from_calibration": result.uncertainty.calibration or "",
        "distributions": json.dumps(result.uncertainty.as_record()),  # the file as resolved (stds, correlations)
        # the planned paths' exit_error below are the planning model's; the summary adds this offset
        **({} if result.refined_offset is None else {"refined_offset": result.refined_offset}),
    }}
    units = {"uncertainty/parameter_names": "text", "uncertainty/nominal_values": parameter_units,
             "uncertainty/std": parameter_units, "uncertainty/correlation": "1",
             "uncertainty/training_parameters": parameter_units, "uncertainty/held_out_parameters": parameter_units,
             "uncertainty/sensitivity": ",".join(per_unit(name) for name in names),
             "uncertainty/sensitivity_step": parameter_units, "uncertainty/mean_shift": "mm",
             "uncertainty/refined_offset": "mm", "uncertainty/samples": "1", "uncertainty/seed": "1",
             "uncertainty/exported": "text", "uncertainty/mean_shift_t2": "1",
             "uncertainty/mean_shift_t2_threshold": "1", "uncertainty/uncertainty_file": "text",
             "uncertainty/from_calibration": "text", "uncertainty/distributions": "text"}
    runs = {"training/nominal": result.training, **{f"held_out/{label}": result.held_out[label] for label in LABELS}}
    for key, group in runs.items():
        name = f"uncertainty/{key}"
        groups[name] = {
            "exit_error": np.array([run.exit_error for run in group]).reshape(-1, 2),
            "achieved_exit_def": np.array([run.achieved_exit_def for run in group]).reshape(-1, 2),
            "failed": np.array([not run.ok for run in group], dtype=int),
            "reason": "\n".join(run.reason for run in group),
            "wall_seconds": np.array([run.wall_seconds for run in group]),
            "newton_iterations": np.array([run.newton_iterations for run in group]),
        }
        units.update({f"{name}/exit_error": "mm", f"{name}/achieved_exit_def": "mm", f"{name}/failed": "1",
                      f"{name}/reason": "text", f"{name}/wall_seconds": "s", f"{name}/newton_iterations": "1"})
    return groups, units


def uncertainty_lines(result: UncertaintyResult) -> list[str]:
    """What the command prints after the plan line."""
    stats = result.statistics
    basis = ("" if result.refined_offset is None else
             " (the plans' on the refined model: their planning-model exits + its offset "
             f"({result.refined_offset[0]:.3g}, {result.refined_offset[1]:.3g}) mm)")
    evaluated = int(result.evaluated.sum())
    lines = [f"uncertainty: {len(result.training)} training samples ({result.failed_training_samples} with a failed "
             f"run), {result.uncertainty.samples} held out ({result.failed_held_out_samples} with a failed run); "
             f"exit error mean / p95 over the {evaluated} held-out samples where every path ran{basis}:"]
    for label in LABELS:
        s = stats[label]
        shown = "n/a" if s["mean_mm"] is None else f"{s['mean_mm']:.4f} / {s['p95_mm']:.4f} mm"
        exported = "  (exported)" if label == result.exported else ""
        if label == "robust" and result.exported != "robust":
            exported = "  (the robust candidate, not exported)"
        lines.append(f"  {label:9s} {shown}{exported}")
    lines.append(result.dominance_line())
    return lines


def plot_title(result: UncertaintyResult, scenario_name: str = "") -> str:
    """The figure's title: the held-out samples evaluated and the p95 misses, or why there
    are none (no held-out sample ran every path)."""
    stats = result.statistics
    exported, unplanned = stats[result.exported]["p95_mm"], stats["unplanned"]["p95_mm"]
    evaluated = int(result.evaluated.sum())
    name = scenario_name or "scenario"
    if exported is None or unplanned is None:
        return (f"{name}: no held-out sample ran every path ({result.failed_held_out_samples} samples with a failed "
                f"run); {result.exported} plan exported")
    basis = "" if result.refined_offset is None else " (plans: on the refined model)"
    failed = result.failed_held_out_samples
    left_out = f" ({failed} of {result.uncertainty.samples} left out: a failed run)" if failed else ""
    return (f"{name}: exit error on {evaluated} held-out samples{left_out}{basis}; {result.exported} plan p95 "
            f"{exported:.3g} mm, unplanned {unplanned:.3g} mm")


def plotted_paths(result: UncertaintyResult) -> list[tuple[str, str]]:
    """(path, legend name) of the exit clouds drawn: the unplanned path and both plans, or, where
    the robust plan is the nominal one (the same held-out runs), that plan once."""
    if result.robust_is_nominal:
        return [("unplanned", "unplanned"), (result.exported, "robust = nominal plan (exported)")]
    return [(label, f"{label}{' (exported)' if label == result.exported else ''}") for label in LABELS]


def _room_for_labels(fig, ax, ends: list[float], labels: list) -> float:
    """The x limit that keeps each label, drawn from its bar's end, inside the panel: a bar
    ending at b with a label w pixels wide in a panel p pixels wide needs b p / (p - w), and at
    least 1.9 x the widest bar."""
    renderer = fig.canvas.get_renderer()
    panel = ax.get_window_extent(renderer).width
    widths = [label.get_window_extent(renderer).width for label in labels]
    needed = [end * panel / (panel - width) for end, width in zip(ends, widths) if width < 0.9 * panel]
    return max([1.9 * max(ends + [1e-6]), *needed])


def plot_uncertainty(path: str | Path, result: UncertaintyResult, scenario_name: str = ""):
    """uncertainty.png: (a) the exit error vectors of the three paths on the held-out samples
    (two where the robust plan is the nominal one: plotted_paths), the desired exit at the
    origin, with 95 % ellipses; (b) the same for the plans, enlarged; (c) each parameter's
    95 % exit move (|sensitivity| x 1.96 std)."""
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(1, 3, figsize=(14.0, 4.6), dpi=SAVED_DPI, gridspec_kw={"width_ratios": [1.0, 1.0, 0.9]})
    fig.subplots_adjust(wspace=0.5)  # before the labels' room is measured
    paths = plotted_paths(result)
    plans = "the plan (robust = nominal)" if result.robust_is_nominal else "the plans"
    for ax, shown, title in ((axes[0], paths, f"unplanned and {plans}\n(x, y scaled separately)"),
                             (axes[1], paths[1:], f"{plans}, enlarged\n(x, y scaled separately)")):
        for label, name in shown:
            errors = result.errors(label)
            marker = "s" if label == result.exported else "o"
            ax.scatter(errors[:, 0], errors[:, 1], s=18, color=COLOURS[label], marker=marker, alpha=0.8,
                       label=name)
            ellipse = ellipse_95(errors)
            if ellipse is not None:
                centre, axes_matrix = ellipse
                t = np.linspace(0.0, 2.0 * np.pi, 120)
                curve = centre + (axes_matrix @ np.vstack([np.cos(t), np.sin(t)])).T  # (120, 2)
                ax.plot(curve[:, 0], curve[:, 1], color=COLOURS[label], lw=1.2,
                        label=f"{name.removesuffix(' (exported)')} 95 % ellipse")
        ax.plot([0.0], [0.0], marker="*", color="k", markersize=12, linestyle="none", label="desired exit")
        if not result.evaluated.any():  # nothing to scatter: say so instead of an empty, arbitrary scale
            ax.set_xlim(-1.0, 1.0)
            ax.set_ylim(-1.0, 1.0)
            ax.text(0.5, 0.6, "no held-out sample ran every path", transform=ax.transAxes, ha="center", fontsize=9)
        ax.axhline(0.0, color="0.85", lw=0.6, zorder=0)
        ax.axvline(0.0, color="0.85", lw=0.6, zorder=0)
        ax.margins(0.15)  # x and y scaled separately: the exits lie along the deformed edge
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.get_xlim()  # settles the automatic limits before the labels read the ticks
        label_with_multiplier(ax.xaxis, "exit error x", "mm")
        label_with_multiplier(ax.yaxis, "exit error y", "mm")
        ax.set_title(title, fontsize=9)
    ax = axes[2]
    names = [s.name for s in result.sensitivities]
    moves = [Z_95 * s.spread_mm if s.exit_error is not None and math.isfinite(s.spread_mm) else 0.0
             for s in result.sensitivities]
    bars = ax.barh(names, moves, color="0.45")
    labels = []
    for bar, s in zip(bars, result.sensitivities):
        text = "failed" if s.exit_error is None else (f"{np.linalg.norm(s.exit_error):.3g} {per_unit(s.name)}"
                                                       f" x 1.96 x {s.std:g}")
        labels.append(ax.text(bar.get_width(), bar.get_y() + bar.get_height() / 2, " " + text, va="center",
                              fontsize=7))
    ax.set_xlim(0.0, _room_for_labels(fig, ax, moves, labels))
    ax.invert_yaxis()
    ax.set_xlabel("95 % exit move from the parameter alone (mm)")
    ax.set_title("sensitivity of the exit (nominal path)", fontsize=9)
    title_above(fig, list(axes), plot_title(result, literal(scenario_name)))
    legend_below(fig, list(axes[:2]), columns=4)
    save(fig, path)
    return fig
