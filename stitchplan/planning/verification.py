"""How far to trust an exit point: discretization error estimates, and plans checked on a
refined model.

Error estimate (Richardson). Two runs of the same needle-centre path at particle spacings
h and h' = h/2 (or 2h) give d = the largest of the deviations of the spatial achieved exit,
the material achieved exit and the exit-error vector (as stitchplan.study measures exit
points). With x(h) - x* ~ C h^p,

    e(h) = d / (1 - 2^-p)   from (h, h/2),        e(h) = d / (2^p - 1)   from (h, 2h).

p = ASSUMED_ORDER = 1: the exit point converges about that fast on the shipped scenes, where
a cutting force concentrated at the tip makes the absolute exit position converge slowly (at
order 1 or above the estimate is on the safe side; where it converges more slowly, very soft
tissue under a large friction, it falls short); the exit *error* (achieved minus desired, both moved alike)
converges much faster, and the deviations say which part moved (`ExitEstimate.deviations`).

Verified plans (`plan_verified`). The planner's own exit error is measured on the model it
planned on; `plan` therefore replays the exported trajectory (the centre column of
trajectory.csv, row n at step n) on a model with half the particle spacing and reports
that replay's exit error. When it exceeds VERIFIED_FACTOR x exit_tolerance, the offset
between the two models' exit-error vectors for the same trajectory, delta = e_refined -
e_base, is the base model's bias: the planner's passes are aimed at e_base = -delta
(shooting with the refined model's mismatch; planning.planner.run_plan `aim`, continuing the
secant of the earlier passes) and the new trajectory is replayed again. At most
MAX_CORRECTIONS such rounds; the trajectory with the smallest verified error is the one
exported and reported (its `wall_seconds` then counts the passes of every round, a failed one's too; the
replays' times are in the verification rounds). The trajectory is judged on the finer
model: where the two models disagree by more than exit_tolerance, the planned (base-model)
exit error of a corrected plan is about |delta|, and `exit_error_estimate_mm` says so too.
With planner.target `symmetric` on a stitch across a wound the rounds judge and re-aim the
bites' difference the same way: the refined model's offset b_refined - b_base aims the
passes at the difference -(b_refined - b_base) on the base model (run_plan `bite_aim`).

Predicted aim (planner.predicted_aim, the default). The first planner pass's trajectory is
replayed at 2h too (a quarter of the planning model's particles; in this process after the
pass, `prediction_replays`), and the refined model's offset is predicted from
the change between 2h and h: delta ~ (e_h - e_2h) / PREDICTED_RATIO. When |e_base + delta|
is above VERIFIED_FACTOR x exit_tolerance, the passes from the second on aim at -delta
(run_plan `retarget`), and the first round's refined replay judges that plan (a miss re-aims
by the measured offset as above). So where the base model's bias is larger than the
tolerance, the first round's passes already aim for the refined model: one refined replay
and one run of passes instead of two, and the re-aimed passes, which keep the first pass's
early steps, are replayed by the helper as the continuation of the first pass's replay
(planning/replays.py). The ratio is a property of the discretization that the prediction
assumes; only the aim depends on it. The symmetric target is not predicted.

A later round's replay starts each step's Newton solve from the round before (run_insertion
`start_from`): its centres are prescribed, so it ends in the same equilibria to the residual
tolerance, in fewer iterations. The re-planning passes start cold (planning.planner.run_plan).
The replays (the refined model's, or without verification the estimate's at 2h) are made
by one `replays` object of planning/replays.py for the whole plan: the `plan` and
`simulate` commands give them to a helper process, which replays each planner pass while
the planning goes on; a round's `replay_wall_seconds` then runs from the start of the pass
it replays (of the first pass, where the replay went on with a re-aimed one).
"""

from __future__ import annotations

