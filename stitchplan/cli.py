"""Command-line interface: parse options, load the scenario, call one function, write results.

Heavy imports live inside the commands so `stitchplan --help` stays instant. Every error a
user can cause ends as one line on stderr and exit code 2, with no output file written.
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Simulate curved suture needle insertion into deformable tissue and plan the "
    "needle-centre trajectory that compensates the deformation.",
)
calibrate_app = typer.Typer(no_args_is_help=True, help="Fit model parameters to measurements.")
app.add_typer(calibrate_app, name="calibrate")

EXIT_USER_ERROR = 2

ScenarioArgument = typer.Argument(..., help="Scenario YAML file (see README: Scenario format).")
SpacingOption = typer.Option(None, "--spacing", help="Particle spacing in mm (overrides the scenario).")
DilationOption = typer.Option(None, "--dilation", help="Kernel support / spacing (overrides the scenario).")
SummaryOption = typer.Option(None, "--summary", help="Write a JSON summary here.")


def user_errors(command: Callable) -> Callable:
    """Turn the project's user-facing exceptions into one line on stderr and exit code 2."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        from .config import ScenarioError
        from .solver import SolverDivergence

        try:
            return command(*args, **kwargs)
        except (ScenarioError, SolverDivergence) as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(EXIT_USER_ERROR) from None
        except ValueError as error:  # domain checks raised by the numerics
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(EXIT_USER_ERROR) from None

    return wrapper


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _load(scenario_path: Path, spacing: Optional[float], dilation: Optional[float]):
    from .config import load_scenario, parse_discretization, with_discretization

    scenario = load_scenario(scenario_path)
    if spacing is not None:
        parse_discretization({"spacing": spacing}, "--spacing")
    if dilation is not None:
        parse_discretization({"dilation": dilation}, "--dilation")
    return with_discretization(scenario, spacing=spacing, dilation=dilation)


def _check_outputs(*paths: Optional[Path]) -> None:
    """Fail before any work if an output folder cannot exist (a file stands in its place)."""
    from .config import ScenarioError

    for path in paths:
        if path is None:
            continue
        for parent in Path(path).resolve().parents:
            if parent.exists():
                if not parent.is_dir():
                    raise ScenarioError(f"{path}: cannot write, {parent} is not a folder")
                break
        if Path(path).is_dir():
            raise ScenarioError(f"{path}: is a folder, expected a file name")


@app.command()
@user_errors
def deform(
    scenario_path: Path = ScenarioArgument,
    probes_out: Optional[Path] = typer.Option(None, "--probes-out", help="CSV x,y,ux,uy per probe."),
    reactions_out: Optional[Path] = typer.Option(None, "--reactions-out",
                                                 help="CSV segment,fx,fy per loaded segment."),
    summary: Optional[Path] = SummaryOption,
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the deformed tissue."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log solver progress."),
) -> None:
    """Static large-deformation solve of the slab under the scenario's `loads`."""
    _setup_logging(verbose)
    _check_outputs(probes_out, reactions_out, summary, out, plot)
    scenario = _load(scenario_path, spacing, dilation)
    from . import reports
    from .deform import run_deform
    from .progress import progress_bar

    with progress_bar("load steps", scenario.load_steps) as advance:
        result = run_deform(scenario, on_step=lambda step, record: advance())
    reports.write_deform_outputs(result, probes_out=probes_out, reactions_out=reactions_out,
                                 summary=summary, out=out, plot=plot)
    typer.echo(
        f"deform: {result.model.n_particles} particles, {scenario.load_steps} load steps, "
        f"{result.report.iterations} Newton iterations, {result.wall_seconds:.3f} s"
    )


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    app()
