"""The sampled runs' cluster when it lets them down, and what `plan --uncertainty` says about
the sets it counts.

A cluster without a worker (none attached, or all lost) ends the run as one ClusterFailure
within the wait allowed (stitchplan.parallel.workers.WORKER_WAIT_S, cut here to about a
second), never as a hang; a Ctrl-C of the whole process group during a local-cluster run ends with the
command's exit code and nothing of the workers on stderr; and the console line and the
summary tie each failure count to its sample set. The cluster tests take a few seconds each.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_plan_cli import invoke, small_raw, write
from test_uncertainty import _failing_on, _thickness_only

from stitchplan.config import parse_scenario
from stitchplan.config.uncertainty import load_uncertainty
from stitchplan.errors import InputError
from stitchplan.parallel import executor as parallel_executor
from stitchplan.parallel import workers as parallel_workers
from stitchplan.parallel.executor import Executor
from stitchplan.parallel.failures import ClusterFailure
from stitchplan.parallel.signals import signals_deferred
from stitchplan.parallel.workers import worker_wait_seconds
from stitchplan.uncertainty.sampling import draw

WAIT = 1.0  # s: the wait for a worker in these tests
BOUND = 30.0  # s: a run that has not ended by then hangs
QUIET_SCHEDULER = {"dashboard_address": "127.0.0.1:0"}  # not 8787, which another cluster may hold


@pytest.fixture
def short_wait(monkeypatch):
    monkeypatch.setattr(parallel_workers, "WORKER_WAIT_S", WAIT)
    monkeypatch.setattr(parallel_executor, "WORKER_POLL_S", 0.2)
    monkeypatch.delenv(parallel_workers.WORKER_WAIT_VARIABLE, raising=False)


def bounded(run, seconds: float = BOUND):
    """run() in a thread: its exception or result, or a test failure if it has not ended
    within `seconds` (a hang would otherwise hold the test run forever)."""
    outcome: dict = {}

    def target():
        try:
            outcome["result"] = run()
        except BaseException as error:  # noqa: BLE001 -- handed to the test
            outcome["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still waiting after {seconds:g} s"
    if "error" in outcome:
        raise outcome["error"]
    return outcome["result"]


def sleeps(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


# --- the wait for workers ----------------------------------------------------------------------


def test_the_wait_for_workers_is_a_setting_in_seconds(monkeypatch):
    monkeypatch.delenv(parallel_workers.WORKER_WAIT_VARIABLE, raising=False)
    assert worker_wait_seconds() == parallel_workers.WORKER_WAIT_S == 60.0
    monkeypatch.setenv(parallel_workers.WORKER_WAIT_VARIABLE, "2.5")
    assert worker_wait_seconds() == 2.5
    for bad in ("0", "-1", "soon", "inf", "nan"):
        monkeypatch.setenv(parallel_workers.WORKER_WAIT_VARIABLE, bad)
        with pytest.raises(InputError) as refused:
            worker_wait_seconds()
        assert str(refused.value).startswith(f"STITCHPLAN_WORKER_WAIT: got {bad!r}, expected the seconds")


def test_a_scheduler_without_workers_is_one_failure_after_the_wait(short_wait, caplog):
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp", dashboard_address=None,
                      scheduler_kwargs=QUIET_SCHEDULER, silence_logs=logging.CRITICAL) as cluster:
        address = cluster.scheduler_address
        started = time.monotonic()
        # at the default level (no -v): a command stalled on a workerless cluster says why
        with caplog.at_level(logging.WARNING, logger="stitchplan.parallel"), pytest.raises(ClusterFailure) as failed:
            bounded(lambda: _map_on(address, sleeps, [0.0, 0.0]))
        waited = time.monotonic() - started
    assert str(failed.value) == (f"Dask scheduler {address} has no workers: none joined within {WAIT:g} s (0 of 2 "
                                 f"tasks done); expected workers attached to it (`dask worker {address}`)")
    assert failed.value.exit_code == 1
    assert WAIT <= waited < WAIT + 10.0
    said = [record.getMessage() for record in caplog.records]
    assert f"Dask scheduler {address} has no workers yet; its tasks will wait up to {WAIT:g} s for one" in said
    assert f"Dask scheduler {address} has no workers (0 of 2 tasks done); waiting up to {WAIT:g} s for one" in said


def test_a_cluster_that_loses_its_workers_says_how_many_tasks_were_done(short_wait):
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp", dashboard_address=None,
                      scheduler_kwargs=QUIET_SCHEDULER, silence_logs=logging.CRITICAL) as cluster:
        address = cluster.scheduler_address

        def lose_the_worker():
            time.sleep(1.0)  # the first task (0 s) is done, the second (3 s) runs
            cluster.scale(0)

        threading.Thread(target=lose_the_worker, daemon=True).start()
        with pytest.raises(ClusterFailure) as failed:
            bounded(lambda: _map_on(address, sleeps, [0.0, 3.0, 3.0]))
    assert str(failed.value) == (f"Dask scheduler {address} lost its workers: 1 of 3 tasks done, then no worker "
                                 f"for {WAIT:g} s; expected workers attached to it that keep running "
                                 f"(`dask worker {address}`)")


def test_tasks_wait_for_a_worker_that_comes_in_time(short_wait, monkeypatch):
    from dask.distributed import LocalCluster

    monkeypatch.setattr(parallel_workers, "WORKER_WAIT_S", 20.0)
    with LocalCluster(n_workers=0, threads_per_worker=1, processes=False, protocol="tcp", dashboard_address=None,
                      scheduler_kwargs=QUIET_SCHEDULER, silence_logs=logging.CRITICAL) as cluster:
        threading.Timer(1.5, lambda: cluster.scale(1)).start()
        assert bounded(lambda: _map_on(cluster.scheduler_address, pow, [2, 3], [2, 2])) == [4, 9]


def _map_on(address: str, function, *arguments):
    with Executor(scheduler=address) as executor:
        return executor.map(function, *arguments)


# --- Ctrl-C --------------------------------------------------------------------------------------


@pytest.fixture
def ctrl_c_interrupts():
    """Ctrl-C as a terminal's foreground job has it: a shell that starts pytest in the
    background (`&`) has it ignore SIGINT, and so the commands it starts, which then rightly
    do not stop on it."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.usefixtures("ctrl_c_interrupts")
