"""`stitchplan calibrate material|needle`: model parameters fitted to measurements."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..allocator import resume_collection
from .group import calibrate_app
from .options import (CalibrationDilationOption, CalibrationNoResourceCheckOption, CalibrationSpacingOption,
                      MaterialFitVerboseOption, MaxParticlesOption, NeedleFitVerboseOption, QuietOption,
                      check_command_outputs, command_line_argv, guard_calibration, guard_limits, named_file,
                      naming_files, option_names, recording_rows, setup_logging)


@calibrate_app.command("material", short_help="Fit lame_lambda and lame_mu to marker displacements.")
def calibrate_material(
    calibration_path: Path = typer.Argument(..., metavar="CALIBRATION", callback=named_file,
                                            help="Calibration YAML: tissue, experiments "
                                            "(loads + markers CSV x,y,x_def,y_def), fit ranges."),
    out: Path = typer.Option(..., "--out",
                             help="Fitted YAML: `material:` block, fit quality, diagnostics."),
    plot_dir: Optional[Path] = typer.Option(
        None, "--plot-dir", help="Folder for cost_surface.png and marker_residuals.png."),
    spacing: Optional[float] = CalibrationSpacingOption,
    dilation: Optional[float] = CalibrationDilationOption,
    estimate: bool = typer.Option(
        True, "--estimate/--no-estimate",
        help="Estimate the moduli's discretization error: the fit again at twice the spacing, from the fitted moduli."),
    max_particles: Optional[int] = MaxParticlesOption,
    no_resource_check: bool = CalibrationNoResourceCheckOption,
    verbose: int = MaterialFitVerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Fit lame_lambda and lame_mu to marker displacements (grid search, then least squares)."""
    setup_logging(verbose, quiet)
    from .. import calibration
    from ..io.calibration_reports import material_outputs, material_summary_line, write_material_outputs
    from ..io.progress import progress_bar

    resume_collection()
    outputs = material_outputs(out, plot_dir)
    check_command_outputs(outputs, {"CALIBRATION": calibration_path})  # --out's format once the markers are known
    problem = calibration.load_material_calibration(calibration_path, spacing, dilation)
    import scipy.optimize  # noqa: F401 -- the fit's; mapped before the guard measures the address space left
    guard_calibration(calibration_path, problem, guard_limits(max_particles, no_resource_check),
                      names=option_names(spacing, dilation), estimate=estimate)
    check_command_outputs(outputs, {f"markers of experiments[{k}]": experiment.source
                                    for k, experiment in enumerate(problem.experiments)},
                          out_format="YAML")
    with naming_files(calibration_path):  # a model the fit builds (a singular moment matrix) names the file
        result = calibration.fit_material(problem, progress=progress_bar, estimate=estimate)
    write_material_outputs(result, out, plot_dir, command=command_line_argv())
    typer.echo(material_summary_line(result))


@calibrate_app.command("needle", short_help="Fit friction and cutting force to force recordings.")
def calibrate_needle(
    air: Path = typer.Option(..., "--air", callback=named_file,
                             help="CSV angle_rad,force_N: needle rotated in air."),
    tissue: Path = typer.Option(..., "--tissue", callback=named_file,
                                help="CSV angle_rad,force_N: needle rotated into "
                                "the tissue, angle from the moment the tip touches it."),
    # the bounds are config.blocks' NEEDLE_RADIUS_RANGE_MM, a scenario's (not imported: pydantic
    # and numpy would slow --help down)
    radius: float = typer.Option(..., "--radius", help="Needle radius, mm (0.05 to 1000)."),
    out: Path = typer.Option(..., "--out", help="YAML with friction, cutting_force and diagnostics."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the recordings and the fit."),
    no_resource_check: bool = typer.Option(
        False, "--no-resource-check", help="Read recordings of more rows than the memory available holds."),
    verbose: int = NeedleFitVerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Fit needle friction (N/mm) and cutting force (N) to force recordings in air and tissue."""
    setup_logging(verbose, quiet)
    check_command_outputs({"--out": out, "--plot": plot}, {"--air": air, "--tissue": tissue},
                          out_format="YAML")
    _check_two_recordings(air, tissue)
    from .. import calibration
    from ..io.calibration_reports import needle_summary_line, write_needle_outputs

    resume_collection()
    max_rows, rows_note = recording_rows(guard_limits(None, no_resource_check), plot is not None)
    result = calibration.calibrate_needle(air, tissue, radius, max_rows, rows_note)
    write_needle_outputs(result, out, plot, command=command_line_argv())
    typer.echo(needle_summary_line(result))


def _check_two_recordings(air: Path, tissue: Path) -> None:
    """--air and --tissue must be two recordings: the fit subtracts the one in air from the
    one in tissue, and a file given twice (or through a link) leaves nothing to fit."""
    from ..errors import InputError
    from ..io.files import same_file  # as outputs are compared with inputs (symbolic and hard links)

    if same_file(air, tissue):
        raise InputError(f"--tissue: got {tissue}, the same file as --air ({air}); expected the recording in "
                         "tissue, a file other than the one in air")
