"""`stitchplan calibrate material|needle`: model parameters fitted to measurements."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import calibrate_app
from .options import DilationOption, QuietOption, SpacingOption, VerboseOption, _check_outputs, _setup_logging


@calibrate_app.command("material")
def calibrate_material(
    calibration_path: Path = typer.Argument(..., help="Calibration YAML: tissue, experiments "
                                            "(loads + markers CSV x,y,x_def,y_def), fit ranges."),
    out: Path = typer.Option(..., "--out",
                             help="Fitted YAML: `material:` block, fit quality, diagnostics."),
    plot_dir: Optional[Path] = typer.Option(
        None, "--plot-dir", help="Folder for cost_surface.png and marker_residuals.png."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Fit lame_lambda and lame_mu to marker displacements (grid search, then least squares)."""
    _setup_logging(verbose, quiet)
    _check_outputs(out, None if plot_dir is None else plot_dir / "cost_surface.png")
    from .. import calibration
    from ..io.calibration_reports import material_summary_line, write_material_outputs
    from ..io.progress import progress_bar

    result = calibration.calibrate_material(calibration_path, spacing, dilation, progress=progress_bar)
    write_material_outputs(result, out, plot_dir)
    typer.echo(material_summary_line(result))


@calibrate_app.command("needle")
def calibrate_needle(
    air: Path = typer.Option(..., "--air", help="CSV angle_rad,force_N: needle rotated in air."),
    tissue: Path = typer.Option(..., "--tissue", help="CSV angle_rad,force_N: needle rotated into "
                                "the tissue, angle from the moment the tip touches it."),
    radius: float = typer.Option(..., "--radius", help="Needle radius, mm."),
    out: Path = typer.Option(..., "--out", help="YAML with friction, cutting_force and diagnostics."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the recordings and the fit."),
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Fit needle friction (N/mm) and cutting force (N) to force recordings in air and tissue."""
    _setup_logging(verbose, quiet)
    _check_outputs(out, plot)
    from .. import calibration
    from ..io.calibration_reports import needle_summary_line, write_needle_outputs

    result = calibration.calibrate_needle(air, tissue, radius)
    write_needle_outputs(result, out, plot)
    typer.echo(needle_summary_line(result))