import logging
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..config import Scenario
from ..errors import InputError, NumericalFailure, PlanningFailure
from ..events import Event, EventKind
from ..needle.prepared_tissue import PreparedTissue
from ..needle.insertion import run_insertion
from ..needle.results import InsertionResult
from .planner import PlanResult, add_timings, run_plan, symmetric_aim
from .replay_models import (
    ESTIMATE_FACTOR,
    VERIFICATION_FACTOR,
    predicts_aim,
    replay_options,
    replay_scenario,
)
from .replays import InlineReplays, StreamTee, replays_for
from .trajectory import exported_centers

log = logging.getLogger(__name__)

ASSUMED_ORDER = 1.0  # convergence order of the exit point in the particle spacing (conservative)
VERIFIED_FACTOR = 1.5  # a verified exit error within 1.5 x exit_tolerance needs no correction
AIMED_TOLERANCE_FRACTION = 0.4  # passes with an aim stop within this x exit_tolerance of it
MAX_CORRECTIONS = 2
ENDS_BEFORE_EXIT = "the exported trajectory ends before the tip leaves the refined model"  # a replay's reason for none
# the exit-error vector's change from 2h to h over its change from h to h/2, by which the
# predicted aim scales the first (2^p for order p): 2.5-3.9 for the first passes of the six
# shipped scenes it re-aims (benchmarks/results/predicted_aim.md)
PREDICTED_RATIO = 3.0


@dataclass
class ExitEstimate:
    """Estimated discretization error of a run's exit point (mm), from a second run of the
    same centre path at `other_spacing_mm`."""

    estimate_mm: float
    basis: str  # "refined" (h/2) or "coarse" (2h)
    order: float
    other_spacing_mm: float  # nominal spacing of the second run
    other_particles: int
    deviations: dict[str, float]  # mm, between the two runs

    def as_record(self) -> dict:
        return {"estimate_mm": self.estimate_mm, "basis": self.basis, "assumed_order": self.order,
                "other_spacing_mm": self.other_spacing_mm, "other_particles": self.other_particles,
                **self.deviations}


@dataclass
class Verification:
    """The exported trajectory replayed on the refined model."""

    spacing_mm: float  # nominal spacing of the refined model
    result: InsertionResult | None  # the replay (None: it could not be replayed)
    rounds: list[dict] = field(default_factory=list)  # per planning round: planned and verified errors
    replayed_in: str = "this process"  # or "helper process" (planning/replays.py)
    aimed_by: str = "none"  # the exported plan's round: aimed by a "predicted offset" or "refined offset"
    no_replay: str | None = None  # without a replay (result None), why

    @property
    def exit_error_mm(self) -> float | None:
        return None if self.result is None else self.result.exit_error_mm


def exit_deviations(result: InsertionResult, reference: InsertionResult) -> dict[str, float | bool]:
    """Distances (mm) between the exit points of two runs: spatial achieved exit, material
    achieved exit, exit-error vector, and the largest of them. The spatial exit is where the
    tissue is after the run's last needle step; when the two runs took different numbers of
    steps (the tip leaving just before and just after a step's end) they end in different
    needle states, and the spatial deviation then measures that step, not the
    discretization: it is reported but not counted (`spatial_compared` false). On
    sh12_100x100_mid's verified plan, 38 against 39 steps, it was 0.137 mm while the material
    exit and the exit-error vector differed by 0.015 mm."""
    spatial = float(np.linalg.norm(result.achieved_exit_def - reference.achieved_exit_def))
    material = float(np.linalg.norm(result.achieved_exit - reference.achieved_exit))
    error = float(np.linalg.norm((result.achieved_exit_def - result.desired_exit_def)
                                 - (reference.achieved_exit_def - reference.desired_exit_def)))
    compared = len(result.steps) == len(reference.steps)
    return {"exit_deviation_mm": spatial, "material_exit_deviation_mm": material,
            "exit_error_deviation_mm": error, "spatial_compared": compared,
            "deviation_mm": max(spatial, material, error) if compared else max(material, error)}


