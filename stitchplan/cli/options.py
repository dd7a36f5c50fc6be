"""Options and helpers shared by the commands: the enumerated choices, discretization
overrides, logging switches, and the small parsers of option values."""

from __future__ import annotations

import contextlib
import math
import os
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import Optional

import typer

# the largest --spacing: config.blocks' MAX_SCENE_MM, a file's bound (written here, not imported, as
# the choices below: the config imports numpy, and --help must not)
MAX_SPACING_MM = 10_000.0


class LinearSolver(str, Enum):
    """--linear-solver; the values of config.LINEAR_SOLVERS (written here, not imported:
    the config imports numpy, and --help must not)."""

    direct = "direct"
    minres = "minres"


class TipTracking(str, Enum):
    """--tip-tracking; the values of config.TIP_TRACKING (see LinearSolver)."""

    auto = "auto"
    inverse_gradient = "inverse-gradient"
    levenberg_marquardt = "levenberg-marquardt"


def _positive_spacing(value: Optional[float]) -> Optional[float]:
    if value is not None and not 0 < value < math.inf:  # also refuses nan
        raise typer.BadParameter(f"got {value!r}, expected a positive number (mm)")
    if value is not None and value > MAX_SPACING_MM:  # as a file's spacing (config.blocks.SceneSpacing)
        raise typer.BadParameter(f"got {value:g}, expected a positive number of at most {MAX_SPACING_MM:g} (mm; a "
                                 f"spacing beyond {MAX_SPACING_MM:g} mm, the bound of every length of a scene, is a "
                                 "unit mistake)")
    return value


def _dilation_above_one(value: Optional[float]) -> Optional[float]:
    if value is not None and not 1 < value < math.inf:
        raise typer.BadParameter(f"got {value!r}, expected a number > 1 (kernel support / spacing)")
    return value


def named_file(param: typer.CallbackParam, value: Optional[Path]) -> Optional[Path]:
    """An input file's argument or option: an empty one given as '' becomes Path('.'), the
    working folder, which would be reported as a folder that cannot be read. An option's text
    is the one given for it (given_value); an argument's, a lone '' on the command line."""
    if value is None or str(value) != ".":
        return value
    argv = command_line_argv() or []
    if param.param_type_name == "option":
        empty = any(given_value(name) == "" for name in param.opts)
    else:
        empty = "" in argv and "." not in argv
    if empty:
        raise typer.BadParameter("got an empty path, expected a file name")
    return value


ScenarioArgument = typer.Argument(..., metavar="SCENARIO", callback=named_file,
                                  help="Scenario YAML file (see README: Scenario format).")
SpacingOption = typer.Option(None, "--spacing", callback=_positive_spacing,
                             help="Particle spacing in mm (overrides the scenario).")
DilationOption = typer.Option(None, "--dilation", callback=_dilation_above_one,
                              help="Kernel support / spacing (overrides the scenario).")
CalibrationSpacingOption = typer.Option(None, "--spacing", callback=_positive_spacing,
                                        help="Particle spacing in mm (overrides the calibration file).")
CalibrationDilationOption = typer.Option(None, "--dilation", callback=_dilation_above_one,
                                         help="Kernel support / spacing (overrides the calibration file).")
SummaryOption = typer.Option(None, "--summary", help="Write a JSON summary here.")
VerboseOption = typer.Option(
    0, "--verbose", "-v", count=True, show_default=False, metavar="",
    help="Log progress on stderr (load steps and needle steps with their Newton iterations); -vv also every "
    "Newton iteration.")
MaterialFitVerboseOption = typer.Option(
    0, "--verbose", "-v", count=True, show_default=False, metavar="",
    help="Log progress on stderr (each of the fit's evaluations: the moduli tried, their misfit and Newton "
    "iterations); -vv also every Newton iteration.")
NeedleFitVerboseOption = typer.Option(0, "--verbose", "-v", count=True, show_default=False, metavar="",
                                      help="Accepted as by the other commands; the needle fit is one linear "
                                      "least-squares solve, with no progress to log.")
SchemaVerboseOption = typer.Option(0, "--verbose", "-v", count=True, show_default=False, metavar="",
                                   help="Accepted as by the other commands; the schema has no progress to log.")
