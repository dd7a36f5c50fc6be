"""--workers and --scheduler (stitchplan.parallel): every bad value is one `error:` line naming
the option, exit 2, before any work and within seconds, never a traceback or a hang.

The address is checked by form before anything runs; reaching it is bounded in time, tried
here on fake servers on localhost (one that never answers, one that answers HTTP, a closed
port) with a deadline of a second. Dask's log records stay off the user's stderr: in this
process they go to stitchplan.parallel's logger, in a local cluster's workers they are
dropped. Two tests start a small cluster (a few seconds each); the rest start none.
"""

from __future__ import annotations

import logging
import platform
import socket
import sys
import threading
import time
from pathlib import Path

import pytest
from test_plan_cli import invoke, one_error_line, small_raw, write

from stitchplan import allocator
from stitchplan.errors import InputError
from stitchplan.parallel import scheduler
from stitchplan.parallel import workers as parallel_workers
from stitchplan.parallel.dask_logs import dask_logs_to_package, dask_setup
from stitchplan.parallel.executor import Executor
from stitchplan.parallel.failures import ClusterFailure
from stitchplan.parallel.scheduler import check_scheduler_address, probe_scheduler
from stitchplan.parallel.workers import check_workers, max_workers

SCENARIO = Path(__file__).resolve().parents[1] / "configs" / "needle20_entry30.yaml"
UNCERTAINTY = {"samples": 3, "seed": 1, "parameters": {"thickness": {"std": 0.2}}}
FAST = 10.0  # s: a refusal before any work (Python, typer, numpy imports) takes well under this


# --- the address, by its form ---------------------------------------------------------------


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:8786", "tcp://localhost:1", "tls://scheduler.lab-2.org:65535",
                                     "ws://[::1]:8786", "wss://my_host:443", "tcp://10.0.0.5:8786"])
def test_well_formed_addresses_pass(address):
    check_scheduler_address(address)
    check_workers(None, address)


@pytest.mark.parametrize("address, problem", [
    ("tcp://host:port", "port 'port' is not a number"),  # the README's placeholder
    ("tcp://127.0.0.1", "no port"),
    ("tcp://127.0.0.1:", "no port"),
    ("http://127.0.0.1:8786", "unknown scheme 'http'"),
    ("inproc://127.0.0.1/1/1", "unknown scheme 'inproc'"),  # in-process only
    ("TCP://127.0.0.1:8786", "unknown scheme 'TCP'"),  # distributed's schemes are lower case
    ("tcp://127.0.0.1:99999", "port 99999 is out of range"),
    ("tcp://127.0.0.1:0", "port 0 is out of range"),
    ("tcp://127.0.0.1:-1", "port '-1' is not a number"),
    ("tcp://127.0.0.1:8786/", "port '8786/' is not a number"),
    ("localhost:8786", "no scheme"),
    ("tcp://", "no host"),
    ("tcp://:8786", "no host"),
    ("tcp://::1:8786", "an IPv6 host needs brackets, such as tcp://[::1]:8786"),
    ("tcp://[::1", "no ']' after the IPv6 host"),
    ("tcp://[::1]", "no port"),
    ("tcp://[nonsense]:8786", "'nonsense' is not an IPv6 address"),
    ("tcp://user@host:8786", "host 'user@host' is not a host name or an IP address"),
    ("tcp://a b:8786", "host 'a b' is not a host name or an IP address"),
])
def test_malformed_addresses_are_refused_saying_why(address, problem):
    with pytest.raises(InputError) as refused:
        check_scheduler_address(address)
    message = str(refused.value)
    assert message.startswith(f"--scheduler: got {address!r}, expected a Dask scheduler address SCHEME://HOST:PORT")
    assert message.endswith(f"({problem})") and "\n" not in message


@pytest.mark.parametrize("command", ["plan", "study"])
@pytest.mark.parametrize("address", ["tcp://host:port", "tcp://127.0.0.1", "http://127.0.0.1:8786",
                                     "tcp://127.0.0.1:99999"])
