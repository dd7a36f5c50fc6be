"""One sampled run: a needle-centre path replayed on a scenario with sampled parameters, as
a Dask task. The task function is top-level and returns a small record (no model, no
displacement history), so it pickles cheaply and a worker anywhere can run it.

A run that fails (parallel.failures.RUN_FAILURES: a numerical failure, a replayed path that
ends before the tip leaves the tissue) is recorded with its reason, never raised."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import Scenario
from ..needle.insertion import run_insertion
from ..parallel.failures import RUN_FAILURES

log = logging.getLogger(__name__)

NAN2 = (math.nan, math.nan)


@dataclass(frozen=True)
class SampleRun:
    """The exit of one run (mm, deformed configuration), or why there is none."""

    exit_error: np.ndarray = field(default_factory=lambda: np.array(NAN2))  # achieved - desired exit
    achieved_exit_def: np.ndarray = field(default_factory=lambda: np.array(NAN2))
    reason: str = ""  # "<exception type>: <message>" when the run failed
    wall_seconds: float = math.nan
    steps: int = 0
    newton_iterations: int = 0

    @property
    def ok(self) -> bool:
        return not self.reason


def run_sample(scenario: Scenario, centers: np.ndarray | None, options: dict | None = None) -> SampleRun:
    """The insertion of `scenario` with the centre path `centers` (n, 2) replayed (None: the
    centre fixed, the unplanned needle); `options` go to run_insertion."""
    start = time.perf_counter()
    try:
        result = run_insertion(scenario, center_path=centers, **(options or {}))
    except RUN_FAILURES as error:
        reason = f"{type(error).__name__}: {error}"
        log.info("sampled run failed: %s", reason)
        return SampleRun(reason=reason, wall_seconds=time.perf_counter() - start)
    return SampleRun(result.exit_error_vector_mm, np.asarray(result.achieved_exit_def, dtype=float),
                     wall_seconds=result.wall_seconds, steps=len(result.steps),
                     newton_iterations=int(sum(s.newton_iterations for s in result.steps)))
