"""One configured insertion, run and timed: what the study's sweep (stitchplan.study.sweep)
and the auto discretization's selection (stitchplan.study.auto) both do, many times.

A run that fails is recorded with its reason, never raised: a sweep wants every row, and
the selection wants to know which configurations it cannot use. Only the failures a
configuration can cause are caught (RUN_FAILURES); anything else is a bug and escapes.

Exit points are compared with `exit_deviations` (stitchplan.planning.verification, as the
exit error estimate compares them); see stitchplan.study.sweep for why three ways.
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..config import Scenario
from ..errors import InputError
from ..events import Event, EventKind
from ..needle.insertion import run_insertion
# what a run may end with because of its configuration (recorded with its reason): the
# project's errors, degenerate linear algebra, a model too big for the machine; shared
# with the sampled runs of `plan --uncertainty`
from ..parallel.failures import RUN_FAILURES
from ..resources.model_size import model_size

if TYPE_CHECKING:
    from ..needle.results import InsertionResult

log = logging.getLogger(__name__)

# how a run's reason starts where its scenario was refused (a discretization that makes no
# model): the study tells a sweep whose every run was refused from one whose methods failed
REFUSED = f"{InputError.__name__}: "


@dataclass
class InsertionRun:
    """One configured insertion of a study or of the auto selection, with its timing and
    outcome (filled in by `run_timed`)."""

    family: str  # the sweep's method family; the auto selection's purpose ("resolution", ...)
    label: str
    scenario: Scenario
    spacing: float  # particle spacing at the needle, mm
    particles: int = 0
    wall_seconds: float = math.nan  # the insertion's own wall time (median over repeats)
    cpu_seconds: float = math.nan
    status: str = "ok"  # "ok" or "failed"
    reason: str = ""  # "<exception type>: <message>" when failed
    result: InsertionResult | None = None  # when ok

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def tip_tracking(self) -> str:
        return self.scenario.needle.tip_tracking

    @property
    def linear_solver(self) -> str:
        return self.scenario.needle.linear_solver


def count_particles(scenario: Scenario) -> int:
    """Particles of the scenario's discretization, without building shape functions (the
    resource guard's count: exact for the needle scenes a study runs)."""
    return model_size(scenario).particles


def run_timed(run: InsertionRun, repeats: int = 1) -> InsertionRun:
    """Run the insertion (`repeats` times for the timing medians) and fill in `run`; a
    failure (RUN_FAILURES) is recorded with its reason, never raised. Returns `run`."""
    try:
        run.particles = count_particles(run.scenario)  # known even when the run fails
    except RUN_FAILURES:
        run.particles = 0
    walls, cpus = [], []
    for repeat in range(repeats):
        # -v's step lines follow this one (a run in this process; a worker's log stays there)
        log.info("study run %s: %d particles%s", run.label, run.particles,
                 f", timing repeat {repeat + 1} of {repeats}" if repeats > 1 else "")
        start, cpu = time.perf_counter(), time.process_time()
        try:
            result = run_insertion(run.scenario)
        except RUN_FAILURES as error:
            run.status, run.reason = "failed", f"{type(error).__name__}: {error}"
            run.wall_seconds = time.perf_counter() - start
            run.cpu_seconds = time.process_time() - cpu
            run.result = None
            log.info("run %s failed: %s", run.label, run.reason)
            return run
        walls.append(result.wall_seconds)
        cpus.append(time.process_time() - cpu)
        run.result = result
    run.particles = run.result.model.n_particles
    run.wall_seconds, run.cpu_seconds = statistics.median(walls), statistics.median(cpus)
    return run


def events_of(result: InsertionResult, kind: EventKind) -> list[Event]:
    """The run's events of one kind (e.g. EventKind.MINRES_FALLBACK), in order."""
    return [event for event in result.events if event.kind is kind]