QuietOption = typer.Option(False, "--quiet", "-q",
                           help="Errors only: no warnings, notes or progress bar.")


def setup_logging(verbose: int, quiet: bool = False) -> None:
    """-q: errors only; default: warnings; -v: progress (INFO); -vv: every iteration (DEBUG)."""
    from ..errors import InputError
    from ..io.progress import configure_terminal

    if verbose and quiet:
        raise InputError("-v/--verbose and -q/--quiet: got both, expected at most one")
    configure_terminal(verbose=int(verbose), quiet=quiet)


def load_with_options(scenario_path: Path, spacing: Optional[float], dilation: Optional[float]):
    from ..config import input_error, load_scenario, with_discretization
    from ..errors import InputError
    from .group import problem_lines

    scenario = load_scenario(scenario_path)
    try:
        return with_discretization(scenario, spacing=spacing, dilation=dilation)
    except InputError as error:  # the file's block, made invalid by the options (a needle_spacing above --spacing)
        options = _discretization_options()
        raise input_error([f"{options} over {scenario_path}: {line}" for line in problem_lines(error)]) from None


def _discretization_options() -> str:
    """--spacing and --dilation as given on the command line, for a problem they made."""
    return " and ".join(f"{option} {given_value(option)}" for option in ("--spacing", "--dilation")
                        if given_value(option) is not None)


def check_command_outputs(outputs: dict[str, Optional[Path]],
                          inputs: Optional[dict[str, Optional[Path]]] = None,
                          out_format: Optional[str] = None) -> None:
    """Fail before any work if an output cannot be written or is the same file as another
    output or an input: `{option: path}` each (None: not given). A figure option's file
    must be named .png: the figures are PNG, and other bytes under .pdf or .svg would
    mislead whatever opens them. A file named for another of the formats written (a run
    log `--out run.json`, a `--summary s.h5`: two outputs swapped) is refused; a name of no
    such format is the user's choice. `out_format`: what `--out` writes (HDF5, YAML); None: no
    format checked here, where a later call knows more inputs (an output over an input says more)."""
    from ..config import input_error
    from ..errors import InputError
    from ..io.files import check_outputs

    for option, path in outputs.items():
        given = given_value(option)
        if path is not None and given == "":  # Path("") is ".", the working folder
            raise InputError(f"{option}: got an empty path, expected a file name")
        if path is not None and given is not None and given.endswith(("/", os.sep)):
            raise InputError(f"{option}: got {given}, a folder name (it ends in /); expected a file name")
    check_outputs(outputs, inputs)  # first: an output that would overwrite an input says so
    formats = {} if out_format is None else {**OUTPUT_FORMATS, "--out": out_format}
    lines = _output_format_problems(outputs, formats)
    if lines:
        raise input_error(lines)


def _output_format_problems(outputs: dict[str, Optional[Path]], formats: dict[str, str]) -> list[str]:
    """A line for each figure not named .png and each output named for another format than it
    writes (`formats`: option -> format)."""
    lines = []
    for option, path in outputs.items():
        if path is None:
            continue
        if option in PNG_OPTIONS and path.suffix.lower() != ".png":
            lines.append(f"{option}: got {path}, expected a file name ending in .png (the figures are PNG)")
            continue
        written = formats.get(option)
        named = next((name for name, suffixes in FORMAT_SUFFIXES.items() if path.suffix.lower() in suffixes), None)
        if written is not None and named is not None and named != written:
            lines.append(f"{option}: got {path}, {_with_article(named)} file name; expected "
                         f"{_with_article(written)} file name ({', '.join(FORMAT_SUFFIXES[written])})")
    return lines


def _with_article(acronym: str) -> str:
    """'an HDF5', 'a JSON': the article as the first letter is spoken."""
    return f"{'an' if acronym[0] in 'AEFHILMNORSX' else 'a'} {acronym}"


def given_value(option: str) -> Optional[str]:
    """The text given for `option` on the command line, as typed (a Path drops a trailing
    slash), or None."""
    argv = command_line_argv() or []
    given = None
    for k, arg in enumerate(argv):  # the last one, as the option takes it
        if arg == option and k + 1 < len(argv):
            given = argv[k + 1]
        elif arg.startswith(option + "="):
            given = arg[len(option) + 1:]
    return given


