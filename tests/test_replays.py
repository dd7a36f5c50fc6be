"""Replays on a second model by a helper process (planning/replays.py) give what the same
replays give in this process, bit for bit: a verified plan with several passes and rounds,
the error estimate of a plan and of `simulate`, a trajectory that was not the last one
streamed, a path that ends before the tip exits, and a helper that dies.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_verification import scene_raw

from stitchplan.config.scenario import parse_scenario
from stitchplan.errors import InputError
from stitchplan.io.reports import discretization_summary
from stitchplan.needle.geometry import scenario_needle
from stitchplan.planning.replays import BackgroundReplays, InlineReplays, helper_available, replays_for
from stitchplan.planning.replay_models import rescaled
from stitchplan.planning.verification import plan_replays, plan_verified, simulate_with_estimate
from stitchplan.planning.trajectory import exported_center



@pytest.fixture(scope="module")
def scenario():
    """A small block where the plan takes two passes in a round and three verification rounds."""
    return parse_scenario(scene_raw(20.0, 18.0, 5.0, 0.3, planner={"max_passes": 2}))


def _plan(scenario, verify: bool, kind):
    """The plan with its replays (and with `verify` the predicted aim's at 2h) made by `kind`."""
    factor = 0.5 if verify else 2.0
    replays = kind(rescaled(scenario, factor))
    predictions = kind(rescaled(scenario, 2.0)) if verify else None
    try:
        return plan_verified(scenario, compare=False, verify=verify, replays=replays,
                             predictions=predictions), replays
    finally:
        replays.close()
        if predictions is not None:
            predictions.close()


def _fingerprint(plan) -> dict:
    verification = plan.verification
    return {"centers": plan.exported_centers.tolist(), "planned": plan.planned.exit_error_mm,
            "passes": [(p["pass"], p.get("round"), p["exit_error_mm"]) for p in plan.passes],
            "rounds": None if verification is None else [(r["round"], r["verified_exit_error_mm"])
                                                         for r in verification.rounds],
            "verified": None if verification is None else verification.result.achieved_exit_def.tolist(),
            "refined model": None if verification is None else discretization_summary(verification.result.model),
            "estimate": plan.estimate.as_record()}


@pytest.mark.parametrize("verify", [True, False])
def test_a_plan_verified_by_the_helper_is_the_plan_verified_here(scenario, verify):
    (here, _), (helper, replays) = _plan(scenario, verify, InlineReplays), _plan(scenario, verify, BackgroundReplays)
    assert _fingerprint(helper) == _fingerprint(here)
    # each pass streamed once, and at most one whole replay a round (its kept pass not its last)
    rounds = len(here.verification.rounds) if verify else 1
    assert len(here.passes) <= replays.jobs <= len(here.passes) + rounds
    if verify:
        assert (here.verification.replayed_in, helper.verification.replayed_in) == ("this process",
                                                                                 "helper process")
    if verify:  # the rounds, passes and predicted aim this test is for
        assert len(here.verification.rounds) > 1 and len({p["pass"] for p in here.passes}) > 1
        assert here.verification.rounds[0]["aimed_by"] == "predicted offset"


def _fixed_path(scenario, rows: int, shift: float = 0.0) -> np.ndarray:
    center = exported_center(scenario_needle(scenario).center + np.array([shift, 0.0]))
    return np.repeat(center[None], rows, axis=0)


def _stream(replays, path: np.ndarray) -> None:
    replays.begin(path[0])
    for step in range(1, len(path) - 1):
        replays.row(step, path[step])
    replays.end(path)


def _after_two_passes(scenario, replay_first: bool):
    """Two passes streamed to a helper on the refined model, then one of them asked for:
    (the refined scenario, the path asked for, its replay, the closed helper)."""
    fine = rescaled(scenario, 0.5)
    first, second = _fixed_path(fine, 40), _fixed_path(fine, 40, shift=0.05)
    asked = first if replay_first else second
    helper = BackgroundReplays(fine)
    try:
        _stream(helper, first)
        _stream(helper, second)
        return fine, asked, helper.replay(asked), helper
    finally:
        helper.close()


def test_a_trajectory_streamed_before_another_is_replayed_whole(scenario):
    """The best of several passes need not be the last: its replay is run when asked for."""
    fine, first, replayed, _ = _after_two_passes(scenario, replay_first=True)
    expected = InlineReplays(fine).replay(first)
    assert replayed.achieved_exit_def.tolist() == expected.achieved_exit_def.tolist()
    assert [s.center.tolist() for s in replayed.steps] == [s.center.tolist() for s in expected.steps]


def test_the_helper_sends_a_replay_without_its_model_s_matrices(scenario):
    """A replay comes back with the outline of its model, which is what the summaries read:
    the model's operators and shape functions took ~0.1 s to pickle, send and load at the end
    of a verified plan on SH 1/2's refined model (29 MB)."""
    import pickle

    from stitchplan.tissue.model import ModelOutline

    fine, first, replayed, _ = _after_two_passes(scenario, replay_first=False)
    expected = InlineReplays(fine).replay(first)
    assert isinstance(replayed.model, ModelOutline)
    assert discretization_summary(replayed.model) == discretization_summary(expected.model)
    assert len(pickle.dumps(replayed)) < 0.2 * len(pickle.dumps(replace(expected, states=[])))


def test_a_dropped_pass_stops_at_the_next_step(scenario):
    """A pass the planner drops (the next one began) is not replayed to its end: the helper
    reads what has come at every step. Both passes are sent while it still builds its model,
    so it meets the second at the first step of the first."""
    _, _, replayed, helper = _after_two_passes(scenario, replay_first=False)
    assert len(replayed.steps) > 5 and helper.jobs == 2
    assert helper.steps_run <= len(replayed.steps) + 1, helper.steps_run


def _streamed_in_two(scenario, shared: int, rows: int = 40):
    """A pass streamed up to row 4 and left open, then a second pass from the same start
    that agrees with it on rows 0 .. shared - 1: (the refined scenario, the second pass,
    its replay by the helper, the closed helper)."""
    fine = rescaled(scenario, 0.5)
    first = _fixed_path(fine, rows)
    second = first.copy()
    second[shared:] += np.array([0.05, 0.0])
    helper = BackgroundReplays(fine)
    try:
        helper.begin(first[0])
        for step in range(1, 5):
            helper.row(step, first[step])
        time.sleep(1.0)  # the helper builds its model and replays what has come
        _stream(helper, second)
        return fine, second, helper.replay(second), helper
    finally:
        helper.close()


@pytest.mark.parametrize("shared", [7, 2])
def test_a_pass_that_keeps_the_first_steps_of_the_one_before_is_replayed_alike(scenario, shared):
    """A re-aimed pass keeps the earlier pass's first steps (planning.pass_offsets.PassPrefix): the
    helper goes on with it where the centres it has used agree, and starts again where they
    do not (shared = 2: the helper may have replayed up to row 4 of the first pass). Either way
    the replay is the second pass's, as this process replays it."""
    fine, second, replayed, helper = _streamed_in_two(scenario, shared)
    expected = InlineReplays(fine).replay(second)
    assert replayed.achieved_exit_def.tolist() == expected.achieved_exit_def.tolist()
    assert [s.center.tolist() for s in replayed.steps] == [s.center.tolist() for s in expected.steps]
    assert helper.jobs == 2
    if shared == 7:  # never more steps than the second pass's own: nothing was replayed twice
        assert helper.steps_run <= len(replayed.steps) + 1, helper.steps_run


def test_a_dropped_replay_gives_its_steps_to_the_pass_that_dropped_it(scenario):
    """The helper's streamed replay of a first pass has done four steps when a second pass
    from the same start arrives that leaves the first pass's centres at step 2: the replay is
    dropped with the steps it had done (InsertionStopped), and the second pass's replay takes
    step 1 over from them (no Newton iteration), to the last bit the replay made here alone.
    The messages come in the order the helper reads them (planning.replays.serve)."""
    from collections import deque

    from stitchplan.needle.prepared_tissue import PreparedTissue
    from stitchplan.needle.insertion import run_insertion
    from stitchplan.planning.replays import _StreamedPath, _Superseded

    fine = rescaled(scenario, 0.5)
    first = _fixed_path(fine, 40)
    second = first.copy()
    second[2:] += np.array([0.05, 0.0])
    arriving = deque([*(("row", 1, step, first[step]) for step in range(1, 5)), ("stream", 2, None, second[0]),
                      *(("row", 2, step, second[step]) for step in range(1, len(second) - 1)),
                      ("end", 2, second)])
    inbox: deque = deque()

    def receive():
        return inbox.popleft() if inbox else arriving.popleft()

    def pending():  # nothing new has come while a step was solved
        return bool(inbox)

    tissue = PreparedTissue(fine)
    with pytest.raises(_Superseded) as dropped:
        run_insertion(fine, control=_StreamedPath(receive, pending, inbox, ("stream", 1, None, first[0])),
                      tissue=tissue)
    done = dropped.value.done
    assert [s.center.tolist() for s in done.steps] == first[1:5].tolist()
    again = _StreamedPath(receive, pending, inbox, receive())  # the second pass's messages, kept
    assert again.job == 2
    replayed = run_insertion(fine, control=again, tissue=tissue, start_from=done, take_over_only=True)
    expected = InlineReplays(fine).replay(second)
    assert replayed.steps[0].newton_iterations == 0 and replayed.steps[1].newton_iterations > 0
    assert replayed.achieved_exit_def.tolist() == expected.achieved_exit_def.tolist()
    assert [s.center.tolist() for s in replayed.steps] == [s.center.tolist() for s in expected.steps]


def test_a_path_that_ends_before_the_exit_fails_alike(scenario):
    short = _fixed_path(scenario, 3)
    messages = []
    for kind in (InlineReplays, BackgroundReplays):
        replays = kind(scenario)
        try:
            _stream(replays, short)
            with pytest.raises(InputError) as failure:
                replays.replay(short)
            messages.append(str(failure.value))
        finally:
            replays.close()
    assert messages[0] == messages[1] and "rows: got 3, expected one per step until the tip exits" in messages[0]


def test_a_failed_replay_is_reported_alike(scenario, monkeypatch):
    """A numerical failure of the second model's run comes back as the same error (the
    estimate then records it as an event), and anything else the helper meets is run again
    here, where it is raised as what it is."""
    import stitchplan.planning.replays as replays_module
    from stitchplan.errors import InsertionFailure
    from stitchplan.planning.verification import estimate_exit_error

    result = InlineReplays(scenario).replay(None)

    def failing(*args, **kwargs):
        raise InsertionFailure("step 3 (needle rotation 0.900 rad): Newton did not converge")

    monkeypatch.setattr(replays_module, "run_insertion", failing)  # the forked helper inherits it
    events = []
    for kind in (InlineReplays, BackgroundReplays):
        replays = kind(rescaled(scenario, 2.0))
        try:
            record = replace(result, events=[])
            assert estimate_exit_error(scenario, record, None, replays=replays) is None
            events.append([event.message for event in record.events])
        finally:
            replays.close()
    assert events[0] == events[1] and "Newton did not converge" in events[0][0]

    def bug(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(replays_module, "run_insertion", bug)
    helper = BackgroundReplays(scenario)
    try:
        with pytest.raises(ZeroDivisionError):
            helper.replay(None)
    finally:
        helper.close()


def test_the_replay_runs_here_when_the_helper_is_gone(scenario):
    path = _fixed_path(scenario, 40)
    helper = BackgroundReplays(scenario)
    try:
        helper._process.kill()
        helper._process.join()
        assert helper.where == "helper process"
        replayed = helper.replay(path)
        assert helper.where == "this process"
    finally:
        helper.close()
    expected = InlineReplays(scenario).replay(path)
    assert replayed.achieved_exit_def.tolist() == expected.achieved_exit_def.tolist()


def test_the_command_s_waiting_time_is_used_once_and_changes_no_replay(scenario):
    """`while_waiting` (the outputs' imports of `plan`) runs the first time the command waits
    for an answer that has not come, and not again; one that fails changes nothing."""
    path = _fixed_path(scenario, 40)
    expected = InlineReplays(scenario).replay(path).achieved_exit_def.tolist()
    for work in ("records", "fails"):
        calls = []

        def waiting():
            calls.append(work)
            if work == "fails":
                raise ImportError("no such library")

        helper = BackgroundReplays(scenario, while_waiting=waiting)
        try:
            first = helper.replay(path)  # submitted now: its answer cannot be there yet
            second = helper.replay(_fixed_path(scenario, 40, shift=0.1))
        finally:
            helper.close()
        assert calls == [work]
        assert first.achieved_exit_def.tolist() == expected
        assert second.achieved_exit_def.tolist() != expected


def test_simulate_estimate_by_the_helper_is_the_estimate_made_here(scenario):
    records = []
    for kind in (InlineReplays, BackgroundReplays):
        replays = kind(rescaled(scenario, 2.0))
        try:
            result, estimate = simulate_with_estimate(scenario, replays=replays)
        finally:
            replays.close()
        records.append((result.exit_error_mm, estimate.as_record()))
    assert records[0] == records[1]
    assert replays.jobs == 1  # the run submitted before the insertion is the one asked for


def test_the_helper_can_be_turned_off(scenario, monkeypatch):
    monkeypatch.setenv("STITCHPLAN_REPLAY_HELPER", "0")
    assert not helper_available()
    with replays_for(scenario) as replays, plan_replays(scenario) as verification:
        assert type(replays) is InlineReplays and type(verification) is InlineReplays


def test_the_helper_ends_when_the_main_process_is_killed(tmp_path):
    """A killed main process cannot close its helper; the helper must not go on replaying."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "main.py"
    script.write_text(
        "import sys, time\n"
        "sys.path.insert(0, sys.argv[1])\n"
        "from test_verification import scene_raw\n"
        "from stitchplan.config.scenario import parse_scenario\n"
        "from stitchplan.planning.replays import BackgroundReplays\n"
        "helper = BackgroundReplays(parse_scenario(scene_raw(20.0, 18.0, 0.5, 0.02)))\n"
        "helper.submit(None)\n"  # a replay of a minute or more: the helper reads no message meanwhile
        "print(helper._process.pid, flush=True)\n"
        "time.sleep(60)\n")
    main = subprocess.Popen([sys.executable, str(script), str(Path(__file__).parent)], stdout=subprocess.PIPE,
                            text=True)
    helper = int(main.stdout.readline())
    time.sleep(1.0)  # the helper is replaying
    main.send_signal(signal.SIGKILL)
    main.wait()
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and _running(helper):
        time.sleep(0.05)
    running = _running(helper)
    if running:
        os.kill(helper, signal.SIGKILL)
    assert not running


def _running(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie (an orphan is reaped by init)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not helper_available(), reason="no helper process on this machine")
def test_the_helper_forked_as_the_command_starts_gives_the_plan_made_without_it(tmp_path):
    """`stitchplan plan` forks its helper before its imports (stitchplan/early_helper.py) and
    hands it the refined model once its inputs are checked, before its own imports of the
    numerics: the trajectory and the verified and estimated errors are those of the replays
    made in the command's process."""
    import json
    import os
    import subprocess
    import sys

    scene = Path(__file__).resolve().parents[1] / "configs" / "needle20_entry30.yaml"
    outputs = {}
    for helper in ("1", "0"):
        folder = tmp_path / helper
        run = subprocess.run([sys.executable, "-m", "stitchplan", "plan", str(scene), "--no-compare", "--spacing", "6",
                              "--export", str(folder / "t.csv"), "--summary", str(folder / "s.json"), "-v"],
                             capture_output=True, text=True, env={**os.environ, "STITCHPLAN_REPLAY_HELPER": helper})
        assert run.returncode == 0, run.stderr
        summary = json.loads((folder / "s.json").read_text())
        outputs[helper] = ((folder / "t.csv").read_bytes(), summary["verified_exit_error_mm"],
                           summary["exit_error_estimate_mm"])
        forked_early = "forked as the command started" in run.stderr
        assert forked_early == (helper == "1"), run.stderr
        assert ("handed its scenario before the command's imports" in run.stderr) == (helper == "1")
        assert summary["verification"]["replayed_in"] == ("helper process" if helper == "1" else "this process")
    assert outputs["1"] == outputs["0"]


@pytest.mark.skipif(not helper_available(), reason="no helper process on this machine")
@pytest.mark.parametrize("handed", ["this model", "another model"])
def test_a_helper_handed_its_model_early_replays_it_as_one_handed_it_later(handed):
    """early_helper.hand sends the helper its model before the replays start (`plan`, once
    its inputs are checked); replays of that model use it as it is, and replays of another
    (the command changed its discretization after) end it and fork a helper of their own.
    Either way the replay is the one made in this process."""
    import subprocess
    import sys

    tests = Path(__file__).resolve().parent
    script = ("import logging, sys\n"
              f"sys.path.insert(0, {str(tests)!r})\n"
              "logging.basicConfig(level=logging.INFO)\n"
              "from stitchplan import early_helper\n"
              "early_helper.start_for(['plan', 'a.yaml', '--export', 't.csv'], 'stitchplan.planning.replays:serve')\n"
              "from test_replays import _fixed_path\n"
              "from test_verification import scene_raw\n"
              "from stitchplan.config.scenario import parse_scenario\n"
              "from stitchplan.planning.replay_models import rescaled\n"
              "from stitchplan.planning.replays import BackgroundReplays, InlineReplays\n"
              "scenario = parse_scenario(scene_raw(20.0, 18.0, 5.0, 0.3))\n"
              f"early_helper.hand(scenario if {handed == 'this model'} else rescaled(scenario, 2.0), {{}})\n"
              "helper = BackgroundReplays(scenario)\n"
              "path = _fixed_path(scenario, 40)\n"
              "replayed = helper.replay(path)\n"
              "where = helper.where\n"
              "helper.close()\n"
              "assert replayed.achieved_exit_def.tolist() == InlineReplays(scenario).replay(path).achieved_exit_def.tolist()\n"
              "print(where)\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "helper process"
    assert "handed its scenario before the command's imports" in run.stderr
    assert ("handed another model" in run.stderr) == (handed == "another model")


@pytest.mark.skipif(not helper_available(), reason="no helper process on this machine")
def test_a_helper_forked_for_no_replays_ends(tmp_path):
    """A command that ends before it asks for its replays (refused input) leaves no helper:
    it reads the end of its pipe once its imports are done. None is forked for --help, for a
    plan under uncertainty (its replays run on a cluster), a simulate without its estimate or
    for another command."""
    import subprocess
    import sys

    script = ("import sys\n"
              "from stitchplan import early_helper\n"
              "for arguments in (['plan', '--help'], ['plan', 'a.yaml', '--uncertainty', 'u.yaml'],\n"
              "                  ['plan', 'a.yaml', '--uncertainty=u.yaml'],\n"
              "                  ['simulate', 'a.yaml', '--no-estimate'], ['deform', 'a.yaml']):\n"
              "    early_helper.start_for(arguments, 'stitchplan.planning.replays:serve')\n"
              "    assert early_helper._started is None, arguments\n"
              "early_helper.start_for(['plan', 'a.yaml', '--export', 't.csv'], 'stitchplan.planning.replays:serve')\n"
              "print(early_helper._started[0], flush=True)\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    helper = int(run.stdout)
    deadline = time.monotonic() + 60.0  # its imports: ~0.3 s on an idle machine
    while time.monotonic() < deadline and _running(helper):
        time.sleep(0.05)
    assert not _running(helper)
