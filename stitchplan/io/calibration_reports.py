"""Reports, plots and summary lines of `stitchplan calibrate`: fitted.yaml and its plots for
the Lamé moduli, needle.yaml and its plot for friction and cutting force."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import __version__, source_sha256
from .files import OutputSet, sha256, utc_now, working_directory, write_yaml

if TYPE_CHECKING:
    from ..calibration import MaterialFit, NeedleFit

MATERIAL_HEADER = ("# stitchplan calibrate material: Lame moduli fitted to marker displacements\n"
                   "# (thesis eq. A.3). Paste the `material:` block into a scenario's `tissue:` block.\n")
REGIONS_HEADER = ("# The moduli are the tissue's own around `regions:`, kept at the materials the\n"
                  "# calibration file gave them: paste both into the scenario's `tissue:` block.\n")
FITTED_REGIONS_HEADER = ("# The moduli are the tissue's own around `regions:`; those fit.fitted_regions lists\n"
                         "# were fitted too (`regions:` holds their fitted moduli), the others kept at the\n"
                         "# materials the calibration file gave them: paste both into the scenario's\n"
                         "# `tissue:` block.\n")
# a fit that did not identify the moduli still writes its best point (and lambda/mu), but a
# `material:` block pasted from it can be far off: the file says so before its first key
NOT_IDENTIFIED_HEADER = ("# NOT IDENTIFIED (fit.identifiable: false): the markers do not determine these moduli\n"
                         "# (see fit.warnings); do not paste them into a scenario as a calibration.\n")
NEEDLE_HEADER = ("# stitchplan calibrate needle: friction (N/mm) and cutting force (N) from force\n"
                 "# recordings (thesis section 5.2). Paste both into a scenario's `needle:` block.\n")
MATERIAL_PLOTS = ("cost_surface.png", "marker_residuals.png")  # written into --plot-dir


def _round(value: float | None, digits: int = 6) -> float | None:
    return None if value is None or not math.isfinite(value) else float(f"{value:.{digits}g}")


def _created() -> str:
    return utc_now()


def _inputs(paths: list[str], read: list[str | None] | None = None) -> dict:
    """{path: SHA-256} of the files a fit read: of the bytes read where `read` gives them (a
    file edited or removed during the fit is recorded as the fit read it), else of the file
    as it is when the report is made."""
    digests = {}
    for path, digest in zip(paths, read or [None] * len(paths)):
        if digest is not None:
            digests[path] = digest
            continue
        try:
            digests[path] = sha256(path)
        except OSError:
            digests[path] = None
    return digests


def _spread(values: np.ndarray) -> float:
    """Sample standard deviation, 0 for a single value."""
    return float(values.std(ddof=1)) if len(values) > 1 else 0.0


# --- material -------------------------------------------------------------------------


def material_report(result: MaterialFit, command: list[str] | None = None) -> dict:
    """fitted.yaml: `material:` pastes into a scenario's tissue block; `fit:` says how well
    the moduli are determined; `diagnostics:` how the fit ran."""
    distances = result.distances
    return {
        "material": {
            "model": result.problem.fit.model,
            "lame_lambda": _round(result.lame_lambda),
            "lame_mu": _round(result.lame_mu),
        },
        # the same figures at the top level, as the output format names them
        "lame_lambda": _round(result.lame_lambda),
        "lame_mu": _round(result.lame_mu),
        "residual_mean_mm": _round(float(distances.mean())),
        "residual_std_mm": _round(_spread(distances)),
        # the regions the moduli were fitted around (a scenario's tissue.regions, as given),
        # those whose moduli were fitted too at their fitted moduli
        "regions": _regions(result),
        "fit": _material_quality(result),
        "diagnostics": {**_material_diagnostics(result), "command": command, "working_directory": working_directory(),
                        "input_sha256": _inputs([result.problem.source]
                                                + [e.source for e in result.problem.experiments],
                                                [result.problem.source_sha256]
                                                + [e.source_sha256 for e in result.problem.experiments])},
    }


def _regions(result: MaterialFit) -> list[dict]:
    """The tissue's regions as a scenario takes them, those of fit.regions at their fitted
    moduli (rounded as the other moduli of the file)."""
    blocks = [region.as_block() for region in result.fitted_tissue.regions]
    for index in result.problem.fit.regions:
        material = blocks[index]["material"]
        material.update(lame_lambda=_round(material["lame_lambda"]), lame_mu=_round(material["lame_mu"]))
    return blocks


def _regions_header(result: MaterialFit) -> str:
    if result.fitted_regions:
        return FITTED_REGIONS_HEADER
    return REGIONS_HEADER if result.problem.tissue.regions else ""


def _fitted_regions(result: MaterialFit) -> dict:
    """fit.fitted_regions and the correlations of every fitted modulus, where fit.regions
    named any (the tissue's own pair alone keeps its `correlation`)."""
    if not result.fitted_regions:
        return {}
    names = result.problem.fit.parameter_names
    correlations = result.correlations if result.identifiable else None
    return {
        "fitted_regions": [{"region": index, "lame_lambda": _round(lame_lambda), "lame_mu": _round(lame_mu),
                            "standard_uncertainty": {"lame_lambda": _round(u_lambda, 3), "lame_mu": _round(u_mu, 3)}}
                           for index, lame_lambda, lame_mu, u_lambda, u_mu in result.fitted_regions],
        "correlations": {"parameters": list(names),
                         "matrix": None if correlations is None else
                         [[_round(float(v), 4) for v in row] for row in correlations]},
    }


def _discretization_estimate(result: MaterialFit) -> dict | None:
    """How far each fitted modulus moves when fitted at twice the spacing (None: not asked
    for, --no-estimate)."""
    estimate = result.estimate
    if estimate is None:
        return None
    names = result.problem.fit.parameter_names
    block = {"spacing_mm": estimate.spacing, "failure": estimate.failure, "moduli": None, "change": None,
             "change_over_standard_uncertainty": None}
    if estimate.change is not None:
        block["moduli"] = {name: _round(float(v)) for name, v in zip(names, estimate.moduli)}
        block["change"] = {name: _round(float(v), 3) for name, v in zip(names, estimate.change)}
        block["change_over_standard_uncertainty"] = {
            name: None if sigma is None else _round(float(change / sigma), 3)
            for name, change, sigma in zip(names, estimate.change, result.parameter_uncertainty)}
    return block


def _material_quality(result: MaterialFit) -> dict:
    distances = result.distances
    per_experiment = []
    for k, (experiment, residual) in enumerate(zip(result.problem.experiments, result.residuals)):
        e = np.linalg.norm(residual, axis=1)
        per_experiment.append({
            "name": experiment.name or f"experiments[{k}]",
            "markers": len(e),
            "residual_mean_mm": _round(float(e.mean())),
            "residual_std_mm": _round(_spread(e)),
            "residual_max_mm": _round(float(e.max())),
        })
    return {
        "residual_mean_mm": _round(float(distances.mean())),
        "residual_std_mm": _round(_spread(distances)),
        "residual_max_mm": _round(float(distances.max())),
        "residual_rms_mm": _round(math.sqrt(result.cost / len(distances))),
        "cost_mm2": _round(result.cost),
        "standard_uncertainty": {
            "lame_lambda": _round(result.standard_uncertainty[0], 3),
            "lame_mu": _round(result.standard_uncertainty[1], 3),
        },
        "correlation": _round(result.correlation, 4),
        "lambda_over_mu": _round(result.lambda_over_mu),
        "lambda_over_mu_uncertainty": _round(result.lambda_over_mu_uncertainty, 3),
        "identifiable": result.identifiable,
        **_fitted_regions(result),
        "discretization_estimate": _discretization_estimate(result),
        "warnings": list(result.warnings),
        "markers": len(distances),
        "experiments": per_experiment,
    }


def _material_diagnostics(result: MaterialFit) -> dict:
    problem, grid, d = result.problem, result.grid, result.problem.discretization
    return {
        "forward_solves": result.forward_solves,
        "grid_forward_solves": result.grid_solves,
        "refinement_forward_solves": result.forward_solves - result.grid_solves,
        "estimate_forward_solves": None if result.estimate is None else result.estimate.forward_solves,
        "cold_starts": result.cold_starts,
        "newton_iterations": result.newton_iterations,
        "wall_seconds": round(result.wall_seconds, 3),
        "search_range": {"lame_lambda": list(problem.fit.lame_lambda),
                         "lame_mu": list(problem.fit.lame_mu)},
        "grid": {
            "points_per_axis": problem.fit.grid_points,
            "scale": problem.fit.grid_scale,
            "best": {"lame_lambda": _round(grid.best[0]), "lame_mu": _round(grid.best[1]),
                     "cost_mm2": _round(float(np.nanmin(grid.cost)))},
            "failed_points": grid.failed,
        },
        "least_squares": {**result.optimizer,
                          "start": [_round(v) for v in (*grid.best, *result.problem.region_start)]},
        # the sparse factorizations of the forward solves and sensitivities, as deform's `solver` gives them
        "linear_solver_backends": result.linear_solver_backends,
        "discretization": {"particles": sum(result.particles), "experiment_particles": result.particles,
                           "spacing_mm": d.spacing,
                           "dilation": d.dilation, "quadrature_order": d.quadrature_order,
                           "basis_order": d.basis_order},
        "source": problem.source,
        "stitchplan_version": __version__,
        "stitchplan_source_sha256": source_sha256(),
        "created_utc": _created(),
    }


def _material_plots_to(result: MaterialFit, cost_path: Path, residuals_path: Path) -> None:
    from .calibration_plots import plot_cost_surface, plot_marker_residuals

    grid, problem = result.grid, result.problem
    plot_cost_surface(cost_path, grid.lame_lambda, grid.lame_mu, grid.cost, grid.best,
                      (result.lame_lambda, result.lame_mu), result.path,
                      log_axes=problem.fit.grid_scale == "log", name=problem.name,
                      residual=(float(result.distances.mean()), _spread(result.distances)),
                      uncertainty=result.standard_uncertainty, identifiable=result.identifiable,
                      note=_fitted_regions_note(result))
    plot_marker_residuals(residuals_path, result.fitted_tissue, problem.experiments, result.simulated,
                          name=problem.name)


def _fitted_regions_note(result: MaterialFit) -> str:
    """The cost surface's line on regions fitted too: the grid holds them at their start."""
    return "; ".join(f"regions[{index}] fitted too: lambda {lame_lambda:.4g}, mu {lame_mu:.4g} MPa "
                     f"(on the grid at its start)" for index, lame_lambda, lame_mu, *_ in result.fitted_regions)


def material_outputs(out: str | Path, plot_dir: str | Path | None = None) -> dict[str, Path | None]:
    """The files `calibrate material` writes, by label."""
    plots = {} if plot_dir is None else {f"--plot-dir's {name}": Path(plot_dir) / name
                                         for name in MATERIAL_PLOTS}
    return {"--out": Path(out), **plots}


def write_material_outputs(result: MaterialFit, out: str | Path,
                           plot_dir: str | Path | None = None, command: list[str] | None = None) -> None:
    """fitted.yaml and the plots: all of them or none (an OutputSet)."""
    outputs = material_outputs(out, plot_dir)
    with OutputSet(outputs).staged() as files:
        if plot_dir is not None:
            _material_plots_to(result, *(files[label] for label in list(outputs)[1:]))
        write_yaml(files["--out"], material_report(result, command),
                   MATERIAL_HEADER + _regions_header(result) + ("" if result.identifiable else NOT_IDENTIFIED_HEADER))


def _plus_minus(value: float | None) -> str:
    return f" +- {value:.2g}" if value is not None else ""


def material_summary_line(result: MaterialFit) -> str:
    spread = [_plus_minus(value) for value in result.standard_uncertainty]
    flag = "" if result.identifiable else " (NOT identifiable: see warnings)"
    regions = "".join(
        f"; tissue.regions[{index}]: lame_lambda {lame_lambda:.6g}{_plus_minus(u_lambda)} MPa, "
        f"lame_mu {lame_mu:.6g}{_plus_minus(u_mu)} MPa"
        for index, lame_lambda, lame_mu, u_lambda, u_mu in result.fitted_regions)
    return (f"calibrate material: lame_lambda {result.lame_lambda:.6g}{spread[0]} MPa, lame_mu "
            f"{result.lame_mu:.6g}{spread[1]} MPa{regions}{flag}; marker residual "
            f"{result.distances.mean():.4g} +- {_spread(result.distances):.2g} mm{_estimate_line(result)}; "
            f"{result.forward_solves} forward solves, {result.wall_seconds:.2f} s")


def _estimate_line(result: MaterialFit) -> str:
    """At twice the spacing the moduli move by at most ... of their standard uncertainty."""
    estimate = result.estimate
    if estimate is None or not result.identifiable:  # moduli not determined: their change says nothing
        return ""
    if estimate.change is None:
        return f"; no discretization estimate (the fit at {estimate.spacing:g} mm failed)"
    shares = [change / sigma for change, sigma in zip(estimate.change, result.parameter_uncertainty)]
    return (f"; fitted at twice the spacing ({estimate.spacing:g} mm) the moduli move by at most "
            f"{max(shares):.2g} of their standard uncertainty")


# --- needle ---------------------------------------------------------------------------


def needle_report(result: NeedleFit, command: list[str] | None = None) -> dict:
    """needle.yaml: `friction` and `cutting_force` paste into a scenario's needle block."""
    fit, background = result.tissue_fit, result.background
    return {
        "friction": _round(result.friction),
        "cutting_force": _round(result.cutting_force),
        "diagnostics": {
            "radius_mm": result.radius,
            "standard_uncertainty": {"friction": _round(result.standard_uncertainty[0], 3),
                                     "cutting_force": _round(result.standard_uncertainty[1], 3)},
            "r_squared": _round(fit.r_squared),
            "residual_std_N": _round(fit.residual_std, 4),
            "samples": {"air": len(result.air), "tissue": len(result.tissue)},
            "inserted_length_mm": [_round(float(result.inserted_length.min())),
                                   _round(float(result.inserted_length.max()))],
            "background": {"offset_N": _round(background.intercept),
                           "slope_N_per_rad": _round(background.slope),
                           "residual_std_N": _round(background.residual_std, 4),
                           "angle_range_rad": [_round(float(result.air[0, 0])),
                                               _round(float(result.air[-1, 0]))]},
            "warnings": list(result.warnings),
            "air": result.sources[0],
            "tissue": result.sources[1],
            "stitchplan_version": __version__,
            "stitchplan_source_sha256": source_sha256(),
            "command": command,
            "working_directory": working_directory(),
            "input_sha256": _inputs(list(result.sources), list(result.source_sha256)),
            "created_utc": _created(),
        },
    }


def write_needle_outputs(result: NeedleFit, out: str | Path, plot: str | Path | None = None,
                         command: list[str] | None = None) -> None:
    """needle.yaml and the plot: both or neither (an OutputSet)."""
    with OutputSet({"--out": out, "--plot": plot}).staged() as files:
        _write_needle_files(result, files["--out"], files.get("--plot"), command)


def _write_needle_files(result: NeedleFit, out: Path, plot: Path | None, command: list[str] | None) -> None:
    if plot is not None:
        from .calibration_plots import plot_needle_forces

        plot_needle_forces(plot, result)
    write_yaml(out, needle_report(result, command), NEEDLE_HEADER)


def needle_summary_line(result: NeedleFit) -> str:
    u = result.standard_uncertainty
    return (f"calibrate needle: friction {result.friction:.6g} +- {u[0]:.2g} N/mm, cutting_force "
            f"{result.cutting_force:.6g} +- {u[1]:.2g} N (R^2 {result.tissue_fit.r_squared:.4f})")
