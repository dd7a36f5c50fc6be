"""The command line as a tool: version, `python -m stitchplan`, instant `--help`, choices in the
help, the schema command, logging levels, and the error contract: usage errors and the
project's input errors are `error:` lines with exit code 2, numerical failures one line with
exit code 1, and anything else a bug that shows its traceback."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

import stitchplan
from stitchplan import cli
from stitchplan.cli import app
from stitchplan.errors import InputError, NumericalFailure
from stitchplan.tissue.factorization import cholesky_available

REPOSITORY = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "scipy", "h5py", "matplotlib", "rich")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def run_module(*args, **options) -> subprocess.CompletedProcess:
    """`python -m stitchplan ARGS` in a fresh interpreter."""
    return subprocess.run([sys.executable, "-m", "stitchplan", *map(str, args)], capture_output=True,
                          text=True, **options)


def one_error_line(result, code: int) -> str:
    assert result.exit_code == code, result.output
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.output and "╭" not in result.output  # no rich box
    return lines[0]


# --- version, python -m, start-up ------------------------------------------------------------


def test_version_option_prints_the_package_version():
    result = invoke("--version")
    assert result.exit_code == 0
    assert result.stdout == f"stitchplan {stitchplan.__version__}\n"
    assert stitchplan.__version__ == "0.2.0"


def test_pyproject_takes_its_version_from_the_package():
    project = tomllib.loads((REPOSITORY / "pyproject.toml").read_text())
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "stitchplan.__version__"}
    assert project["project"]["scripts"]["stitchplan"] == "stitchplan.cli:main"


def test_python_dash_m_works_like_the_command():
    help_run = run_module("--help")
    assert help_run.returncode == 0, help_run.stderr
    for command in ("deform", "simulate", "plan", "calibrate", "study", "schema"):
        assert command in help_run.stdout
    assert "Exit codes" in help_run.stdout and "--install-completion" in help_run.stdout
    version_run = run_module("--version")
    assert (version_run.returncode, version_run.stdout) == (0, f"stitchplan {stitchplan.__version__}\n")


def test_help_and_version_import_no_numerics(tmp_path):
    """--help (top level and of a command) and --version load none of numpy, scipy, h5py,
    matplotlib, rich: the modules loaded are listed by the interpreter that ran them."""
    listing = tmp_path / "modules.json"
    script = (
        "import json, sys\n"
        "from stitchplan.cli import app\n"
        "for args in (['--help'], ['--version'], ['plan', '--help'], ['simulate', '--help'],\n"
        "             ['calibrate', 'material', '--help']):\n"
        "    try:\n"
        "        app(args)\n"
        "    except SystemExit as done:\n"
        "        assert done.code == 0, (args, done.code)\n"
        f"open({str(listing)!r}, 'w').write(json.dumps(sorted(sys.modules)))\n"
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    loaded = {name.split(".")[0] for name in json.loads(listing.read_text())}
    assert "stitchplan" in loaded and "typer" in loaded  # the listing is real
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_runs_on_a_rectangle_import_neither_scipy_spatial_nor_optimize(tmp_path):
    """`simulate` and `plan` on a rectangular tissue (the shipped slab scene with a needle)
    load neither scipy.spatial nor scipy.optimize (about 0.1 and 0.08 s of every command's
    start-up; the neighbour search and the exit's root search are the package's own), nor the
    calibration input's models; with CHOLMOD (the `fast` extra), whose factors stay positive
    definite here, nor scipy.linalg and scipy.sparse.linalg (~0.07 s: imported for MINRES,
    GMRES and SuperLU only)."""
    listing = tmp_path / "modules.json"
    scenario = REPOSITORY / "configs" / "needle20_entry30.yaml"
    script = (
        "import json, sys\n"
        "from stitchplan.cli import app\n"
        f"for args in (['simulate', {str(scenario)!r}, '--no-estimate', '--spacing', '6', '--summary', "
        f"{str(tmp_path / 's.json')!r}],\n"
        f"             ['plan', {str(scenario)!r}, '--no-compare', '--no-verify', '--spacing', '6', '--export', "
        f"{str(tmp_path / 't.csv')!r}]):\n"
        "    try:\n"
        "        app(args)\n"
        "    except SystemExit as done:\n"
        "        assert done.code == 0, (args, done.code)\n"
        f"open({str(listing)!r}, 'w').write(json.dumps(sorted(sys.modules)))\n"
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env={**os.environ, "STITCHPLAN_REPLAY_HELPER": "0"})
    assert run.returncode == 0, run.stderr
    loaded = set(json.loads(listing.read_text()))
    assert "scipy.sparse" in loaded and (tmp_path / "t.csv").exists()  # the runs were real
    assert not loaded & {"scipy.spatial", "scipy.optimize", "stitchplan.config.calibration"}
    if cholesky_available():
        assert not loaded & {"scipy.linalg", "scipy.sparse.linalg"}, sorted(loaded & {"scipy.linalg", "scipy.sparse.linalg"})
    else:  # SuperLU factors every matrix: imported with the factorization module
        assert "scipy.sparse.linalg" in loaded


def test_version_is_answered_before_the_app_loads():
    """`stitchplan --version` (the console entry point) prints the version without importing
    typer or the commands."""
    script = ("import sys\n"
              "sys.argv = ['stitchplan', '--version']\n"
              "from stitchplan.cli import main\n"
              "main()\n"
              "print(sorted({name.split('.')[0] for name in sys.modules} & {'typer', 'click', 'numpy'}))\n"
              "print('stitchplan.cli.commands' in sys.modules)\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines() == [f"stitchplan {stitchplan.__version__}", "[]", "False"], run.stdout


# --- choices -------------------------------------------------------------------------------------


def test_choice_enums_equal_the_config_choices():
    from stitchplan.config import LINEAR_SOLVERS, TIP_TRACKING

    assert tuple(choice.value for choice in cli.LinearSolver) == tuple(LINEAR_SOLVERS)
    assert tuple(choice.value for choice in cli.TipTracking) == tuple(TIP_TRACKING)


@pytest.mark.parametrize("command", ["simulate", "plan"])
def test_help_lists_the_choices(command):
    result = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "250"})  # no wrapping
    assert result.exit_code == 0
    assert "<direct|minres>" in result.stdout
    assert "<auto|inverse-gradient|levenberg-marquardt>" in result.stdout


def test_choice_option_reaches_the_command_as_its_value(monkeypatch, tmp_path):
    """--linear-solver minres arrives at the numerics as the string 'minres'."""
    seen = {}

    def fake_resolve(scenario, tip_tracking, linear_solver, **limits):
        seen.update(tip_tracking=tip_tracking, linear_solver=linear_solver)
        raise NumericalFailure("stop here")

    monkeypatch.setattr("stitchplan.study.auto.resolve_accuracy", fake_resolve)
    scenario = write_needle_scene(tmp_path)
    result = invoke("simulate", scenario, "--linear-solver", "minres", "--tip-tracking", "inverse-gradient")
    assert one_error_line(result, 1) == "error: stop here"
    assert seen == {"tip_tracking": "inverse-gradient", "linear_solver": "minres"}
    assert type(seen["linear_solver"]) is str


# --- usage errors --------------------------------------------------------------------------------


@pytest.mark.parametrize("args,expected", [
    (["deform", "{scenario}", "--spacing", "abc"], "error: --spacing: got 'abc', expected a number"),
    (["deform", "{scenario}", "--spacing", "0"], "error: --spacing: got 0.0, expected a positive number (mm)"),
    (["deform", "{scenario}", "--dilation", "nan"], "error: --dilation: got nan, expected a number > 1"),
    (["simulate", "{scenario}", "--linear-solver", "lu"],
     "error: --linear-solver: got 'lu', expected one of direct, minres"),
    (["plan", "{scenario}"], "error: missing option '--export'; see 'stitchplan plan --help'"),
    (["deform", "{scenario}", "--unknown"], "error: no such option: --unknown"),
    (["deform"], "error: missing argument 'SCENARIO'; see 'stitchplan deform --help'"),
    (["deform", "{scenario}", "-v", "-q"], "error: -v/--verbose and -q/--quiet: got both"),
    (["frobnicate"], "error: no such command 'frobnicate'"),
    # click's suggestion ends in a question mark: the pointer to --help is a sentence of its own
    (["stduy"], "error: no such command 'stduy'. Did you mean 'study'? See 'stitchplan --help'."),
])
def test_usage_error_is_one_line_with_exit_code_2(slab_path, args, expected):
    result = CliRunner().invoke(app, [a.format(scenario=slab_path) for a in args], prog_name="stitchplan")
    line = one_error_line(result, 2)
    assert line.startswith(expected), line
    assert line.count("--spacing") <= 1


def test_a_problem_two_models_of_a_plan_share_is_said_once(tmp_path):
    """--dilation out of range is refused for the planned and the refined model alike: one line."""
    result = invoke("plan", write_needle_scene(tmp_path), "--export", tmp_path / "t.csv", "--dilation", "50")
    assert one_error_line(result, 2).startswith("error: --dilation: got 50, expected at most 10")
    assert not (tmp_path / "t.csv").exists()


def test_usage_error_from_the_console_entry_point(tmp_path):
    """The real entry point (no CliRunner): a missing required option is one line on stderr."""
    run = run_module("plan", tmp_path / "scene.yaml")
    assert run.returncode == 2
    assert run.stdout == ""
    assert run.stderr.splitlines() == ["error: missing option '--export'; see 'python -m stitchplan plan --help'"]


def test_a_real_process_ends_with_its_outputs_whole_and_its_lines_written(tmp_path):
    """The console entry point ends a finished command without the interpreter's teardown
    (cli._exit): its outputs, its result line, its log lines (-v) and its exit code are all
    there, through a pipe; and a refused input still exits 2 with its one line."""
    import h5py

    scene = write_needle_scene(tmp_path)
    run = run_module("simulate", scene, "--summary", tmp_path / "s.json", "--out", tmp_path / "run.h5", "-v")
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("simulate: ") and run.stdout.endswith("\n")
    assert "needle rotation" in run.stderr  # the -v log lines were flushed
    summary = json.loads((tmp_path / "s.json").read_text())
    with h5py.File(tmp_path / "run.h5") as log:
        assert log.attrs["command"] == "simulate"
        assert len(log["steps/step"]) == summary["steps"] > 0
    refused = run_module("simulate", tmp_path / "absent.yaml")
    assert refused.returncode == 2 and refused.stderr.startswith("error: ")


# --- the project's errors and bugs ---------------------------------------------------------------


def write_needle_scene(folder: Path) -> Path:
    import yaml

    path = folder / "scene.yaml"
    path.write_text(yaml.safe_dump({
        "tissue": {"size": [20.0, 20.0], "thickness": 10.0, "clamped": ["right"],
                   "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
        "discretization": {"spacing": 5.0},
        "needle": {"radius": 8.88, "entry": [0.0, 18.0], "turn": "cw", "step": 0.3,
                   "friction": 0.0602, "cutting_force": 0.7}}))
    return path


def test_input_error_exits_2_naming_the_file(tmp_path):
    result = invoke("deform", tmp_path / "absent.yaml", "--summary", tmp_path / "summary.json")
    line = one_error_line(result, 2)
    assert "absent.yaml" in line and "cannot be read" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_file_name_holding_a_line_break_stays_in_its_one_error_line(tmp_path, slab_raw):
    """A file name with a line break (or a carriage return, a line separator) printed raw made
    one problem two lines, the second without `error:`; it is shown escaped, as Python writes it."""
    import yaml

    missing = tmp_path / "a\nb.yaml"
    line = one_error_line(invoke("deform", missing), 2)
    assert line == f"error: {tmp_path}/a\\nb.yaml: cannot be read (No such file or directory)"
    del slab_raw["loads"]
    bad = tmp_path / "c\rd\u2028e.yaml"
    bad.write_text(yaml.safe_dump(slab_raw))
    line = one_error_line(invoke("deform", bad, "--summary", tmp_path / "s.json"), 2)
    assert line.startswith(f"error: {tmp_path}/c\\rd\\u2028e.yaml: loads: got none, expected at least one load")
    scenario = tmp_path / "slab.yaml"
    scenario.write_text(yaml.safe_dump({**slab_raw, "needle": {"radius": 8.88, "entry": [0.0, 30.0], "turn": "cw",
                                                               "step": 0.08}}))
    (tmp_path / "out\nfile").write_text("")
    for given in (["--out", f"{tmp_path}/out\nfile"], [f"--out={tmp_path}/out\nfile"]):
        line = one_error_line(invoke("study", scenario, *given), 2)
        assert line == f"error: --out: got {tmp_path}/out\\nfile, a file; expected a folder"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c\rd\u2028e.yaml", "out\nfile", "slab.yaml"]


@pytest.mark.parametrize("how", ["lines", "newlines"])
def test_input_error_with_several_lines_prints_each_as_an_error_line(monkeypatch, slab_path, how):
    problems = ["tissue.thickness: got -1.0, expected a positive number (mm)",
                "needle.step: got 0, expected a positive number (rad)"]

    def fail(*args, **kwargs):
        error = InputError("\n".join(problems))
        if how == "lines":
            error = InputError(f"{len(problems)} problems")
            error.lines = problems
        raise error

    monkeypatch.setattr("stitchplan.tissue.deform.run_deform", fail)
    result = invoke("deform", slab_path)
    assert result.exit_code == 2
    # raised while the run builds its model: each line names the scenario file
    assert result.stderr.splitlines() == [f"error: {slab_path}: {problem}" for problem in problems]
    assert result.stdout == ""


def test_numerical_failure_exits_1_with_one_line_and_no_output(monkeypatch, slab_path, tmp_path):
    def fail(*args, **kwargs):
        raise NumericalFailure("Newton failed at load step 3 (load fraction 0.3000) after 4 step cuts")

    monkeypatch.setattr("stitchplan.tissue.deform.run_deform", fail)
    result = invoke("deform", slab_path, "--probes-out", tmp_path / "probes.csv", "--summary",
                    tmp_path / "summary.json")
    line = one_error_line(result, 1)
    assert line == "error: Newton failed at load step 3 (load fraction 0.3000) after 4 step cuts"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slab_edge_load.yaml"]


@pytest.mark.parametrize("bug", [ZeroDivisionError("division by zero"), ValueError("operands could not be broadcast"),
                                 KeyError("spacing")])
def test_an_unexpected_exception_is_not_swallowed(monkeypatch, slab_path, bug):
    """Anything but the project's own errors is a bug: it propagates (CliRunner keeps it) and the
    command fails; it is not turned into an `error:` line."""
    def fail(*args, **kwargs):
        raise bug

    monkeypatch.setattr("stitchplan.tissue.deform.run_deform", fail)
    result = invoke("deform", slab_path)
    assert result.exit_code != 0
    assert result.exception is bug
    assert "error:" not in result.output


def test_an_unexpected_exception_shows_its_traceback(slab_path):
    """In a real process the bug ends with Python's traceback and a non-zero exit code."""
    script = ("import sys\n"
              "import stitchplan.tissue.deform as deform\n"
              "def broken(*args, **kwargs):\n"
              "    raise ZeroDivisionError('a bug')\n"
              "deform.run_deform = broken\n"
              "from stitchplan.cli import main\n"
              f"sys.argv = ['stitchplan', 'deform', {str(slab_path)!r}]\n"
              "main()\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 1
    assert "Traceback (most recent call last)" in run.stderr
    assert run.stderr.strip().splitlines()[-1] == "ZeroDivisionError: a bug"
    assert "error:" not in run.stderr


# --- logging -------------------------------------------------------------------------------------


def test_verbosity_levels_of_deform(slab_path):
    """Default: nothing on stderr for a clean run; -v: the load steps with their Newton
    iterations (INFO); -vv: every Newton iteration (DEBUG); -q: nothing but errors."""
    runs = {flags: invoke("deform", slab_path, "--spacing", "10", *flags)
            for flags in ((), ("-v",), ("-vv",), ("-q",))}
    for flags, result in runs.items():
        assert result.exit_code == 0, (flags, result.output)
        # the 10 mm grid (121) plus the particles graded toward the segment ends
        assert result.stdout.startswith("deform: 177 particles, 10 load steps")
    assert runs[()].stderr == "" and runs[("-q",)].stderr == ""
    info = runs[("-v",)].stderr.splitlines()
    steps = [line for line in info if ": load step " in line]
    assert len(steps) == 10 and all(line.startswith("INFO stitchplan.tissue.deform: ") for line in steps)
    assert "load step 10/10: load fraction 1.000" in steps[-1] and "Newton iterations" in steps[-1]
    assert not any(line.startswith("DEBUG") for line in info)
    debug = runs[("-vv",)].stderr.splitlines()
    assert sum("Newton iteration 1:" in line for line in debug) >= 10  # at least one per load step
    assert all(line.startswith(("INFO ", "DEBUG ")) for line in debug)


# --- schema --------------------------------------------------------------------------------------


def test_schema_prints_the_json_schema_of_scenario_files():
    result = invoke("schema")
    assert result.exit_code == 0, result.output
    schema = json.loads(result.stdout)
    assert isinstance(schema, dict)
    assert {"tissue", "needle", "loads"} <= set(schema["properties"])
    assert "tissue" in schema.get("required", [])


def test_the_command_reuses_freed_memory():
    """After the console entry point has run a command, glibc's malloc serves 1 MiB blocks
    from its heap and keeps them there once freed (stitchplan/allocator.py): no block is
    mapped on its own (mallinfo's hblks) and the 16 MiB freed stay at the heap's top
    (keepcost), where glibc's default maps the first block by itself and trims the heap's top
    below 2 MiB. Elsewhere (not glibc) reuse_freed_memory reports that it did nothing."""
    from stitchplan.allocator import reuse_freed_memory

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        assert reuse_freed_memory() is False
        return
    script = (
        "import ctypes, sys\n"
        "import stitchplan.cli as cli\n"
        "if sys.argv[1] == 'default':\n"
        "    import stitchplan.allocator as allocator; allocator.reuse_freed_memory = lambda: False\n"
        "sys.argv = ['stitchplan', 'schema']\n"
        "cli._exit = lambda code: None  # stay alive after the command\n"
        "try:\n"
        "    cli.main()\n"
        "except SystemExit:\n"
        "    pass\n"
        "libc = ctypes.CDLL('libc.so.6')\n"
        "class Info(ctypes.Structure):\n"
        "    _fields_ = [(name, ctypes.c_int) for name in ('arena', 'ordblks', 'smblks', 'hblks', 'hblkhd',\n"
        "                'usmblks', 'fsmblks', 'uordblks', 'fordblks', 'keepcost')]\n"
        "libc.mallinfo.restype = Info\n"
        "libc.malloc.restype = ctypes.c_void_p\n"
        "mapped = libc.mallinfo().hblks\n"
        "blocks = [libc.malloc(2**20) for _ in range(16)]\n"
        "mapped = libc.mallinfo().hblks - mapped\n"
        "for block in reversed(blocks):\n"
        "    libc.free(ctypes.c_void_p(block))\n"
        "sys.stderr.write(f'{mapped} {libc.mallinfo().keepcost}')\n"
    )
    mapped, top = {}, {}  # blocks mapped on their own; the free memory left at the heap's top
    # without glibc's malloc variables: a Dask LocalCluster started by an earlier test sets
    # MALLOC_TRIM_THRESHOLD_ in this process's environment (for its workers), and with it set
    # the command leaves malloc as the user set it
    environment = {key: value for key, value in os.environ.items() if not key.startswith("MALLOC_")}
    for variant in ("command", "default"):
        run = subprocess.run([sys.executable, "-c", script, variant], capture_output=True, text=True,
                             env=environment)
        assert run.returncode == 0, run.stderr
        mapped[variant], top[variant] = map(int, run.stderr.strip().splitlines()[-1].split())
    assert mapped["command"] == 0 and mapped["default"] >= 1, mapped
    assert top["command"] >= 16 * 2**20 and top["default"] < 2 * 2**20, top


def test_a_run_estimated_above_the_accuracy_it_was_chosen_for_says_so():
    """The auto discretization meets an accuracy by its estimate from runs at h and h/2; the
    run's own estimate (from a run at 2h) can come out above it: an accuracy-check note then
    says both, never silence beside a contradicting summary."""
    from types import SimpleNamespace

    from stitchplan.cli.runs import _accuracy_events
    from stitchplan.events import EventKind

    above = SimpleNamespace(estimate_mm=0.0129, other_spacing_mm=9.96)
    [event] = _accuracy_events(0.01, above)
    assert event.kind == EventKind.ACCURACY_CHECK
    assert event.message.startswith("accuracy: the run's own exit error estimate, 0.0129 mm (from the run at "
                                    "9.96 mm), is above the 0.01 mm asked for")
    assert _accuracy_events(0.01, SimpleNamespace(estimate_mm=0.009, other_spacing_mm=9.96)) == []
    assert _accuracy_events(None, above) == [] and _accuracy_events(0.01, None) == []