def estimate_from(result: InsertionResult, other: InsertionResult, factor: float, other_spacing: float) -> ExitEstimate:
    """Richardson estimate of `result`'s exit error from a run at `factor` x its spacing."""
    deviations = exit_deviations(result, other)
    ratio = 2.0 ** ASSUMED_ORDER
    if factor < 1.0:  # other is the finer run
        estimate = deviations["deviation_mm"] / (1.0 - 1.0 / ratio)
        basis = "refined"
    else:
        estimate = deviations["deviation_mm"] / (ratio - 1.0)
        basis = "coarse"
    return ExitEstimate(estimate, basis, ASSUMED_ORDER, other_spacing, other.model.n_particles, deviations)


def estimate_exit_error(scenario: Scenario, result: InsertionResult, center_path: np.ndarray | None = None,
                        replays: InlineReplays | None = None, **options) -> ExitEstimate | None:
    """The exit error estimate of `result` from a coarser run (2h) of the same centre path
    (`center_path` rows as run_insertion takes them; None: the needle centre stays fixed),
    by `replays` on the 2h model (estimate_replays) when given. None, with an event on
    `result`, when the coarse model cannot run the insertion."""
    try:
        coarse = replay_scenario(scenario, verify=False)
        other = (replays or InlineReplays(coarse, **replay_options(options))).replay(center_path)
    except (InputError, NumericalFailure) as error:
        message = f"exit error estimate: the model at twice the spacing failed ({error}); no estimate"
        result.events.append(Event(EventKind.ACCURACY_CHECK, message))
        log.info(message)
        return None
    return estimate_from(result, other, ESTIMATE_FACTOR, coarse.discretization.spacing)


def estimate_replays(scenario: Scenario, background: bool = True, estimate: bool = True, **options):
    """replays_for the exit error estimate's 2h model (a context manager; planning/replays.py);
    None without an `estimate`."""
    if not estimate:
        return nullcontext(None)
    return plan_replays(scenario, verify=False, background=background, **options)


def plan_replays(scenario: Scenario, verify: bool = True, background: bool = True, while_waiting=None, **options):
    """replays_for plan_verified's replays (replay_scenario; a context manager); `while_waiting`:
    replays.BackgroundReplays'."""
    return replays_for(replay_scenario(scenario, verify), background, while_waiting, **replay_options(options))


def prediction_replays(scenario: Scenario, verify: bool = True, background: bool = False, **options):
    """replays_for the predicted aim's model at 2h, which replays the first planner pass (a
    context manager); None where plan_verified predicts no aim. By default in this process,
    after the pass: the refined model's replay in the helper is a verified plan's longest
    path, and a second helper beside it took CPU from it; in this process the replay at 2h
    fills time the planning would wait anyway (`plan --no-compare` 1-5 % faster on four
    shipped scenes, the trajectories byte for byte the same,
    benchmarks/results/prediction_in_process.md). `background`: a helper process of its own
    while the pass runs."""
    if not predicts_aim(scenario, verify):
        return nullcontext(None)
    return replays_for(replay_scenario(scenario, verify=False), background, **replay_options(options))


def simulate_with_estimate(scenario: Scenario, center_path: np.ndarray | None = None, estimate: bool = True,
                           on_step=None, replays: InlineReplays | None = None,
                           **options) -> tuple[InsertionResult, ExitEstimate | None]:
    """run_insertion, and (with `estimate`) its exit error estimate from a run at 2h, by
    `replays` on the 2h model (estimate_replays; started before this run) when given."""
    if estimate and replays is not None:
        replays.submit(center_path)
    result = run_insertion(scenario, center_path=center_path, on_step=on_step, **options)
    if not estimate:
        return result, None
    return result, estimate_exit_error(scenario, result, center_path, replays=replays, **options)


