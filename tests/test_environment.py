"""The command in an unusual environment: closed or full standard streams, a termination
signal, limits on open files and on the address space. Each runs the real command in a
process of its own (the limits and streams are the process's)."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time

import pytest
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]
NEEDLE20 = REPOSITORY / "configs" / "needle20_entry30.yaml"
SH12 = REPOSITORY / "configs" / "sh12_100x100.yaml"


def command(*args, **options) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "stitchplan", *map(str, args)], cwd=REPOSITORY,
                            stdout=subprocess.PIPE, **options)


def test_a_closed_standard_error_does_not_fail_a_run(tmp_path):
    """Python gives a closed stderr (`2>&-`) as None; the logging set-up used to fail on it
    (exit 1, nothing written)."""
    run = command("plan", NEEDLE20, "--no-compare", "--no-verify", "--export", tmp_path / "t.csv",
                  preexec_fn=lambda: os.close(2))
    run.communicate(timeout=300)
    assert run.returncode == 0 and (tmp_path / "t.csv").exists()


def test_an_input_error_keeps_its_exit_code_when_standard_error_is_full(tmp_path):
    with open("/dev/full", "w") as full:
        run = command("plan", tmp_path / "absent.yaml", "--export", tmp_path / "t.csv", stderr=full)
        run.communicate(timeout=300)
    assert run.returncode == 2


def test_sigterm_ends_the_command_leaving_no_file(tmp_path):
    """The default action of SIGTERM would leave the outputs' temporaries beside the targets
    when it came while they were written; the command now unwinds and exits 128 + 15."""
    outputs = ["--export", tmp_path / "t.csv", "--summary", tmp_path / "s.json", "--out", tmp_path / "r.h5"]
    # at --spacing 2 the command takes ~7 s (its default spacing, ~1.8 s, could end before the signal)
    run = command("plan", SH12, "--spacing", "2", *outputs, stderr=subprocess.PIPE)
    time.sleep(2.0)
    run.send_signal(signal.SIGTERM)
    _, error = run.communicate(timeout=300)
    assert run.returncode == 128 + signal.SIGTERM, error
    assert list(tmp_path.iterdir()) == [] and b"Traceback" not in error


def test_too_few_open_files_for_a_local_cluster_is_one_line(tmp_path):
    """At `ulimit -n 16` the local cluster's scheduler looped on 'too many open files',
    writing hundreds of MB of tracebacks."""
    def few_files():
        resource.setrlimit(resource.RLIMIT_NOFILE, (16, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))

    run = command("study", NEEDLE20, "--quick", "--workers", "2", "--out", tmp_path / "study",
                  stderr=subprocess.PIPE, preexec_fn=few_files)
    _, error = run.communicate(timeout=300)
    assert run.returncode == 2
    assert error.decode().strip().splitlines() == [
        "error: --workers: a local Dask cluster needs at least 64 open files, got a limit of 16 (ulimit -n); "
        "expected a higher limit, or --workers 0 to run in this process"]


def test_the_resource_guard_counts_the_address_space_limit(tmp_path):
    """Under `ulimit -v` a model past the limit crashed CHOLMOD (exit 139); the guard now
    takes the memory the limit leaves as the memory available."""
    def capped():
        resource.setrlimit(resource.RLIMIT_AS, (700_000 * 1024, resource.RLIM_INFINITY))

    run = command("plan", SH12, "--spacing", "0.8", "--no-verify", "--no-compare", "--export", tmp_path / "t.csv",
                  stderr=subprocess.PIPE, preexec_fn=capped)
    _, error = run.communicate(timeout=300)
    assert run.returncode == 2, error
    assert error.decode().startswith("error: --spacing: got 0.8 mm, expected a model within the ~"), error
    assert " of memory the process's address-space limit of 717 MB (ulimit -v 700000) leaves it (" in error.decode()
    assert list(tmp_path.iterdir()) == []


def test_an_address_space_limit_counts_what_a_run_maps_beyond_its_memory(tmp_path):
    """At `ulimit -v 400000` the smallest deform's run (estimated ~107 MB) fitted half of what
    the limit left (~270 MB), but the libraries and buffers the run maps took the address
    space past the limit: SuperLU spun at an allocation that failed, for as long as it was
    left running (it needs 448 MB: resources/machine.py). The guard refuses it naming the limit,
    not a scenario field: even the smallest model would not fit (it once said `tissue.size: got
    [100, 100] mm, expected a model within 50% of the 0 kB of memory available`)."""
    def capped():
        resource.setrlimit(resource.RLIMIT_AS, (400_000 * 1024, resource.RLIM_INFINITY))

    run = subprocess.run([sys.executable, "-m", "stitchplan", "deform", "configs/slab_edge_load.yaml",
                          "--probes-out", str(tmp_path / "probes.csv")], cwd=REPOSITORY, capture_output=True,
                         preexec_fn=capped, timeout=120)
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.decode().splitlines()
    assert line.startswith("error: configs/slab_edge_load.yaml: ulimit -v: got 400000 (the process's address-space "
                           "limit of 410 MB; "), line
    assert "), expected at least ~" in line and " 0 kB" not in line and "tissue.size" not in line
    assert line.endswith("or pass --no-resource-check to run it anyway")
    assert list(tmp_path.iterdir()) == []


def test_a_deleted_working_directory_is_named_for_a_local_cluster(tmp_path):
    """The workers start in the working directory; its absence used to read as 'Nanny failed
    to start' under --workers."""
    gone = tmp_path / "gone"
    gone.mkdir()

    def leave_it_deleted():
        os.chdir(gone)
        os.rmdir(gone)

    run = subprocess.Popen([sys.executable, "-m", "stitchplan", "study", str(NEEDLE20), "--quick", "--out",
                            str(tmp_path / "study")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           preexec_fn=leave_it_deleted, env={**os.environ, "PYTHONPATH": str(REPOSITORY)})
    _, error = run.communicate(timeout=300)
    assert run.returncode == 2
    assert error.decode().startswith("error: --workers: the working directory no longer exists")


def test_quiet_silences_matplotlib_too(tmp_path):
    """-q is errors only: matplotlib's note about an unwritable cache folder stays out."""
    run = command("simulate", NEEDLE20, "--no-estimate", "--plot", tmp_path / "run.png", "-q",
                  stderr=subprocess.PIPE, env={**os.environ, "MPLCONFIGDIR": "/proc/stitchplan-test"})
    _, error = run.communicate(timeout=300)
    assert run.returncode == 0 and error == b""


def test_a_non_ascii_scenario_path_under_an_ascii_locale_is_logged_escaped(tmp_path):
    """Under an ASCII-only locale Python carries a path's non-ASCII bytes as lone surrogates,
    which HDF5's UTF-8 strings refused (traceback); the run log keeps them as escapes."""
    import h5py

    folder = tmp_path / "Größe ü"
    folder.mkdir()
    scenario = folder / "plain.yaml"
    scenario.write_bytes(NEEDLE20.read_bytes())
    environment = {key: value for key, value in os.environ.items() if key not in ("LANG", "LC_CTYPE")}
    environment.update(LC_ALL="C", PYTHONUTF8="0", PYTHONCOERCECLOCALE="0", PYTHONPATH=str(REPOSITORY))
    run = subprocess.Popen([sys.executable, "-m", "stitchplan", "simulate", os.fsencode(scenario), "--no-estimate",
                            "--out", str(tmp_path / "run.h5")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           cwd=REPOSITORY, env=environment)
    _, error = run.communicate(timeout=300)
    assert run.returncode == 0, error
    with h5py.File(tmp_path / "run.h5") as log:
        assert log.attrs["scenario"].endswith("Gr\\udcc3\\udcb6\\udcc3\\udc9fe \\udcc3\\udcbc/plain.yaml")


def test_a_non_ascii_output_path_on_an_ascii_standard_output_is_written_escaped(tmp_path):
    """The done line names the output, which standard output under PYTHONIOENCODING=ascii
    could not encode: a traceback after the run, its outputs undone (a study lost)."""
    export = tmp_path / "tü.csv"
    run = subprocess.run([sys.executable, "-m", "stitchplan", "plan", str(NEEDLE20), "--export", str(export),
                          "--no-verify", "--no-compare", "-q"], cwd=REPOSITORY, capture_output=True,
                         env={**os.environ, "PYTHONIOENCODING": "ascii", "OPENBLAS_NUM_THREADS": "1"}, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.decode("ascii").rstrip().endswith("t\\xfc.csv") and export.exists()


def test_a_replay_helper_setting_other_than_0_or_1_is_one_line_and_no_file(tmp_path):
    """STITCHPLAN_REPLAY_HELPER=abc was read as "on" in silence; STITCHPLAN_WORKER_WAIT and
    STITCHPLAN_LINEAR_BACKEND refuse a bad value, and so does it now."""
    export = tmp_path / "t.csv"
    run = subprocess.run([sys.executable, "-m", "stitchplan", "plan", str(NEEDLE20), "--export", str(export)],
                         cwd=REPOSITORY, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "STITCHPLAN_REPLAY_HELPER": "abc", "OPENBLAS_NUM_THREADS": "1"})
    assert run.returncode == 2 and not export.exists()
    assert run.stderr == ("error: STITCHPLAN_REPLAY_HELPER: got 'abc', expected 0 (the replays in the command's own "
                          "process) or 1 (in a helper process where one can run, the default)\n")


def test_an_unknown_linear_backend_is_one_line_and_no_file(tmp_path):
    """STITCHPLAN_LINEAR_BACKEND takes scipy or superlu; anything else ends the command before
    any work (the helper process, which imports the same module, ends with it)."""
    environment = {**os.environ, "STITCHPLAN_LINEAR_BACKEND": "cholmodd"}
    run = command("plan", NEEDLE20, "--export", tmp_path / "t.csv", stderr=subprocess.PIPE, env=environment)
    _, error = run.communicate(timeout=300)
    lines = error.decode().splitlines()
    assert run.returncode == 2 and list(tmp_path.iterdir()) == []
    assert lines == ["error: STITCHPLAN_LINEAR_BACKEND: got 'cholmodd', expected scipy (no CHOLMOD, as without the "
                     "fast extra) or superlu (scipy's SuperLU alone), or unset for the default"]


def test_the_collector_is_paused_for_the_imports_only(tmp_path):
    """The command turns Python's cyclic garbage collector off as it starts and on again once
    its imports are done, what they made frozen out of its passes (stitchplan/allocator.py);
    outside a command (a test's runner) the pause does nothing."""
    import gc

    from stitchplan import allocator

    allocator.pause_collection()  # not a command's process: left as it is
    assert gc.isenabled() and not allocator._paused
    script = ("import atexit, gc, sys\n"
              "from stitchplan.cli import main\n"
              "atexit.register(lambda: sys.stderr.write(f'collector {gc.isenabled()} {gc.get_freeze_count()}\\n'))\n"
              "sys.argv = ['stitchplan', *sys.argv[1:]]\n"
              "main()\n")
    for arguments in (["schema"], ["deform", REPOSITORY / "configs" / "slab_edge_load.yaml", "--spacing", "10"]):
        run = subprocess.run([sys.executable, "-c", script, *map(str, arguments)], cwd=tmp_path, capture_output=True,
                             text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        enabled, frozen = run.stderr.strip().splitlines()[-1].split()[1:]
        assert enabled == "True" and int(frozen) > 10_000, arguments  # numpy's and pydantic's objects among them


# A command whose deform run is first interrupted where Python turns the interrupt into another
# error or only reports it: `signal` sent to the process while a class body's __set_name__ runs
# (3.11 raises a RuntimeError from it), or within a weak reference's callback (whose exceptions
# are printed as `Exception ignored in ...` and dropped), then the run as it was.
INTERRUPTED_RUN = """
import os, signal, sys, time, weakref
import stitchplan.tissue.deform as deform

run_deform, where, number = deform.run_deform, sys.argv[1], getattr(signal, sys.argv[2])
sys.argv = ["stitchplan", *sys.argv[3:]]


def interrupted(*args, **kwargs):
    def interrupt(*_):
        os.kill(os.getpid(), number)
        for _ in range(100000):  # the handler runs here
            pass

    if where == "set_name":
        type("Owner", (), {"attribute": type("Name", (), {"__set_name__": interrupt})()})
    else:
        class Referent:
            pass

        referent = Referent()
        reference = weakref.ref(referent, interrupt)
        del referent
    time.sleep(2.0)  # an interrupt dropped in the callback is sent again meanwhile
    return run_deform(*args, **kwargs)


deform.run_deform = interrupted
from stitchplan.cli import main

main()
"""


@pytest.mark.parametrize("where", ["set_name", "weakref"])
@pytest.mark.parametrize("name", ["SIGTERM", "SIGINT"])
def test_an_interrupt_python_wraps_or_drops_still_ends_the_command(tmp_path, where, name):
    """SIGTERM while matplotlib's axes were imported ended in a RuntimeError's traceback (exit 1);
    one within a weak reference's callback printed `Exception ignored in ...` and the command
    ran on, writing its outputs (exit 0). Either ends as the interrupt: 128 + the signal, no
    file, no traceback."""
    outputs = ["--summary", tmp_path / "s.json", "--probes-out", tmp_path / "p.csv"]
    run = subprocess.Popen([sys.executable, "-c", INTERRUPTED_RUN, where, name, "deform",
                            REPOSITORY / "configs" / "slab_edge_load.yaml", *map(str, outputs)], cwd=REPOSITORY,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _, error = run.communicate(timeout=300)
    assert run.returncode == 128 + getattr(signal, name), error
    assert b"Traceback" not in error and b"Exception ignored" not in error, error
    assert list(tmp_path.iterdir()) == []


# A deform command interrupted (`signal` sent to itself) while its outputs are staged and land:
# as the first temporary has been made ("temporary"), after the first output has been renamed
# onto its target ("rename"), or while the renames are made final ("keep").
INTERRUPTED_COMMIT = """
import os, signal, sys
from stitchplan.io import files

where, number = sys.argv[1], getattr(signal, sys.argv[2])
sys.argv = ["stitchplan", *sys.argv[3:]]
replace, keep, mkstemp = os.replace, files.Renamed.keep, files.tempfile.mkstemp


def interrupt():
    os.kill(os.getpid(), number)
    for _ in range(100000):  # the handler runs here
        pass


def temporary_then_interrupt(*args, **kwargs):
    made = mkstemp(*args, **kwargs)
    if where == "temporary" and kwargs.get("suffix") == ".tmp":
        interrupt()
    return made


def replace_then_interrupt(source, target):
    replace(source, target)
    if where == "rename" and not str(source).endswith(".old"):  # an output, not a backup put back
        interrupt()


def keep_interrupted(self):
    if where == "keep" and self.labels:
        interrupt()
    keep(self)


files.os.replace = replace_then_interrupt
files.tempfile.mkstemp = temporary_then_interrupt
files.Renamed.keep = keep_interrupted
from stitchplan.cli import main

main()
"""


@pytest.mark.parametrize("name", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("where", ["temporary", "rename", "keep"])
def test_an_interrupt_while_the_outputs_land_leaves_all_or_none(tmp_path, where, name):
    """An interrupt just after a temporary was made left it beside its target; one between two
    renames ended the command with 128 + the signal having replaced the first output and left
    the backups of the replaced files beside them; one after they were kept ended it with a
    traceback (exit by the signal) or 128 + the signal, which says no file was written. Before
    the outputs are final the interrupt undoes them (the files as they were); once they are,
    it is too late and the command ends done."""
    outputs = {"--summary": tmp_path / "s.json", "--probes-out": tmp_path / "p.csv",
               "--reactions-out": tmp_path / "r.csv"}
    for path in outputs.values():
        path.write_text("before\n")
    run = subprocess.run([sys.executable, "-c", INTERRUPTED_COMMIT, where, name, "deform",
                          REPOSITORY / "configs" / "slab_edge_load.yaml",
                          *(str(part) for item in outputs.items() for part in item)], cwd=REPOSITORY,
                         capture_output=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
                         timeout=300)
    assert b"Traceback" not in run.stderr, run.stderr
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(path.name for path in outputs.values())
    contents = [path.read_text() for path in outputs.values()]
    if where != "keep":
        assert run.returncode == 128 + getattr(signal, name), run.stderr
        assert contents == ["before\n"] * 3
    else:
        assert run.returncode == 0, run.stderr
        assert "before\n" not in contents