PNG_OPTIONS = ("--plot", "--uncertainty-plot")
FORMAT_SUFFIXES = {"HDF5": (".h5", ".hdf5"), "JSON": (".json",), "CSV": (".csv",), "YAML": (".yaml", ".yml"),
                   "PNG": (".png",)}
OUTPUT_FORMATS = {"--summary": "JSON", "--export": "CSV", "--probes-out": "CSV", "--reactions-out": "CSV"}


def run_provenance(scenario_path: Optional[Path] = None, scenario=None) -> dict:
    """Version, command line (argv), scenario path and the SHA-256 of the `scenario` as
    loaded, time: for the summaries."""
    from ..io.files import provenance

    return provenance(command_line_argv(), scenario_path, getattr(scenario, "source_sha256", None))


def command_line_argv() -> Optional[list[str]]:
    """The command line as a list (kept by cli.group.Commands), None outside a command."""
    from .group import COMMAND_LINE

    return COMMAND_LINE.get()


def choice_value(choice: Optional[Enum]) -> Optional[str]:
    return None if choice is None else choice.value



def parse_steps(text: Optional[str]) -> Optional[list[int]]:
    from ..errors import InputError

    if not text:
        return None
    try:
        return [int(part) for part in text.split(",")]  # an empty item (10,,20) is a typing mistake too
    except ValueError:
        raise InputError(f"--plot-steps: got {text!r}, expected comma-separated step numbers") from None


LinearSolverOption = typer.Option(None, "--linear-solver",
                                  help="Saddle-point solver (overrides the scenario).")
TipTrackingOption = typer.Option(
    None, "--tip-tracking",
    help="How the tip's next material point is found; auto: inverse gradient, falling back to "
    "Levenberg-Marquardt (overrides the scenario).")


def scenario_expected_steps(scenario) -> int:
    from ..needle.geometry import scenario_needle

    return scenario_needle(scenario).expected_steps


def checked_needle_geometry(scenario_path: Path, scenario, command: str):
    """The scenario's needle geometry; a needle that cannot enter or exit, or that puts no
    load on the tissue, is refused with the file named."""
    from ..config.scenario import require_needle_loads
    from ..needle.geometry import scenario_needle

    with naming_files(scenario_path):
        geometry = scenario_needle(scenario)
    require_needle_loads(scenario, scenario_path, command)
    return geometry


@contextmanager
def naming_files(scenario_path: Path, center_path: Optional[Path] = None):
    """Input errors met after the scenario was loaded (the needle, the resource guard, the
    model's build, a replayed centre path) name what they concern: the option for a line
    that starts with one, --center-path and its file for the path's rows (as its reading's
    errors do), the scenario's for the rest (a calibration file's for calibrate material), a
    problem of the discretization with the --spacing and --dilation that changed it."""
    from ..config import input_error
    from ..errors import InputError
    from .group import problem_lines

    try:
        yield
    except InputError as error:
        named = []
        options = _discretization_options()
        for line in problem_lines(error):
            if center_path is not None and line.startswith("centre path: "):
                line = f"--center-path: {center_path}: {line.removeprefix('centre path: ')}"
            elif options and line.startswith("discretization: "):  # the file's, changed by the options
                line = f"{options} over {scenario_path}: {line}"
            elif not line.startswith(("--", f"{scenario_path}:")):
                line = f"{scenario_path}: {line}"
            named.append(line)
        raise input_error(named) from None


@contextmanager
def naming_option(option: str, path: Path):
    """Input errors about the file an option gives (the lines starting with its path) name the
    option first, as `--center-path: path.csv: line 5, ...`."""
    from ..config import input_error
    from ..errors import InputError

    try:
        yield
    except InputError as error:
        lines = getattr(error, "lines", None) or [str(error)]
        raise input_error([f"{option}: {line}" if line.startswith(f"{path}:") else line for line in lines]) from None