def predicted_offset(scenario: Scenario, planned: InsertionResult, predictions: InlineReplays | None = None,
                     **options) -> np.ndarray | None:
    """The refined model's offset e(h/2) - e(h) of the exit-error vector for the planned
    run's trajectory, predicted from its replay at 2h (by `predictions`, prediction_replays's,
    when given) as (e(h) - e(2h)) / PREDICTED_RATIO; None when the model at 2h cannot replay it."""
    try:
        coarse = predictions or InlineReplays(replay_scenario(scenario, verify=False), **replay_options(options))
        replayed = coarse.replay(exported_centers(planned))
    except (InputError, NumericalFailure) as error:
        log.info("verification: no predicted offset, the model at twice the spacing failed (%s)", error)
        return None
    return (planned.exit_error_vector_mm - replayed.exit_error_vector_mm) / PREDICTED_RATIO


def exit_offset(replayed: InsertionResult, planned: InsertionResult) -> np.ndarray:
    """The refined model's exit offset delta = e_refined - e_base for the same trajectory (the
    module docstring): what the passes aim by."""
    return replayed.exit_error_vector_mm - planned.exit_error_vector_mm


def replay(replays: InlineReplays, centers: np.ndarray) -> tuple[InsertionResult | None, str | None]:
    """The centre path replayed, or None and why: the tip does not leave the tissue within it,
    or the refined model fails on it (the plan stands, its verification unknown)."""
    try:
        return replays.replay(centers), None
    except InputError as error:  # the path ends before the tip exits on this model
        log.info("verification replay: %s", error)
        return None, ENDS_BEFORE_EXIT
    except NumericalFailure as error:  # the refined model fails where the planning model did not
        reason = f"the replay on the refined model failed ({error})"
        log.info("verification replay: %s", reason)
        return None, reason


def _verified_miss(replayed: InsertionResult | None, symmetric: bool) -> float:
    """What a round is judged by on the refined model: the exit error, or with the symmetric
    target the bites' difference (mm); inf when the trajectory could not be replayed."""
    if replayed is None or (symmetric and replayed.bites is None):
        return np.inf
    return abs(replayed.bites["difference_mm"]) if symmetric else replayed.exit_error_mm


def plan_verified(scenario: Scenario, compare: bool = True, verify: bool = True, on_step=None,
                  replays: InlineReplays | None = None, predictions: InlineReplays | None = None,
                  **options) -> PlanResult:
    """run_plan, then (with `verify`) the exported trajectory replayed on the refined model
    and, where needed, the passes re-aimed by the refined model's offset (module docstring).
    The plan's `verification` is set (with `verify`), and its `estimate`, the exit error
    estimate of the planned run: from the refined replay, or without `verify` from a replay
    of the trajectory at 2h. `replays`: plan_replays's, which replay each planner pass while
    the planning goes on; by default the replays run here after it. `predictions`:
    prediction_replays's, which replay the first pass at 2h for the predicted aim; by default
    that replay runs here after the pass."""
    tissue = PreparedTissue(scenario)  # shared by the plan's runs and the re-planning rounds
    other = replay_scenario(scenario, verify)
    replays = replays or InlineReplays(other, **replay_options(options))  # one model for every round
    predict = predicts_aim(scenario, verify)
    prediction = _PredictedAim(scenario, replays, predictions if predict else None, options)
    result = run_plan(scenario, compare=compare, on_step=on_step, tissue=tissue, stream=prediction.tee or replays,
                      retarget=prediction.retarget if predict else None, **options)
    # planner.target symmetric on a stitch across a wound: the bites' difference is judged (and
    # re-aimed on the refined model) as the exit error is otherwise
    symmetric = scenario.planner.target == "symmetric" and result.planned.bites is not None
    if not verify:
        return _estimated(scenario, result, replays, symmetric, **options)
    rounds = _VerificationRounds(scenario, result, tissue, replays, symmetric, on_step, options)
    miss, replayed = rounds.verify(1, "predicted offset" if prediction.aimed else "none", prediction.offset)
    for number in range(2, MAX_CORRECTIONS + 2):  # the re-aimed rounds
        # no replay, or (symmetric) a refined track that does not cross the wound: nothing to re-aim by
        if not np.isfinite(miss) or miss <= VERIFIED_FACTOR * scenario.planner.exit_tolerance:
            break
        if not rounds.re_plan(number, replayed):  # its passes failed: the best round so far stands
            break
        miss, replayed = rounds.verify(number, "refined offset")
    return rounds.exported(other.discretization.spacing)