def test_the_commands_refuse_a_malformed_address_at_once(tmp_path, command, address):
    uncertainty = write(tmp_path, UNCERTAINTY, "u.yaml")
    outputs = (["--uncertainty", uncertainty, "--export", tmp_path / "t.csv", "--no-verify"]
               if command == "plan" else ["--out", tmp_path / "out", "--quick"])
    start = time.perf_counter()
    line = one_error_line(invoke(command, SCENARIO, *outputs, "--scheduler", address))
    assert time.perf_counter() - start < FAST
    assert line.startswith(f"error: --scheduler: got {address!r}, expected a Dask scheduler address")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["u.yaml"]  # nothing written


# --- the worker count ------------------------------------------------------------------------


def test_the_worker_count_is_bounded_by_the_usable_cores(monkeypatch):
    monkeypatch.setattr(parallel_workers.os, "sched_getaffinity", lambda pid: {0, 3})  # 2 of the machine's cores
    assert max_workers() == 8 and parallel_workers.default_workers() == 2
    check_workers(0, None)
    check_workers(8, None)
    for workers in (9, 100000, -1):
        with pytest.raises(InputError) as refused:
            check_workers(workers, None)
        assert str(refused.value) == (f"--workers: got {workers}, expected a number of worker processes from 0 to 8 "
                                      "(at most 4 x the 2 CPU cores this process may use; 0: run in this process)")
    monkeypatch.setattr(parallel_workers.os, "sched_getaffinity", lambda pid: {1})
    with pytest.raises(InputError, match=r"from 0 to 4 \(at most 4 x the 1 CPU core this"):
        check_workers(5, None)


