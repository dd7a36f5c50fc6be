"""The runs of `simulate` and `plan` once their inputs are checked: the discretization chosen
for an asked accuracy, and the run with its replays and progress bar, input errors naming
their file.

Imported inside those commands, with their imports of the numerics (this module's bring
numpy, scipy and the solvers), before the collector resumes (stitchplan/allocator.py). What
it calls is looked up in its module at each call, as the commands' own imports did."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..io import progress, readers, reports
from ..needle import geometry as needle_geometry
from ..planning import verification
from ..study import auto
from .options import naming_files, naming_option, scenario_expected_steps


def resolve_accuracy_guarded(scenario_path: Path, scenario, limits, linear_solver: Optional[str] = None,
                             tip_tracking: Optional[str] = None):
    """study.auto.resolve_accuracy within the resource guard's particle limit (`limits`; None:
    unchecked): the scenario with the discretization chosen for its `accuracy`, and the note
    saying so (None without one). An accuracy the discretizations cannot reach names the file."""
    with naming_files(scenario_path):
        return auto.resolve_accuracy(scenario, tip_tracking, linear_solver,
                                     max_particles=None if limits is None else limits.max_particles)


def read_center_path_option(scenario_path: Path, center_path: Path, scenario, geometry):
    """The --center-path file as read (readers.CenterPathFile), its centres checked against
    the scenario's needle `geometry`, its rows' errors naming the file."""

    def needle_for(first_center):
        """The needle a path starting about `first_center` replays: a path planned with the
        needle leaning at entry leans it (run_insertion does the same)."""
        with naming_files(scenario_path, center_path):
            return needle_geometry.scenario_needle(needle_geometry.entry_lean(scenario, first_center))

    with naming_option("--center-path", center_path):  # as --air's and --tissue's lines do
        return readers.read_center_path_file(center_path, geometry, needle_for)


def simulate_with_replays(scenario_path: Path, scenario, center_path: Optional[Path], path, estimate: bool,
                          condition_numbers: bool, linear_solver: Optional[str] = None,
                          tip_tracking: Optional[str] = None):
    """planning.verification.simulate_with_estimate of the centre `path` (None: fixed) with a
    progress bar: (result, exit error estimate or None)."""
    # the estimate's run at 2h goes on in a helper process alongside (planning/replays.py)
    with (naming_files(scenario_path, center_path),
          verification.estimate_replays(scenario, estimate=estimate, linear_solver=linear_solver,
                                        tip_tracking=tip_tracking) as replays,
          progress.progress_bar("needle steps", scenario_expected_steps(scenario)) as advance):
        return verification.simulate_with_estimate(
            scenario, center_path=path, estimate=estimate, linear_solver=linear_solver,
            tip_tracking=tip_tracking, condition_numbers=condition_numbers,
            on_step=lambda record: advance(description="needle steps"),
            on_ramp=_ramp_note(advance, "needle steps"), replays=replays)


def plan_with_replays(scenario_path: Path, scenario, compare: bool, verify: bool, out: Optional[Path],
                      plot: Optional[Path], **options):
    """planning.verification.plan_verified with a progress bar; the run log's and the plot's
    writers are imported while the planning waits for a replay (io.reports.prepare_plan_outputs)."""
    expected = scenario_expected_steps(scenario)
    # the trajectory's replays go on in a helper process alongside (planning/replays.py); the
    # predicted aim's at 2h here, after the first pass (planning/verification.py)
    with (naming_files(scenario_path),
          verification.plan_replays(scenario, verify, while_waiting=lambda: reports.prepare_plan_outputs(out, plot),
                                    **options) as replays,
          verification.prediction_replays(scenario, verify, **options) as predictions,
          progress.progress_bar("planned steps", (2 if compare else 1) * expected) as advance):
        return verification.plan_verified(scenario, compare=compare, verify=verify,
                                          on_step=lambda record: advance(description="planned steps"),
                                          on_ramp=_ramp_note(advance, "planned steps"), replays=replays,
                                          predictions=predictions, **options)


def _ramp_note(advance, label: str):
    """run_insertion's on_ramp: the bar's label says how far a step's ramp has carried its
    load while it cuts it (a step's own label again once the step is done)."""
    return lambda step, carried, increment: advance(0, description=(
        f"{label} (step {step}: {100 * carried:.0f} % of its load carried, increments of {100 * increment:.3g} %)"))


def put_accuracy_notes_first(events: list, auto_note, accuracy: float | None, estimate) -> None:
    """The auto discretization's note (None: none chosen) first among a run's `events`, and
    after it the accuracy check of _accuracy_events."""
    if auto_note is not None:
        events[:0] = [auto_note, *_accuracy_events(accuracy, estimate)]


def _accuracy_events(accuracy: float | None, estimate) -> list:
    """An accuracy-check event where the run's own exit error estimate (from a run at twice
    its spacing) is above the `accuracy` the auto discretization chose the run for by its
    estimate (from runs at h and h/2): both stand in the summary, so the difference is said."""
    if accuracy is None or estimate is None or estimate.estimate_mm <= accuracy:
        return []
    return [_note_event(f"accuracy: the run's own exit error estimate, {estimate.estimate_mm:.3g} mm (from "
                        f"the run at {estimate.other_spacing_mm:.3g} mm), is above the {accuracy:g} mm "
                        "asked for, which the auto discretization met by its estimate from two finer "
                        "runs (first note); the two estimate the same error from different pairs of "
                        "runs: for a firmer bound ask for a smaller accuracy")]


def _note_event(message: str):
    from ..events import Event, EventKind

    return Event(EventKind.ACCURACY_CHECK, message)