class _PredictedAim:
    """plan_verified's run_plan `retarget`: after the first pass, the passes aimed at -delta
    where the refined replay is predicted to miss (the module docstring, predicted aim), with
    the first pass's centres handed to `predictions` (prediction_replays's; None: no
    prediction, or its replay runs here after the pass) beside the refined model's replays."""

    def __init__(self, scenario: Scenario, replays: InlineReplays, predictions: InlineReplays | None, options: dict):
        self.scenario, self.replays, self.predictions, self.options = scenario, replays, predictions, options
        self.tee = StreamTee(replays, predictions) if predictions is not None else None
        self.offset: np.ndarray | None = None  # the predicted offset
        self.aimed = False  # whether the passes were aimed by it

    def retarget(self, first_pass: InsertionResult) -> tuple[np.ndarray, float] | None:
        """(aim, tolerance) for the passes after `first_pass`, or None to keep theirs."""
        if self.tee is not None:
            self.tee.replays = (self.replays,)  # the later passes: the refined model's replays only
        offset = predicted_offset(self.scenario, first_pass, self.predictions, **self.options)
        if offset is None:
            return None
        self.offset = offset
        tolerance = self.scenario.planner.exit_tolerance
        if np.linalg.norm(first_pass.exit_error_vector_mm + offset) <= VERIFIED_FACTOR * tolerance:
            return None  # the refined replay is predicted to pass
        self.aimed = True
        log.info("verification: refined model's exit offset predicted from 2h (%.4g, %.4g) mm; the passes aim at "
                 "(%.4g, %.4g) mm", *offset, *-offset)
        return -offset, AIMED_TOLERANCE_FRACTION * tolerance


def _estimated(scenario: Scenario, result: PlanResult, replays: InlineReplays, symmetric: bool,
               **options) -> PlanResult:
    """An unverified plan with its exit error estimate from the replay at 2h, and an event
    where it misses the target on the planning model."""
    result.estimate = estimate_exit_error(scenario, result.planned, result.exported_centers, replays=replays,
                                          **options)
    _note_missed(result, _verified_miss(result.planned, symmetric), scenario.planner.exit_tolerance,
                 "on the planning model", symmetric, result.stopped)
    return result


class _Round(NamedTuple):
    """A verification round: its miss on the refined model (_verified_miss), its plan, the replay, its record."""

    miss: float
    plan: PlanResult
    replayed: InsertionResult | None
    record: dict