def check_plot_steps(steps: Optional[list[int]], scenario) -> None:
    """--plot-steps within the run: 0 (the entry) to the last step before the undeformed
    circle's exit (the needle geometry knows it before the run)."""
    from ..errors import InputError

    if not steps:
        return
    last = scenario_expected_steps(scenario) - 1
    outside = [step for step in steps if not 0 <= step <= last]
    if outside:
        raise InputError(f"--plot-steps: got {','.join(map(str, outside))}, expected steps between 0 "
                         f"(the entry) and {last} (the undeformed circle's last step before its tip exits; "
                         "a run whose tip exits sooner draws its last step instead)")


def plot_steps_note(steps: Optional[list[int]], result, quiet: bool) -> None:
    """A note when the run ended before a requested step (the plot then draws its last)."""
    late = [step for step in steps or () if step > len(result.steps)]
    if late and not quiet:
        typer.echo(f"note: --plot-steps {','.join(map(str, late))}: the tip left the tissue after step "
                   f"{len(result.steps)}; drew step {len(result.steps)} instead", err=True)


def _at_least(minimum: int, expected: str):
    """An option callback refusing a count below `minimum` (`expected`: what it should be)."""

    def check(value: Optional[int]) -> Optional[int]:
        if value is not None and value < minimum:
            raise typer.BadParameter(f"got {value!r}, expected {expected}")
        return value

    return check


MaxParticlesOption = typer.Option(
    None, "--max-particles", callback=_at_least(1, "a positive number of particles"), metavar="N",
    help="Refuse models of more than N particles (default 50000; see README: resource guard).")
NoResourceCheckOption = typer.Option(
    False, "--no-resource-check",
    help="Run even when the estimated particles, needle steps, kernel neighbours or memory exceed "
    "the resource guard's limits.")
CalibrationNoResourceCheckOption = typer.Option(
    False, "--no-resource-check",
    help="Run even when the estimated particles, kernel neighbours or memory exceed the resource guard's limits.")


def guard_limits(max_particles: Optional[int], no_resource_check: bool):
    """The resource guard's limits (None: no check)."""
    if no_resource_check:
        return None
    from ..resources.limits import Limits

    return Limits() if max_particles is None else Limits(max_particles=max_particles)


def guard_runs(scenario_path: Path, limits, *runs: tuple, names: Optional[dict] = None,
               linear_solver: Optional[str] = None, alongside: Optional[list] = None, forked: bool = True,
               workers: Optional[int] = None, condition_numbers: bool = False, in_one_process: bool = False,
               beside: tuple = (), data=None) -> None:
    """Refuse, before any heavy work, runs past the resource guard's limits; `runs` are
    (kind, scenario, label, count) with kind "deform" or "insertion", and optionally the
    resources.origin.Origin of the run's discretization (default: the file's, with the fields in
    `names` set by options, option_names); `linear_solver`: the --linear-solver option;
    `alongside`: runs of the same form in helper processes at the same time, counted in the
    memory held at once with `runs` (resources.guard.check_resources; None: `runs` do not go on at
    once), in processes `forked` from this one or (False) Dask workers; `workers`: `runs` go
    on in this many worker processes, none here (check_resources); `condition_numbers`: `runs`
    take each needle step's dense condition numbers (--condition-numbers; not their replays);
    `in_one_process`: `runs` are held at once in this process (check_resources), with `beside`
    (runs of the same form counted in that memory only: check_resources), and `data` (a
    resources.costs.Data: a calibration's markers) held with them.
    Lines name the file, or the option."""
    if limits is None:
        return
    from ..resources.costs import estimate
    from ..resources.guard import check_resources
    from ..resources.origin import Origin

    def estimates(given, condition: bool = False) -> list:
        return [estimate(scenario, kind, label, count, origin=origin[0] if origin else Origin(names or {}),
                         linear_solver=linear_solver, condition_numbers=condition)
                for kind, scenario, label, count, *origin in given]

    with naming_files(scenario_path):
        check_resources(estimates(runs, condition_numbers), limits, alongside=None if alongside is None else estimates(alongside),
                        forked=forked, workers=workers, in_one_process=in_one_process, beside=estimates(beside),
                        data=data)


