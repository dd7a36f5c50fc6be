"""What each command's resource guard counts (options._guard): its runs, the replays that go
on alongside them and where they run, so that a refusal names the file, the option or the
study field that set each one."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from .options import estimate_run, guard_runs


def guard_simulate(scenario_path: Path, limits, names: dict, scenario, estimate: bool,
                   linear_solver: Optional[str] = None, condition_numbers: bool = False) -> None:
    """simulate's run (with its dense `condition_numbers`), and with `estimate` its replay at
    twice the spacing in a helper."""
    guard_runs(scenario_path, limits, ("insertion", scenario, "simulate", 1), names=names, linear_solver=linear_solver,
               condition_numbers=condition_numbers,
               alongside=[estimate_run(scenario, "exit error estimate", "pass --no-estimate to skip the estimate",
                                       names)] if estimate else [])


def guard_plan(scenario_path: Path, limits, names: dict, scenario, verify: bool, compare: bool,
               linear_solver: Optional[str] = None) -> None:
    """plan's runs on its model (its unplanned comparison with `compare`), the verification's
    replays on the refined model, and a replay at twice the spacing alongside: the predicted
    aim's (in this process), or without the verification the exit error estimate's (in a
    helper)."""
    from ..planning.replay_models import predicts_aim
    from ..resources.costs import PLAN_RUNS, VERIFICATION_RUNS

    at_2h = [] if verify and not predicts_aim(scenario, verify) else [estimate_run(
        scenario, "plan's replay at twice the spacing",
        "set planner.predicted_aim: false to skip the predicted aim" if verify else "", names)]
    guard_runs(scenario_path, limits, ("insertion", scenario, "plan", PLAN_RUNS + compare),
               *_verification(scenario, names, VERIFICATION_RUNS, verify), names=names,
               linear_solver=linear_solver, alongside=at_2h)


def guard_plan_under_uncertainty(scenario_path: Path, limits, names: dict, scenario, verify: bool, tasks: int,
                                 workers: Optional[int], linear_solver: Optional[str] = None) -> None:
    """plan --uncertainty's runs (its plans and `tasks` sampled runs) and its verification's,
    beside a sampled plan's runs on each of a local cluster's `workers` (None: a scheduler's,
    elsewhere, not counted)."""
    from ..resources.costs import PLAN_RUNS, VERIFICATION_RUNS
    from ..resources.origin import Origin

    # a local cluster's workers each hold a sampled plan's runs while this process holds its own
    workers = workers or 0
    on_workers = Origin(dict(names), skip="pass --workers with fewer workers" if workers > 1 else "")
    guard_runs(scenario_path, limits, ("insertion", scenario, "plan --uncertainty", 2 * PLAN_RUNS + 1 + tasks),
               *_verification(scenario, names, VERIFICATION_RUNS + 1, verify), names=names, linear_solver=linear_solver,
               alongside=[("insertion", scenario, f"worker {k + 1} of {workers}: sampled plans", PLAN_RUNS, on_workers)
                          for k in range(workers)], forked=False)


def _verification(scenario, names: dict, count: int, verify: bool) -> list[tuple]:
    """The plan verification's `count` replays on the refined model, as a run of guard_runs's
    (none without `verify`)."""
    if not verify:
        return []
    from ..planning.replay_models import replay_scenario
    from ..resources.origin import verification_origin

    return [("insertion", replay_scenario(scenario, verify=True), "plan verification", count,
             verification_origin(scenario, names))]


def guard_study(scenario_path: Path, limits, runs: list, reference, repeats: int, workers: Optional[int]) -> None:
    """A study's runs, each `repeats` times, and its reference run, once (as run_study runs
    it); a refusal names the study field that set the run's spacing. On a local cluster its
    `workers` run as many at once, each in a process of its own (None: a scheduler's workers,
    elsewhere; 0: one after another here)."""
    from ..resources.origin import Origin

    def origin(run) -> Origin:
        return Origin({"spacing": run.source, "needle_spacing": run.source, **run.fields},
                      {"spacing": run.spacing, "needle_spacing": run.spacing})

    guard_runs(scenario_path, limits, *[("insertion", run.scenario, f"study run {run.label!r}", count, origin(run))
                                        for run, count in [*((run, repeats) for run in runs), (reference, 1)]],
               alongside=[] if workers else None, forked=False, workers=workers or None)