class _VerificationRounds:
    """plan_verified's rounds: each round's plan replayed on the refined model and recorded,
    the best round so far, and the planning time of every pass of every round."""

    def __init__(self, scenario: Scenario, result: PlanResult, tissue: PreparedTissue, replays: InlineReplays,
                 symmetric: bool, on_step, options: dict):
        self.scenario, self.settings, self.tissue, self.replays = scenario, scenario.planner, tissue, replays
        self.symmetric, self.on_step, self.options = symmetric, on_step, options
        self.result = result  # the latest round's plan
        for record in result.passes:
            record["round"] = 1
        self.planning_seconds, self.planning_timings = result.planned.wall_seconds, dict(result.planned.timings)
        self.records: list[dict] = []  # Verification.rounds
        self.best: _Round | None = None

    def verify(self, number: int, aimed_by: str,
               predicted: np.ndarray | None = None) -> tuple[float, InsertionResult | None]:
        """Round `number`'s plan replayed on the refined model (started from the round
        before's) and recorded; its miss there and the replay."""
        planned = self.result.planned
        replayed, no_replay = replay(self.replays, self.result.exported_centers)
        verified = _round_record(number, aimed_by, planned, replayed, no_replay)
        if predicted is not None:
            verified["predicted_offset_mm"] = predicted.tolist()
        if self.symmetric:
            verified["planned_bite_difference_mm"] = planned.bites["difference_mm"]
            verified["verified_bite_difference_mm"] = (None if replayed is None or replayed.bites is None
                                                       else replayed.bites["difference_mm"])
        self.records.append(verified)
        miss = _verified_miss(replayed, self.symmetric)
        log.info("verification round %d: planned exit error %.4g mm, on the refined model %.4g mm%s",
                 number, planned.exit_error_mm, np.inf if replayed is None else replayed.exit_error_mm,
                 f" (bite difference {miss:.4g} mm)" if self.symmetric else "")
        if self.best is None or miss < self.best.miss:
            self.best = _Round(miss, self.result, replayed, verified)
        return miss, replayed

    def re_plan(self, number: int, replayed: InsertionResult) -> bool:
        """Round `number`'s plan: the passes re-aimed by the refined model's offset, going on
        with the secant of the passes before; False when they fail (the best round so far stands)."""
        aim, bite_aim = self._aim_by_offset(replayed)
        round_start = time.perf_counter()
        try:
            again = run_plan(self.scenario, compare=False, on_step=self.on_step, aim=aim, shooting=self.result.shooting,
                             tolerance=AIMED_TOLERANCE_FRACTION * self.settings.exit_tolerance, tissue=self.tissue,
                             bite_aim=bite_aim, stream=self.replays, **self.options)
        except PlanningFailure:  # --strict
            raise
        except NumericalFailure as failure:
            self.planning_seconds += time.perf_counter() - round_start  # spent on the plan all the same
            message = (f"verification round {number}: its re-aimed planner pass failed ({failure}); "
                       f"the best of the {number - 1} round{'s' if number > 2 else ''} before it is exported")
            self.best.plan.planned.events.append(Event(EventKind.PASS_FAILED, message))
            log.info(message)
            return False
        self.planning_seconds += again.planned.wall_seconds
        add_timings(self.planning_timings, again.planned.timings)
        for record in again.passes:
            record["round"] = number
        result = self.result
        self.result = PlanResult(again.planned, result.unplanned, result.passes + again.passes, again.shooting,
                                 lean=again.lean.after(result.lean) if again.lean else None, stopped=again.stopped)
        return True

    def _rounds_moved(self) -> str:
        """Why a plan whose passes met their aim on the planning model still misses on the
        refined one: that model's offset changed from round to round (each round's miss there)."""
        key = "verified_bite_difference_mm" if self.symmetric else "verified_exit_error_mm"
        misses = ", ".join("none" if record.get(key) is None else f"{abs(record[key]):.3g}" for record in self.records)
        return (f"the passes met their aim on the planning model, but the refined model's offset changed from round "
                f"to round (its miss {misses} mm over the {len(self.records)} rounds)")

    def _aim_by_offset(self, replayed: InsertionResult) -> tuple[np.ndarray, float]:
        """The re-aimed passes' aim of the exit error vector and of the bites' difference
        (run_plan `aim`, `bite_aim`): minus the refined model's offset (the module docstring)."""
        planned = self.result.planned
        if self.symmetric:
            bite_offset = replayed.bites["difference_mm"] - planned.bites["difference_mm"]
            bite_aim = -bite_offset
            log.info("verification: refined model's bite-difference offset %.4g mm; re-planning aimed at "
                     "a difference of %.4g mm", bite_offset, bite_aim)
            return symmetric_aim(planned, bite_aim), bite_aim
        offset = exit_offset(replayed, planned)
        aim = -offset
        log.info("verification: refined model's exit offset (%.4g, %.4g) mm; re-planning aimed at "
                 "(%.4g, %.4g) mm", *offset, *aim)
        return aim, 0.0

    def exported(self, spacing: float) -> PlanResult:
        """The best round's plan, its wall time and timings every pass of every round's (the
        failed ones' too), with its verification and exit error estimate."""
        best = self.best
        best.plan.planned.wall_seconds, best.plan.planned.timings = self.planning_seconds, self.planning_timings
        if np.isfinite(best.miss):
            _note_missed(best.plan, best.miss, VERIFIED_FACTOR * self.settings.exit_tolerance,
                         f"on the refined model (spacing {spacing:.4g} mm)", self.symmetric,
                         best.plan.stopped or self._rounds_moved())
        verification = Verification(spacing, best.replayed, self.records, self.replays.where, best.record["aimed_by"],
                                    best.record.get("no_replay"))
        return _verified(self.scenario, best.plan, verification, **self.options)