def test_signals_are_deferred_until_the_block_closes():
    reached = []
    with pytest.raises(KeyboardInterrupt), signals_deferred():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs at the next bytecode: it only notes the signal
        reached.append("after the signal")
    assert reached == ["after the signal"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


@pytest.mark.usefixtures("ctrl_c_interrupts")
def test_an_interrupt_noted_in_a_block_that_fails_is_still_the_interrupt():
    """A terminal's Ctrl-C reaches a local cluster's workers as they start, and their nannies
    fail: the noted interrupt was dropped and the command ended on the failed start (exit 2,
    `cannot start a local Dask cluster ...; expected fewer --workers`) instead of 130."""
    with pytest.raises(KeyboardInterrupt) as raised, signals_deferred():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        raise RuntimeError("Nanny failed to start.")
    assert isinstance(raised.value.__context__, RuntimeError)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def signal_handling() -> str:
    import signal

    return repr(signal.getsignal(signal.SIGINT))


@pytest.mark.usefixtures("ctrl_c_interrupts")
def test_a_local_clusters_workers_ignore_ctrl_c():
    with Executor(workers=1) as executor:
        assert list(executor.client.run(signal_handling).values()) == [repr(signal.SIG_IGN)]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # this process keeps it


@pytest.mark.usefixtures("ctrl_c_interrupts")
def test_ctrl_c_during_a_local_cluster_run_is_the_commands_exit_alone(tmp_path):
    """SIGINT to the process group, as a terminal sends it, during the sampled runs: exit code
    130, no output file, no process left, and on stderr only the command's own log lines (-v;
    a plain `plan` prints nothing on an interrupt), nothing of the workers or of Dask."""
    scenario_path = write(tmp_path, small_raw())
    spec = write(tmp_path, {"samples": 30, "seed": 3, "parameters": {"thickness": {"std": 0.5}}}, "u.yaml")
    out = tmp_path / "out"
    stderr = tmp_path / "stderr.txt"
    command = [str(Path(sys.executable).parent / "stitchplan"), "plan", str(scenario_path), "--uncertainty", str(spec),
               "--export", str(out / "t.csv"), "--summary", str(out / "s.json"), "--workers", "2", "-v"]
    with stderr.open("w") as errors:
        process = subprocess.Popen(command, stderr=errors, stdout=subprocess.DEVNULL, start_new_session=True,
                                   env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, cwd=tmp_path)
    try:
        deadline = time.monotonic() + BOUND  # the nominal plan's steps are logged once the cluster is up
        while "stitchplan.needle.insertion" not in stderr.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(2.0)  # into the sampled runs (120 of them: a dozen seconds on two workers)
        os.killpg(process.pid, signal.SIGINT)
        code = process.wait(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    lines = stderr.read_text().splitlines()
    assert code == 130, lines[-5:]
    assert lines and all(line.startswith("INFO stitchplan.") for line in lines), [
        line for line in lines if not line.startswith("INFO stitchplan.")][:10]
    assert _process_group_ends(process.pid, within=10.0)  # multiprocessing's resource tracker takes a second
    assert not out.exists() or not any(out.iterdir())


def _process_group_ends(group: int, within: float) -> bool:
    """Whether every process of the group has ended (zombies reaped) within `within` seconds."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        if not subprocess.run(["pgrep", "-g", str(group)], capture_output=True, text=True).stdout.split():
            return True
        time.sleep(0.25)
    return False


# --- the counts, each of its set ---------------------------------------------------------------


def test_failed_training_samples_are_not_counted_as_held_out(tmp_path, monkeypatch):
    scenario_path = write(tmp_path, small_raw())
    path = write(tmp_path, _thickness_only(samples=4), "u.yaml")
    design = draw(load_uncertainty(path), parse_scenario(small_raw()))
    _failing_on(monkeypatch, design.train[:2])  # two training samples fail, every held-out one runs
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "t.csv", "--summary",
                    tmp_path / "s.json", "--workers", "0", "--no-verify")
    assert result.exit_code == 0, result.output
    [line] = [line for line in result.output.splitlines() if line.startswith("uncertainty: ")]
    assert line.startswith("uncertainty: 4 training samples (2 with a failed run), 4 held out (0 with a failed "
                           "run); exit error mean / p95 over the 4 held-out samples where every path ran"), line
    block = json.loads((tmp_path / "s.json").read_text())["uncertainty"]
    assert (block["samples"], block["failed_samples"], block["evaluated_samples"]) == (4, 0, 4)
    assert (block["held_out_samples"], block["failed_held_out_samples"]) == (4, 0)
    assert (block["training_samples"], block["failed_training_samples"]) == (4, 2)
    assert {failure["set"] for failure in block["failures"]} == {"training"}


TRACKER_SIGNALS = """
from multiprocessing import resource_tracker
from stitchplan.parallel.executor import Executor

with Executor(workers=1) as executor:
    with open(f"/proc/{resource_tracker._resource_tracker._pid}/status") as status:
        fields = dict(line.split(":\\t", 1) for line in status)
    print(int(fields["SigBlk"], 16), int(fields["SigIgn"], 16))
"""


WORKER_SIGNALS = """
from stitchplan.parallel.executor import Executor

def masks():
    with open("/proc/self/status") as status:
        fields = dict(line.split(":\\t", 1) for line in status)
    return int(fields["SigBlk"], 16), int(fields["SigIgn"], 16)

with Executor(workers=1) as executor:
    print(*executor.client.submit(masks, pure=False).result())
"""


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the workers' signal masks in /proc")
def test_a_local_clusters_workers_start_with_ctrl_c_blocked():
    """The terminal's Ctrl-C reaches every process of the group: a local cluster's workers
    still importing printed a KeyboardInterrupt traceback each (they ignore it once up). They
    start with SIGINT blocked (inherited from the threads that spawn them) and keep it so."""
    run = subprocess.run([sys.executable, "-c", WORKER_SIGNALS], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stderr
    blocked, ignored = map(int, run.stdout.split())
    sigint = 1 << (signal.SIGINT - 1)
    assert blocked & sigint and ignored & sigint


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the tracker's signal masks in /proc")
def test_a_hangup_does_not_stop_the_local_clusters_resource_tracker():
    """SIGHUP to the process group (the terminal closed) killed multiprocessing's resource
    tracker, which only ignores SIGINT and SIGTERM; the one started in its place printed a
    warning and a KeyError traceback for every semaphore the closing cluster released."""
    run = subprocess.run([sys.executable, "-c", TRACKER_SIGNALS], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    blocked, ignored = map(int, run.stdout.split())
    assert (blocked | ignored) & (1 << (signal.SIGHUP - 1))