@pytest.mark.parametrize("workers", ["100000", "-1"])
@pytest.mark.parametrize("command", ["plan", "study"])
def test_the_commands_refuse_a_worker_count_out_of_bounds_at_once(tmp_path, command, workers):
    uncertainty = write(tmp_path, UNCERTAINTY, "u.yaml")
    outputs = (["--uncertainty", uncertainty, "--export", tmp_path / "t.csv"] if command == "plan"
               else ["--out", tmp_path / "out", "--quick"])
    start = time.perf_counter()
    line = one_error_line(invoke(command, SCENARIO, *outputs, "--workers", workers))
    assert time.perf_counter() - start < FAST
    assert line == (f"error: --workers: got {workers}, expected a number of worker processes from 0 to "
                    f"{max_workers()} (at most 4 x the {parallel_workers.usable_cores()} CPU "
                    f"core{'s' if parallel_workers.usable_cores() > 1 else ''} this process may use; "
                    "0: run in this process)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["u.yaml"]


# --- reaching the scheduler: fake servers on localhost -----------------------------------------


class FakeServer:
    """A listening socket on a free localhost port whose every connection gets `reply` (None:
    nothing, ever); closed by `close`."""

    def __init__(self, reply: bytes | None):
        self.reply = reply
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        self.connections: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                connection, _ = self.listener.accept()
            except OSError:  # closed
                return
            self.connections.append(connection)
            if self.reply is not None:
                connection.settimeout(0.5)
                try:
                    connection.recv(4096)
                    connection.sendall(self.reply)
                except OSError:
                    pass
                connection.close()

    def close(self) -> None:
        self.listener.close()
        for connection in self.connections:
            connection.close()


@pytest.fixture
def silent():
    server = FakeServer(None)
    yield server.address
    server.close()


@pytest.fixture
def http():
    server = FakeServer(b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\n\r\n")
    yield server.address
    server.close()


@pytest.fixture
def closed_port():
    """A port bound but not listening, kept for the test: connecting is refused, and no other
    process (a Dask worker of another test) can take the port meanwhile, as it could once freed."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as bound:
        bound.bind(("127.0.0.1", 0))
        yield f"tcp://127.0.0.1:{bound.getsockname()[1]}"


def refusal(address: str, timeout: float = 1.0) -> tuple[str, float]:
    start = time.perf_counter()
    with pytest.raises(InputError) as refused:
        probe_scheduler(address, timeout=timeout)
    return str(refused.value), time.perf_counter() - start


def test_a_server_that_never_answers_is_refused_at_the_deadline(silent):
    message, elapsed = refusal(silent)
    assert message == (f"--scheduler: no answer from {silent} within 1 s; expected the address of a running "
                       "`dask scheduler`")
    assert 0.9 < elapsed < 3


def test_a_server_that_answers_something_else_is_refused(http):
    message, elapsed = refusal(http)
    assert message.startswith(f"--scheduler: {http} does not answer as a Dask scheduler (its reply could not be read: ")
    assert message.endswith("; expected the address of a running `dask scheduler`") and "\n" not in message
    assert elapsed < 3


def test_a_server_whose_banner_reads_as_a_huge_message_is_refused_without_the_allocation():
    """A banner (an SSH server's) whose first bytes Dask reads as a frame length of exabytes: the
    line says the reply is not Dask's protocol, not numpy's failed allocation."""
    server = FakeServer(b"SSH-2.0-OpenSSH_9.6\r\n" + b"x" * 64)
    try:
        message, _ = refusal(server.address)
    finally:
        server.close()
    assert "its reply could not be read: it is not Dask's protocol" in message, message
    assert "MemoryError" not in message and "EiB" not in message


def test_a_closed_port_is_refused_naming_the_reason(closed_port):
    message, elapsed = refusal(closed_port)
    assert message == (f"--scheduler: cannot connect to {closed_port} within 1 s (ConnectionRefusedError: "
                       "[Errno 111] Connection refused); expected the address of a running `dask scheduler`")
    assert elapsed < 3


def refused_plan_line(tmp_path: Path, address: str) -> str:
    """The one error line of `plan --uncertainty --scheduler address` on a small scene, which
    must end well before any run could (FAST)."""
    scenario = write(tmp_path, small_raw())
    uncertainty = write(tmp_path, UNCERTAINTY, "u.yaml")
    start = time.perf_counter()
    line = one_error_line(invoke("plan", scenario, "--uncertainty", uncertainty, "--export", tmp_path / "t.csv",
                                 "--summary", tmp_path / "s.json", "--scheduler", address))
    assert time.perf_counter() - start < FAST
    return line


@pytest.mark.parametrize("server", ["silent", "http", "closed_port"])
def test_the_plan_command_ends_in_one_line_at_an_address_without_a_scheduler(tmp_path, monkeypatch, request, server):
    address = request.getfixturevalue(server)
    monkeypatch.setattr(scheduler, "CONNECT_TIMEOUT_S", 1.0)
    line = refused_plan_line(tmp_path, address)
    assert line.startswith("error: --scheduler: ") and address in line
    assert line.endswith("expected the address of a running `dask scheduler`")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml", "u.yaml"]


# --- Dask's log records ----------------------------------------------------------------------


class Collected(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_dask_records_go_to_the_package_logger_and_back(caplog):
    distributed = logging.getLogger("distributed")
    child = logging.getLogger("distributed.worker")
    own = Collected()  # in place of the stderr handler distributed installs at import
    distributed.addHandler(own)
    before = (list(distributed.handlers), distributed.propagate, list(child.handlers), child.propagate)
    try:
        with caplog.at_level(logging.DEBUG, logger="stitchplan"), dask_logs_to_package():
            child.error("Failed to communicate with scheduler during heartbeat.")
        assert own.records == []  # not through distributed's own handler
        [record] = [r for r in caplog.records if "heartbeat" in r.getMessage()]
        assert record.name == "stitchplan.parallel" and record.levelno == logging.DEBUG
        assert record.getMessage() == "distributed.worker ERROR: Failed to communicate with scheduler during heartbeat."
        assert (list(distributed.handlers), distributed.propagate, list(child.handlers), child.propagate) == before
        child.error("after")  # distributed's own handler again
        assert [r.getMessage() for r in own.records] == ["after"]
    finally:
        distributed.removeHandler(own)


def test_dask_setup_drops_every_dask_record_of_a_worker_process():
    names = ("distributed", "distributed.worker", "distributed.nanny", "tornado", "tornado.application")
    saved = {name: logging.getLogger(name).level for name in names}
    try:
        logging.getLogger("distributed.nanny").setLevel(logging.ERROR)  # what distributed's silence_logs sets
        dask_setup(None)
        for name in names:
            assert not logging.getLogger(name).isEnabledFor(logging.CRITICAL), name
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


# --- on a real cluster (a few seconds each) ------------------------------------------------------


def report_from_a_worker():
    import logging

    logging.getLogger("distributed.worker").error("an ERROR record of a worker process")
    return logging.getLogger("distributed.worker").getEffectiveLevel()


def test_a_local_clusters_workers_keep_their_records_off_stderr(capfd):
    with Executor(workers=1) as executor:
        assert executor.map(pow, [2, 3], [2, 2]) == [4, 9]
        assert list(executor.client.run(report_from_a_worker).values()) == [logging.CRITICAL + 1]
    captured = capfd.readouterr()
    assert "distributed" not in captured.err and "ERROR" not in captured.err, captured.err


def faults_making_arrays(count: int) -> tuple[dict, int]:
    """In a worker: glibc's malloc variables in its environment, and the page faults while
    `count` arrays of 1 MiB are made and freed one after another."""
    import os
    import resource

    import numpy as np

    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(count):
        np.ones(2**17)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    return {name: value for name, value in os.environ.items() if name.startswith("MALLOC_")}, faults


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                    reason="glibc's malloc")
def test_a_local_clusters_workers_reuse_freed_memory_as_the_command_does():
    """A worker starts with the command's malloc thresholds (stitchplan/allocator.py): a freed
    1 MiB array's pages are reused by the next, where with Dask's MALLOC_TRIM_THRESHOLD_ alone
    each was mapped afresh and faulted in, 256 faults an array; a user's own variables are
    left to Dask."""
    with Executor(workers=1) as executor:
        ((environment, faults),) = executor.map(faults_making_arrays, [200])
    assert faults < 200 * 256 / 10, faults
    assert environment == {"MALLOC_MMAP_THRESHOLD_": str(allocator.MMAP_THRESHOLD_BYTES),
                           "MALLOC_TRIM_THRESHOLD_": str(allocator.TRIM_THRESHOLD_BYTES)}
    assert allocator.worker_environment() == environment


def test_workers_get_no_malloc_thresholds_where_the_user_set_either(monkeypatch):
    monkeypatch.setattr(allocator, "USER_SET", True)
    assert allocator.worker_environment() == {}


def sleeps(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def test_a_scheduler_lost_during_the_run_is_a_cluster_failure():
    from dask.distributed import LocalCluster

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                           dashboard_address=None, silence_logs=logging.CRITICAL)
    with pytest.raises(ClusterFailure) as failed, Executor(scheduler=cluster.scheduler_address) as executor:
        threading.Timer(0.5, cluster.close).start()
        executor.map(sleeps, [2.0, 2.0])
    message = str(failed.value)
    assert message.startswith(f"Dask scheduler {cluster.scheduler_address} lost a task: ") and "\n" not in message
    assert failed.value.exit_code == 1


# --- the package on a scheduler's workers ----------------------------------------------------


@pytest.fixture
def worker_on():
    """worker_on(pythonpath): a LocalCluster scheduler's address with one `dask worker`
    process attached whose PYTHONPATH is `pythonpath`, as a user starts one elsewhere."""
    import os
    import subprocess

    from dask.distributed import Client, LocalCluster

    clusters, processes = [], []

    def start(pythonpath: Path) -> str:
        cluster = LocalCluster(n_workers=0, processes=False, protocol="tcp", dashboard_address=None,
                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, silence_logs=logging.CRITICAL)
        clusters.append(cluster)
        environment = {**os.environ, "PYTHONPATH": str(pythonpath), "OPENBLAS_NUM_THREADS": "1"}
        processes.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", cluster.scheduler_address, "--nworkers", "1",
             "--nthreads", "1", "--no-dashboard"], env=environment, cwd=pythonpath,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with Client(cluster.scheduler_address, timeout=10) as client:
            client.wait_for_workers(1, timeout=60)
        return cluster.scheduler_address

    yield start
    for process in processes:
        process.terminate()
        process.wait(30)
    for cluster in clusters:
        cluster.close()


def test_a_scheduler_whose_worker_cannot_import_the_package_is_refused_before_any_run(tmp_path, worker_on):
    # another `stitchplan` first on the worker's path, a module without the package's modules,
    # as on a worker started where stitchplan is neither installed nor on PYTHONPATH (such a
    # worker died on its first task, which the command only saw as lost workers)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "stitchplan.py").write_text("")
    address = worker_on(elsewhere)
    line = refused_plan_line(tmp_path, address)
    assert line.startswith(f"error: --scheduler: worker tcp://127.0.0.1:") and f" of {address} cannot import " \
        "this command's stitchplan (" in line and "No module named 'stitchplan.parallel'" in line
    assert line.endswith("started where stitchplan is installed or with it on PYTHONPATH, and restarted since it "
                         f"changed (`PYTHONPATH=DIR dask worker {address}`)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", "scene.yaml", "u.yaml"]


def test_a_scheduler_whose_worker_runs_another_version_is_refused(worker_on, monkeypatch):
    import stitchplan

    address = worker_on(Path(stitchplan.__file__).resolve().parents[1])  # this package: its version
    with Executor(scheduler=address) as executor:
        assert executor.map(abs, [-1.0]) == [1.0]  # it runs tasks
    version = stitchplan.__version__  # the worker's
    monkeypatch.setattr(stitchplan, "__version__", "0.0.1")  # the command's, now another
    with pytest.raises(InputError) as refused, Executor(scheduler=address):
        pass
    message = str(refused.value)
    assert message.startswith("--scheduler: worker tcp://127.0.0.1:") and "\n" not in message
    assert message.endswith(f" of {address} runs stitchplan {version}, this command 0.0.1; expected "
                            "the same version on every worker (the runs must not depend on where they ran)")



def test_a_scheduler_whose_worker_runs_other_sources_of_this_version_is_refused(worker_on, monkeypatch):
    """The version stays the same over many changes of the numerics: a worker started before the
    code changed, or from another checkout, runs other code under it."""
    import stitchplan

    address = worker_on(Path(stitchplan.__file__).resolve().parents[1])
    theirs = stitchplan.source_sha256()
    monkeypatch.setattr(stitchplan, "source_sha256", lambda: "0" * 64)  # the command's code, now changed
    with pytest.raises(InputError) as refused, Executor(scheduler=address):
        pass
    message = str(refused.value)
    assert message.startswith("--scheduler: worker tcp://127.0.0.1:") and "\n" not in message
    assert message.endswith(f" of {address} runs stitchplan {stitchplan.__version__} from other sources (SHA-256 "
                            f"{theirs[:12]}..., this command's 000000000000...); expected the same code on every "
                            "worker, restarted since it changed (the runs must not depend on where they ran)")


def test_a_worker_at_code_that_answers_its_version_alone_is_refused_in_one_line(tmp_path, worker_on):
    """A worker started before its sources were checked runs the earlier probe, which answers
    the version alone (a str, not the pair): at this very version it is still other code, refused
    naming the worker, not a traceback of the pair's unpacking."""
    import stitchplan

    earlier = tmp_path / "earlier" / "stitchplan"
    (earlier / "parallel").mkdir(parents=True)
    (earlier / "__init__.py").write_text(f"__version__ = {stitchplan.__version__!r}\n")
    (earlier / "parallel" / "__init__.py").write_text("")
    (earlier / "parallel" / "executor.py").write_text(
        "def package_version():\n    from .. import __version__\n\n    return __version__\n")
    address = worker_on(earlier.parent)
    with pytest.raises(InputError) as refused, Executor(scheduler=address):
        pass
    message = str(refused.value)
    assert message.startswith("--scheduler: worker tcp://127.0.0.1:") and "\n" not in message
    assert f" of {address} runs stitchplan {stitchplan.__version__} from other sources (" in message