def _note_missed(result: PlanResult, miss: float, accepted: float, where: str, symmetric: bool,
                 why: str | None) -> None:
    """An event on the exported plan when even its best pass misses the target by more than
    `accepted` mm (the planner's exit_tolerance, or 1.5 x it on the refined model): the
    trajectory is still written, the best found, and the summary and the stderr note say so,
    and `why`: what its passes did (planner.PlanResult.stopped)."""
    if miss <= accepted:
        return
    what = f"its bites differ by {miss:.4g} mm" if symmetric else f"the tip exits {miss:.4g} mm from the desired exit"
    message = (f"plan: {what} {where}, above the {accepted:.4g} mm accepted, after {len(result.passes)} planner "
               f"passes: the best trajectory found is exported; {why or 'see planner_passes in the summary'}")
    result.planned.events.append(Event(EventKind.TARGET_MISSED, message))
    log.info(message)


def verify_exported(scenario: Scenario, result: PlanResult, **options) -> PlanResult:
    """A plan made elsewhere (the re-aimed robust plan under uncertainty, aimed by the nominal
    plan's refined offset) checked as plan_verified checks its own: the exported trajectory
    replayed on the refined model at the scenario's values, once (not re-aimed by it), giving
    the plan's `verification` and `estimate`."""
    other = replay_scenario(scenario, verify=True)
    replays = InlineReplays(other, **replay_options(options))
    try:
        replayed, no_replay = replay(replays, result.exported_centers)
    finally:
        replays.close()
    log.info("verification: the exported plan's exit error %.4g mm, on the refined model %.4g mm",
             result.planned.exit_error_mm, np.inf if replayed is None else replayed.exit_error_mm)
    rounds = [_round_record(1, "none", result.planned, replayed, no_replay)]
    return _verified(scenario, result, Verification(other.discretization.spacing, replayed, rounds,
                                                    replays.where, "none", no_replay), **options)


def _round_record(number: int, aimed_by: str, planned: InsertionResult, replayed: InsertionResult | None,
                  no_replay: str | None = None) -> dict:
    """A verification round's record: what aimed its plan, the planned and verified errors
    (and, without a replay, why: replay's reason)."""
    record = {"round": number, "aimed_by": aimed_by, "planned_exit_error_mm": planned.exit_error_mm,
              "verified_exit_error_mm": None if replayed is None else replayed.exit_error_mm,
              "replay_wall_seconds": None if replayed is None else replayed.wall_seconds}
    if no_replay is not None:
        record["no_replay"] = no_replay
    return record


def _verified(scenario: Scenario, result: PlanResult, verification: Verification, **options) -> PlanResult:
    """The plan with its `verification` and the exit error estimate from the refined replay
    (from a replay at 2h where the exported trajectory ends before the tip leaves the refined
    model, which an event says)."""
    result.verification = verification
    if verification.result is None:
        why = verification.no_replay or ENDS_BEFORE_EXIT
        message = f"verification: {why} (spacing {verification.spacing_mm:.4g} mm); verified exit error unknown"
        result.planned.events.append(Event(EventKind.ACCURACY_CHECK, message))
        log.info(message)
        result.estimate = estimate_exit_error(scenario, result.planned, result.exported_centers, **options)
    else:
        result.estimate = estimate_from(result.planned, verification.result, VERIFICATION_FACTOR,
                                        verification.spacing_mm)
    return result