def estimate_run(scenario, label: str, skip: str, names: Optional[dict] = None) -> tuple:
    """The exit error estimate's (or the predicted aim's) replay at twice the spacing, as a
    run of `guard_runs`'s `alongside`; `skip` says how to leave it out."""
    from ..planning.replay_models import replay_scenario
    from ..resources.origin import replay_origin

    return ("insertion", replay_scenario(scenario, verify=False), label, 1,
            replay_origin(scenario, names, " in its replay at twice the spacing", skip))


def option_names(spacing: Optional[float], dilation: Optional[float]) -> dict:
    """The discretization fields that command-line options set, named as the options."""
    given = {"spacing": ("--spacing", spacing), "dilation": ("--dilation", dilation)}
    return {field: option for field, (option, value) in given.items() if value is not None}


def guard_calibration(calibration_path: Path, problem, limits, names: Optional[dict] = None,
                      estimate: bool = True) -> None:
    """The resource guard on the forward model of each experiment of a material calibration
    (run once per forward evaluation of the fit: grid^2 + max_evaluations times), all of them
    held at once: each experiment keeps its model and tangent factor between evaluations.
    With `estimate`, also each experiment's model at twice the spacing (the discretization
    estimate's least squares: up to max_evaluations more), held beside them, and the fit's
    markers (costs.marker_bytes each), named by the largest marker file."""
    from ..config import Scenario
    from ..errors import InputError
    from ..resources.costs import Data, marker_bytes
    from ..resources.model_size import kernel_neighbours

    fit = problem.fit

    def runs(discretization, label: str, count: int) -> list[tuple]:
        return [("deform", Scenario(tissue=problem.tissue, discretization=discretization, loads=experiment.loads,
                                    load_steps=experiment.load_steps), f"experiments[{k}]{label}", count)
                for k, experiment in enumerate(problem.experiments)]

    coarse = []
    if estimate:
        with contextlib.suppress(InputError):  # a spacing no file may give: the estimate says so itself
            coarse = runs(problem.discretization.replaced(spacing=problem.estimate_spacing), " at twice the spacing",
                          fit.max_evaluations)
    counts = [len(experiment.markers) for experiment in problem.experiments]
    k = counts.index(max(counts))
    markers = Data(f"experiments[{k}].markers: {problem.experiments[k].source}", counts[k], sum(counts), "markers",
                   marker_bytes(kernel_neighbours(problem.discretization.dilation)), "in all experiments",
                   "fit fewer markers (a subset of them)")
    guard_runs(calibration_path, limits, *runs(problem.discretization, "", fit.grid_points ** 2 + fit.max_evaluations),
               names=names, in_one_process=True, beside=tuple(coarse), data=markers)


def recording_rows(limits, plot: bool) -> tuple[Optional[int], str]:
    """The rows calibrate needle may read in both recordings within the resource guard's
    `limits` (None: no check), and why, as a refusal says it (None, "": no limit)."""
    from ..resources.costs import BASE_MEMORY, MEMORY_PER_RECORDING_ROW, PLOT_MEMORY
    from ..resources.formatting import bytes_text
    from ..resources.guard import SKIP_GUARD, data_budget, items_within

    held = BASE_MEMORY + (PLOT_MEMORY if plot else 0.0)
    budget = None if limits is None else data_budget(held, limits)
    if budget is None:
        return None, ""
    bytes_left, within = budget
    what = "the interpreter and the --plot's figure" if plot else "the interpreter"
    return items_within(MEMORY_PER_RECORDING_ROW, bytes_left), (
        f" {within} (~{bytes_text(MEMORY_PER_RECORDING_ROW)} a row beside ~{bytes_text(held)} for {what}); record "
        f"fewer rows (or average them), or {SKIP_GUARD}")

def echo_notes(notes, quiet: bool) -> None:
    """A command's notes as `note:` lines on stderr (none with -q)."""
    if not quiet:
        for note in notes:
            typer.echo(f"note: {note}", err=True)


def echo_events(events, quiet: bool, shown: int = 3) -> None:
    """A run's events as `note:` lines on stderr (none with -q): every one about the whole run
    (a missed target, a verification that could not be made: a few at most), then its steps'
    in order up to `shown` notes in all; a run's verdict is never cut behind its steps' notes."""
    whole_run = [event for event in events if event.step is None]
    of_steps = [event for event in events if event.step is not None]
    listed = whole_run + of_steps[:max(0, shown - len(whole_run))]
    left = len(events) - len(listed)
    more = [f"{left} more note{'s' if left > 1 else ''} in the summary and run log"] if left else []
    echo_notes([event.message for event in listed] + more, quiet)


