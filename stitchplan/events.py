"""Typed records of what happened during a run that a user should know about: a method that
fell back to another, a planner step that could not meet eq. 4.2, the discretization the
auto choice made. Results, summaries and the HDF5 log carry them as records; tests assert
on their fields, and the message is the sentence a person reads.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from enum import Enum


class EventKind(str, Enum):
    TIP_TRACKING_FALLBACK = "tip-tracking-fallback"  # inverse gradient jumped; Levenberg-Marquardt used
    MINRES_FALLBACK = "minres-fallback"  # MINRES stagnated; direct solve used
    PLANNER_NOT_CONVERGED = "planner-not-converged"  # centre iterations ran out within a step
    AUTO_DISCRETIZATION = "auto-discretization"  # what the accuracy target chose, and why
    PASS_FAILED = "planner-pass-failed"  # a planner pass after the first failed numerically; the best before it is kept
    PATH_LIMITS_EXCEEDED = "path-limits-exceeded"  # the exported centre path breaks the planner's move limits
    TARGET_MISSED = "target-missed"  # a plan's best pass still misses its target (exit or bites)
    TARGET_NOT_APPLICABLE = "target-not-applicable"  # planner.target symmetric on a needle crossing no wound: aimed at the exit
    CROSSING_MISSED = "crossing-missed"  # the tip did not make a crossing of the undeformed circle (a wound it passed by)
    WALL_CROSSED_BACK = "wall-crossed-back"  # a soft wound wall bulged round the tip: it crossed back to the side it left
    ACCURACY_CHECK = "accuracy-check"  # an exit error estimate or a verification could not be made, or an estimate is above the accuracy asked for


@dataclass(frozen=True)
class Event:
    kind: EventKind
    message: str
    step: int | None = None  # needle step (None: before or outside the steps)
    angle_rad: float | None = None  # needle rotation since entry at that step

    def as_record(self) -> dict:
        record = asdict(self)
        record["kind"] = self.kind.value
        return record

    def __str__(self) -> str:
        return self.message