def parse_base_transform(text: Optional[str]):
    """ROTATION_DEG,TX_MM,TY_MM within the bounds that keep the base-frame columns of
    trajectory.csv meaningful (planning.trajectory)."""
    from ..errors import InputError
    from ..decimals import parse_number
    from ..config.plan_blocks import MAX_BASE_OFFSET_MM, MAX_BASE_ROTATION_DEG

    if text is None:
        return None
    values = [parse_number(part) for part in text.split(",")]  # None: not a finite number
    bounds = (MAX_BASE_ROTATION_DEG, MAX_BASE_OFFSET_MM, MAX_BASE_OFFSET_MM)
    if len(values) != 3 or not all(value is not None and abs(value) <= bound for value, bound in zip(values, bounds)):
        raise InputError(f"--base-transform: got {text!r}, expected ROTATION_DEG,TX_MM,TY_MM: three numbers with "
                         f"|ROTATION_DEG| <= {MAX_BASE_ROTATION_DEG:g} and |TX_MM|, |TY_MM| <= {MAX_BASE_OFFSET_MM:g} "
                         f"(mm)")
    rotation, tx, ty = values
    return rotation, (tx, ty)


def check_replay_helper() -> None:
    """STITCHPLAN_REPLAY_HELPER 0 or 1 (or unset): the commands whose replays a helper runs
    refuse another value (a typo was read as "on")."""
    from ..early_helper import helper_variable_problem
    from ..errors import InputError

    problem = helper_variable_problem()
    if problem is not None:
        raise InputError(problem)


def check_angular_speed(speed: Optional[float]) -> None:
    """--angular-speed: slower than MIN_ANGULAR_SPEED, time_s would overflow to inf."""
    from ..errors import InputError
    from ..config.plan_blocks import MIN_ANGULAR_SPEED

    if speed is not None and not MIN_ANGULAR_SPEED <= speed < math.inf:  # also refuses nan
        raise InputError(f"--angular-speed: got {speed!r}, expected a positive speed in rad/s of at least "
                         f"{MIN_ANGULAR_SPEED:g}")


def check_plot_scale_option(scale: float, plot: Optional[Path]) -> None:
    """deform --plot-scale, before the run: positive and at most io.plots.MAX_PLOT_SCALE (near
    1e308 the drawn positions overflow), and given with the --plot it draws (without one it
    would be dropped without a word). plot_deformed checks the scale again when it draws."""
    from ..errors import InputError
    from ..io.plots import check_plot_scale

    check_plot_scale(scale)
    if scale != 1.0 and plot is None:
        raise InputError(f"--plot-scale: got {scale:g} without --plot, expected it with the --plot PNG it "
                         "enlarges the displacements in")




WorkersOption = typer.Option(  # checked with --scheduler by stitchplan.parallel.workers.check_workers
    None, "--workers", metavar="N",
    help="Run the independent runs (study's, or plan's with --uncertainty) on a local Dask cluster of N "
    "single-threaded worker processes (default: the CPU cores this process may use; at most 4 times as "
    "many; 0: one after another in this process).")
SchedulerOption = typer.Option(
    None, "--scheduler", metavar="ADDRESS",
    help="Run the independent runs (study's, or plan's with --uncertainty) on the running Dask cluster "
    "at ADDRESS (tcp://HOST:PORT, or tls://, ws://, wss://) instead of a local one; a scheduler that "
    "does not answer within 5 s is an error.")


def command_executor(workers: Optional[int], scheduler: Optional[str]):
    """The executor of a command's independent runs (stitchplan.parallel.executor.Executor), not
    yet started: --workers (0 to 4 x the usable cores) and the form of the --scheduler address are
    checked here, before any work, as InputErrors; the scheduler is reached when the executor
    starts."""
    from ..parallel.executor import Executor

    return Executor(workers=workers, scheduler=scheduler)
