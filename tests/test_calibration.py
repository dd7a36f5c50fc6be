"""Calibration: the forward model and its exact Jacobian, round trips of known parameters
through synthetic data, the identifiability warning, and the CLI on good and bad files.

Synthetic markers come from the calibration's own forward model at the fit's
discretization (coarse, 10 mm, for speed), so a noise-free round trip must return the
parameters to solver tolerance, and a noisy one tests the statistics, not the discretization.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import TypeAdapter
from typer.testing import CliRunner

from stitchplan import calibration
from stitchplan.cli import app
from stitchplan.config.blocks import Region
from stitchplan.config.scenario import (
    Discretization,
    Load,
    Material,
    Scenario,
    Solver,
    Tissue,
    parse_material,
    parse_needle,
)

TRUE = Material("saint-venant-kirchhoff", 0.189151, 0.147688)
THETA = np.array([TRUE.lame_lambda, TRUE.lame_mu])
TISSUE = Tissue((100.0, 60.0), 10.0, TRUE, ("right",))
COARSE = Discretization(spacing=10.0)
LOADS = {  # force-controlled experiments on the 100 x 60 mm block clamped on the right
    "left-pull": (Load(((0.0, 24.0), (0.0, 36.0)), force=(2.0, 1.0)),),
    "top-press": (Load(((0.0, 60.0), (100.0, 60.0)), force=(0.0, -4.0)),),
    "left-shear": (Load(((0.0, 0.0), (0.0, 60.0)), force=(0.0, 2.0)),),
    "left-stretch": (Load(((0.0, 0.0), (0.0, 60.0)), force=(-4.0, 0.0)),),
}
DISPLACED = (Load(((0.0, 20.0), (0.0, 40.0)), displacement=(-4.0, 2.0)),)
# a stiff inclusion of known material between the loaded edge and the clamp
STIFF_DISC = {"circle": {"center": [45.0, 30.0], "radius": 14.0},
              "material": {"model": "neo-hookean", "lame_lambda": 0.8, "lame_mu": 0.6}}
REGION_ADAPTER = TypeAdapter(Region)
FIT = {"lame_lambda": [0.01, 2.0], "lame_mu": [0.01, 2.0], "grid": 4}


def random_markers(rng: np.random.Generator, count: int) -> np.ndarray:
    return np.column_stack([rng.uniform(0.0, 100.0, count), rng.uniform(0.0, 60.0, count)])


def load_block(loads: tuple[Load, ...], scale: float = 1.0) -> list[dict]:
    block = []
    for load in loads:
        item = {"segment": [list(p) for p in load.segment]}
        if load.force is not None:
            item["force"] = [scale * f for f in load.force]
        else:
            item["displacement"] = list(load.displacement)
        block.append(item)
    return block


def write_calibration(folder, experiments, fit=None, rng=None, noise=0.0, markers=20, scale=1.0,
                      extra=None, regions=None):
    """Markers from the forward model at TRUE (+ noise) and the calibration YAML; returns its path.
    `regions`: the tissue's regions as the file gives them (their markers simulated with them).
    The markers are the fit's own 10 mm model's, so a fit returns TRUE exactly: the round trips
    skip the discretization estimate, which rightly finds that model far from converged."""
    rng = rng or np.random.default_rng(0)
    tissue = TISSUE if regions is None else replace(TISSUE, regions=tuple(REGION_ADAPTER.validate_python(r)
                                                                          for r in regions))
    entries = []
    for k, loads in enumerate(experiments):
        scaled = tuple(Load(l.segment, None if l.force is None else tuple(scale * f for f in l.force),
                            l.displacement) for l in loads)
        rest = random_markers(rng, markers)
        deformed = calibration.simulate_markers(tissue, COARSE, scaled, rest, TRUE)
        deformed += noise * rng.standard_normal(deformed.shape)
        name = f"markers{k}.csv"
        rows = "\n".join(",".join(f"{v:.12g}" for v in row) for row in np.hstack([rest, deformed]))
        (folder / name).write_text("x,y,x_def,y_def\n" + rows + "\n")
        entries.append({"loads": load_block(loads, scale), "markers": name})
    data = {
        "tissue": {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"],
                   **({"regions": regions} if regions else {})},
        "experiments": entries,
        "fit": fit or dict(FIT),
        "discretization": {"spacing": 10.0},
        **(extra or {}),
    }
    path = folder / "calib.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


# --- forward model ----------------------------------------------------------------------


def test_forward_model_is_the_deform_solve_at_the_markers():
    """simulate_markers = X + u(X) of `stitchplan deform` (probes = markers, deform.interpolate)."""
    from stitchplan.tissue.deform import run_deform

    markers = random_markers(np.random.default_rng(1), 12)
    loads = LOADS["left-pull"]
    scenario = Scenario(tissue=TISSUE, discretization=COARSE, loads=loads,
                        probes=tuple(map(tuple, markers)))
    reference = run_deform(scenario)
    positions = calibration.simulate_markers(TISSUE, COARSE, loads, markers, TRUE)
    np.testing.assert_allclose(positions - markers, reference.probe_displacements, rtol=0, atol=1e-9)


@pytest.mark.parametrize("model, regions", [("saint-venant-kirchhoff", None), ("neo-hookean", None),
                                            ("saint-venant-kirchhoff", "given"), ("neo-hookean", "fitted")])
def test_marker_jacobian_matches_finite_differences(model, regions):
    """dq/dtheta from K dd/dtheta = -B^T (w F S_theta) against central differences of solves;
    with a region of given material the fitted moduli act only outside it (S_theta zero there);
    with the region's moduli fitted too, theta holds its pair and each acts only inside it."""
    tissue = replace(TISSUE, regions=(REGION_ADAPTER.validate_python(STIFF_DISC),)) if regions else TISSUE
    markers = random_markers(np.random.default_rng(2), 10)
    loads = LOADS["left-pull"] + (Load(((0.0, 50.0), (0.0, 60.0)), displacement=(-1.0, 0.5)),)
    experiment = calibration.Experiment("", loads, 10, markers, markers)
    fitted = (0,) if regions == "fitted" else ()
    forward = calibration.ExperimentModel(tissue, COARSE, experiment, model, Solver(), fitted_regions=fitted)
    theta = np.array([*THETA, 0.8, 0.6]) if fitted else THETA
    _, jacobian = forward.predict(theta, jacobian=True)
    assert jacobian.shape == (len(markers), 2, len(theta))
    assert np.abs(jacobian).max() > 1.0  # mm per MPa: the markers do move with the moduli
    for k in range(len(theta)):
        step = np.zeros(len(theta))
        step[k] = 1e-5 * theta[k]
        plus, _ = forward.predict(theta + step)
        minus, _ = forward.predict(theta - step)
        np.testing.assert_allclose(jacobian[:, :, k], (plus - minus) / (2 * step[k]),
                                   rtol=1e-4, atol=1e-6 * np.abs(jacobian).max())


def test_displacement_control_sees_only_the_ratio():
    """Scaling both moduli moves no marker when every load is a prescribed displacement,
    but does under a force: the reason for the identifiability warning."""
    markers = random_markers(np.random.default_rng(3), 8)
    for loads, moves in ((DISPLACED, False), (LOADS["left-pull"], True)):
        a = calibration.simulate_markers(TISSUE, COARSE, loads, markers, TRUE)
        b = calibration.simulate_markers(TISSUE, COARSE, loads, markers,
                                         Material(TRUE.model, 2 * TRUE.lame_lambda, 2 * TRUE.lame_mu))
        assert (np.abs(a - b).max() > 0.1) == moves


def test_a_region_of_given_material_makes_displacements_show_the_moduli():
    """Against a region that keeps its moduli, scaling the tissue's own moves the markers
    under a prescribed displacement too (the scaling of a one-material tissue is broken)."""
    tissue = replace(TISSUE, regions=(REGION_ADAPTER.validate_python(STIFF_DISC),))
    markers = random_markers(np.random.default_rng(3), 8)
    doubled = Material(TRUE.model, 2 * TRUE.lame_lambda, 2 * TRUE.lame_mu)
    a = calibration.simulate_markers(tissue, COARSE, DISPLACED, markers, TRUE)
    b = calibration.simulate_markers(tissue, COARSE, DISPLACED, markers, doubled)
    assert np.abs(a - b).max() > 0.1


# --- material round trips ---------------------------------------------------------------


def test_round_trip_noise_free_through_the_cli(tmp_path):
    path = write_calibration(tmp_path, [LOADS["left-pull"], LOADS["top-press"]])
    out, plots = tmp_path / "fitted.yaml", tmp_path / "plots"
    result = run("calibrate", "material", path, "--out", out, "--plot-dir", plots, "--no-estimate")
    assert result.exit_code == 0, result.output
    fitted = yaml.safe_load(out.read_text())
    material = parse_material(fitted["material"])  # pastes into a scenario as it is
    assert material.lame_lambda == pytest.approx(TRUE.lame_lambda, rel=1e-3)
    assert material.lame_mu == pytest.approx(TRUE.lame_mu, rel=1e-3)
    assert fitted["fit"]["residual_mean_mm"] < 1e-5
    assert fitted["fit"]["identifiable"] is True and fitted["fit"]["warnings"] == []
    assert fitted["fit"]["markers"] == 40
    diagnostics = fitted["diagnostics"]
    assert diagnostics["forward_solves"] == (diagnostics["grid_forward_solves"]
                                             + diagnostics["refinement_forward_solves"])
    assert 0 < diagnostics["grid_forward_solves"] <= 2 * 4 * 4  # 2 experiments, 4 x 4 grid
    assert diagnostics["wall_seconds"] > 0
    # what ran, as deform's summary says it: the factorizations and each experiment's model
    from stitchplan.tissue.factorization import SUPERLU
    assert SUPERLU in diagnostics["linear_solver_backends"]  # the sensitivities' LU
    particles = diagnostics["discretization"]["experiment_particles"]
    assert len(particles) == 2 and diagnostics["discretization"]["particles"] == sum(particles)
    for name in ("cost_surface.png", "marker_residuals.png"):
        assert (plots / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_round_trip_with_noise(tmp_path):
    """0.05 mm noise: 4 force experiments x 400 markers make the standard uncertainty of
    lambda (the weakly determined modulus, volumetric) about 0.5 %, so the 2 % bound is
    ~4 sigma and a pass is not luck; the reported uncertainty must explain the error."""
    rng = np.random.default_rng(20240611)
    path = write_calibration(tmp_path, list(LOADS.values()), rng=rng, noise=0.05, markers=400,
                             scale=2.0)
    problem = calibration.load_material_calibration(path)
    result = calibration.fit_material(problem, estimate=False)  # the data are the 10 mm model's
    errors = np.array([result.lame_lambda, result.lame_mu]) / THETA - 1.0
    sigma = np.array(result.standard_uncertainty) / THETA
    assert np.all(np.abs(errors) < 0.02), errors
    assert np.all(sigma < 0.006), sigma
    assert np.all(np.abs(errors) < 4 * sigma), (errors, sigma)
    # |p - q| of 2D Gaussian noise is Rayleigh distributed: mean 0.05 sqrt(pi/2) mm
    assert result.distances.mean() == pytest.approx(0.05 * math.sqrt(math.pi / 2), rel=0.05)
    assert result.identifiable and not result.warnings


def test_identifiability_warning_on_displacement_only_data(tmp_path, caplog):
    rng = np.random.default_rng(5)
    path = write_calibration(tmp_path, [DISPLACED], rng=rng, noise=0.05)
    out = tmp_path / "fitted.yaml"
    with caplog.at_level(logging.WARNING, logger="stitchplan.calibration"):
        result = run("calibrate", "material", path, "--out", out)
    assert result.exit_code == 0, result.output
    assert "NOT identifiable" in result.output
    assert "cannot separate lame_lambda and lame_mu" in caplog.text  # logged warning
    fit = yaml.safe_load(out.read_text())["fit"]
    assert fit["identifiable"] is False
    assert "# NOT IDENTIFIED (fit.identifiable: false)" in out.read_text().split("\nmaterial:")[0]
    assert fit["correlation"] == pytest.approx(1.0, abs=1e-3)
    assert any("cannot separate" in w for w in fit["warnings"])
    assert fit["standard_uncertainty"] == {"lame_lambda": None, "lame_mu": None}
    # the ratio is still determined, within its reported uncertainty
    ratio = TRUE.lame_lambda / TRUE.lame_mu
    assert abs(fit["lambda_over_mu"] - ratio) < 4 * fit["lambda_over_mu_uncertainty"]


def test_no_identifiability_warning_on_force_data(tmp_path):
    path = write_calibration(tmp_path, [LOADS["left-pull"], LOADS["top-press"]],
                             rng=np.random.default_rng(6), noise=0.05)
    result = calibration.fit_material(calibration.load_material_calibration(path))
    assert result.identifiable
    assert abs(result.correlation) < calibration.CORRELATION_LIMIT
    assert not any("cannot separate" in w for w in result.warnings)


def test_round_trip_with_a_region_of_given_material_through_the_cli(tmp_path):
    """The fit finds the tissue's own moduli around a region it keeps as given, from force
    data and from displacement data alone (identified there too: the region breaks the
    scaling); a fit that leaves the region out misses them."""
    from stitchplan.config.uncertainty import calibration_spread

    for experiments in ([DISPLACED], [LOADS["left-pull"], LOADS["top-press"]]):
        path = write_calibration(tmp_path, experiments, regions=[STIFF_DISC])
        out = tmp_path / "fitted.yaml"
        result = run("calibrate", "material", path, "--out", out, "--no-estimate")
        assert result.exit_code == 0, result.output
        fitted = yaml.safe_load(out.read_text())
        assert fitted["lame_lambda"] == pytest.approx(TRUE.lame_lambda, rel=1e-3)
        assert fitted["lame_mu"] == pytest.approx(TRUE.lame_mu, rel=1e-3)
        assert fitted["fit"]["residual_mean_mm"] < 1e-5
        assert fitted["fit"]["identifiable"] is True and fitted["fit"]["warnings"] == []
        # the regions it kept, as a scenario's tissue takes them, read back by an uncertainty file
        assert fitted["regions"] == [STIFF_DISC]
        assert out.read_text().count("paste both into the scenario's `tissue:` block") == 1
        assert calibration_spread(out, tmp_path / "u.yaml")[2] == (REGION_ADAPTER.validate_python(STIFF_DISC),)
    data = yaml.safe_load(path.read_text())  # the force experiments' file
    del data["tissue"]["regions"]
    path.write_text(yaml.safe_dump(data))
    blind = calibration.fit_material(calibration.load_material_calibration(path))
    assert blind.distances.mean() > 0.01  # mm: the markers are not explained (fitted: < 1e-5)
    assert abs(blind.lame_mu / TRUE.lame_mu - 1.0) > 0.03


def test_round_trip_fitting_a_region_too_through_the_cli(tmp_path):
    """fit.regions fits the disc's moduli with the tissue's from a start far off (0.3 MPa
    each against 0.8 and 0.6): all four come back from two force experiments; fitted.yaml's
    regions hold the fitted moduli (pasted into a scenario as they are) and fit.fitted_regions
    and fit.correlations their uncertainties, which an uncertainty file takes."""
    from stitchplan.config.uncertainty import calibration_spread

    path = write_calibration(tmp_path, [LOADS["left-pull"], LOADS["top-press"]], regions=[STIFF_DISC])
    data = yaml.safe_load(path.read_text())
    data["tissue"]["regions"][0]["material"].update(lame_lambda=0.3, lame_mu=0.3)
    data["fit"]["regions"] = [0]
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--no-estimate")
    assert result.exit_code == 0, result.output
    assert "tissue.regions[0]: lame_lambda 0.8" in result.output
    fitted = yaml.safe_load(out.read_text())
    assert fitted["lame_lambda"] == pytest.approx(TRUE.lame_lambda, rel=1e-3)
    assert fitted["lame_mu"] == pytest.approx(TRUE.lame_mu, rel=1e-3)
    region = REGION_ADAPTER.validate_python(fitted["regions"][0])  # a scenario's region as it is
    assert region.material.lame_lambda == pytest.approx(0.8, rel=1e-3)
    assert region.material.lame_mu == pytest.approx(0.6, rel=1e-3)
    fit = fitted["fit"]
    assert fit["identifiable"] is True and fit["warnings"] == [] and fit["residual_mean_mm"] < 1e-5
    assert [entry["region"] for entry in fit["fitted_regions"]] == [0]
    assert fit["fitted_regions"][0]["lame_mu"] == fitted["regions"][0]["material"]["lame_mu"]
    matrix = np.array(fit["correlations"]["matrix"])
    assert fit["correlations"]["parameters"][2:] == ["tissue.regions[0].lame_lambda", "tissue.regions[0].lame_mu"]
    assert matrix.shape == (4, 4) and np.allclose(matrix, matrix.T) and matrix[0, 1] == fit["correlation"]
    std, pairs, regions, _ = calibration_spread(out, tmp_path / "u.yaml")
    assert set(std) == set(fit["correlations"]["parameters"]) and len(pairs) == 6
    assert std["tissue.regions[0].lame_mu"] == fit["fitted_regions"][0]["standard_uncertainty"]["lame_mu"]
    assert regions == (region,)


def test_fitting_every_region_under_displacements_sees_only_the_ratios(tmp_path):
    """With the disc's moduli fitted too and only a prescribed displacement, scaling all four
    moves no marker again: not identifiable, said so, yet each material's lambda/mu is right."""
    path = write_calibration(tmp_path, [DISPLACED], regions=[STIFF_DISC])
    data = yaml.safe_load(path.read_text())
    data["fit"]["regions"] = [0]
    path.write_text(yaml.safe_dump(data))
    result = calibration.fit_material(calibration.load_material_calibration(path))
    assert not result.identifiable
    assert any("cannot separate" in w and "scaling every modulus" in w for w in result.warnings), result.warnings
    assert result.lame_lambda / result.lame_mu == pytest.approx(TRUE.lame_lambda / TRUE.lame_mu, rel=1e-3)
    (_, lame_lambda, lame_mu, *spread), = result.fitted_regions
    assert lame_lambda / lame_mu == pytest.approx(0.8 / 0.6, rel=1e-3) and spread == [None, None]


# --- discretization estimate ------------------------------------------------------------


def test_the_discretization_estimate_bounds_the_error_against_a_finer_model(tmp_path):
    """Markers made noise-free on a model four times finer (2.5 mm) and fitted at 10 mm: the
    fitted moduli are off by the 10 mm model's discretization error alone, and the estimate
    (the fit again at 20 mm) bounds it within a factor 3 (measured 1.2 and 2.0)."""
    fine = Discretization(spacing=2.5)
    rng = np.random.default_rng(0)
    experiments = []
    for k, loads in enumerate([LOADS["left-pull"], LOADS["top-press"]]):
        rest = random_markers(rng, 20)
        deformed = calibration.simulate_markers(TISSUE, fine, loads, rest, TRUE)
        rows = "\n".join(",".join(f"{v:.12g}" for v in row) for row in np.hstack([rest, deformed]))
        (tmp_path / f"markers{k}.csv").write_text("x,y,x_def,y_def\n" + rows + "\n")
        experiments.append({"loads": load_block(loads), "markers": f"markers{k}.csv"})
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump({"tissue": {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"]},
                                    "experiments": experiments, "fit": dict(FIT), "discretization": {"spacing": 10.0}}))
    result = calibration.fit_material(calibration.load_material_calibration(path))
    error = np.abs(result.parameters - THETA)
    assert result.estimate.spacing == 20.0 and np.all(error > 1e-3)
    assert np.all(result.estimate.change >= error) and np.all(result.estimate.change <= 3.0 * error), \
        (result.estimate.change, error)
    # noise-free markers: any discretization error is large beside the (tiny) standard uncertainty
    assert any("when fitted at twice the spacing (20 mm)" in w for w in result.warnings)


def test_the_estimate_is_written_skipped_with_no_estimate_and_its_failure_said(tmp_path, monkeypatch):
    """fitted.yaml's fit.discretization_estimate holds the moduli at twice the spacing and their
    change; --no-estimate writes null; a fit at twice the spacing that fails is said, not fatal."""
    path = write_calibration(tmp_path, [LOADS["left-pull"], LOADS["top-press"]], noise=0.05)
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert result.exit_code == 0, result.output
    assert "fitted at twice the spacing (20 mm) the moduli move by at most" in result.output
    fitted = yaml.safe_load(out.read_text())
    block = fitted["fit"]["discretization_estimate"]
    assert block["spacing_mm"] == 20.0 and block["failure"] is None
    for name in ("lame_lambda", "lame_mu"):
        assert block["change"][name] == pytest.approx(abs(block["moduli"][name] - fitted[name]), rel=1e-3, abs=2e-6)
        ratio = block["change"][name] / fitted["fit"]["standard_uncertainty"][name]
        assert block["change_over_standard_uncertainty"][name] == pytest.approx(ratio, rel=1e-2)
    assert fitted["diagnostics"]["estimate_forward_solves"] > 0
    result = run("calibrate", "material", path, "--out", out, "--no-estimate")
    assert result.exit_code == 0 and "twice the spacing" not in result.output
    fitted = yaml.safe_load(out.read_text())
    assert fitted["fit"]["discretization_estimate"] is None and fitted["diagnostics"]["estimate_forward_solves"] is None

    def fail(*args, **kwargs):
        raise material_fit.ForwardFailure("experiments[0]", THETA, "det F < 0")

    from stitchplan.calibration import material_fit

    monkeypatch.setattr(material_fit, "refine", _failing_at_twice_the_spacing(material_fit.refine, fail))
    result = run("calibrate", "material", path, "--out", out)
    assert result.exit_code == 0, result.output
    assert "no discretization estimate (the fit at 20 mm failed)" in result.output
    fitted = yaml.safe_load(out.read_text())
    assert fitted["fit"]["discretization_estimate"]["failure"] == "experiments[0] at lame_lambda 0.1892, lame_mu " \
                                                                   "0.1477 MPa: det F < 0"
    assert any(w.startswith("no discretization estimate: the fit at twice the spacing (20 mm) failed")
               for w in fitted["fit"]["warnings"])


def _failing_at_twice_the_spacing(refine, fail):
    """`refine` as it is, but for the estimate's fit (a coarser discretization than 10 mm)."""
    def refine_or_fail(misfit, problem, *args):
        if problem.discretization.spacing > 10.0:
            fail()
        return refine(misfit, problem, *args)

    return refine_or_fail


# --- needle -----------------------------------------------------------------------------

RADIUS = 8.88
FRICTION, CUTTING = 0.0602, 0.7
BACKGROUND = (0.12, 0.035)


def write_recordings(folder, noise=(0.0, 0.0), seed=0, samples=(200, 180)):
    """Air on one angle grid, tissue on another (the background is evaluated at the tissue's)."""
    rng = np.random.default_rng(seed)
    air_angle = np.linspace(0.0, math.pi, samples[0])
    air = BACKGROUND[0] + BACKGROUND[1] * air_angle + noise[0] * rng.standard_normal(samples[0])
    angle = np.sort(rng.uniform(0.0, 2.8, samples[1]))
    tissue = (BACKGROUND[0] + BACKGROUND[1] * angle + CUTTING + FRICTION * RADIUS * angle
              + noise[1] * rng.standard_normal(samples[1]))
    paths = folder / "air.csv", folder / "tissue.csv"
    for path, a, f in zip(paths, (air_angle, angle), (air, tissue)):
        path.write_text("angle_rad,force_N\n" + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in zip(a, f)))
    return paths


def test_needle_noise_free_is_exact(tmp_path):
    air, tissue = write_recordings(tmp_path)
    result = calibration.calibrate_needle(air, tissue, RADIUS)
    assert result.friction == pytest.approx(FRICTION, rel=1e-10)
    assert result.cutting_force == pytest.approx(CUTTING, rel=1e-10)
    assert result.tissue_fit.r_squared == pytest.approx(1.0)


def test_a_tissue_recording_that_starts_after_the_touch_is_warned_about(tmp_path):
    """Angles that start 1 rad after the touch (the recording's own zero missed) move the
    cutting force, the line's value at zero inserted length: a warning says how far it was
    extrapolated; a recording from the touch gets none."""
    air, tissue = write_recordings(tmp_path)
    assert not [w for w in calibration.calibrate_needle(air, tissue, RADIUS).warnings if "not at the touch" in w]
    rows = tissue.read_text().splitlines()
    late = tmp_path / "late.csv"
    late.write_text("\n".join([rows[0]] + [f"{float(a) + 1.0!r},{f}" for a, f in (r.split(",") for r in rows[1:])]))
    warnings = calibration.calibrate_needle(air, late, RADIUS).warnings
    first = float(rows[1].split(",")[0]) + 1.0
    assert f"the tissue recording starts at {first:.3g} rad, not at the touch (0 rad): the cutting force is the " \
           f"line extrapolated back over {RADIUS * first:.3g} mm of inserted length" in warnings[0]


def test_needle_round_trip_with_noise_through_the_cli(tmp_path):
    air, tissue = write_recordings(tmp_path, noise=(0.01, 0.02), seed=11)
    out, plot = tmp_path / "needle.yaml", tmp_path / "forces.png"
    result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", RADIUS,
                 "--out", out, "--plot", plot)
    assert result.exit_code == 0, result.output
    data = yaml.safe_load(out.read_text())
    needle = parse_needle({"radius": RADIUS, "entry": [0.0, 30.0], "turn": "cw", "step": 0.08,
                           "friction": data["friction"], "cutting_force": data["cutting_force"]})
    assert needle.friction == pytest.approx(FRICTION, rel=0.02)
    assert needle.cutting_force == pytest.approx(CUTTING, rel=0.02)
    sigma = data["diagnostics"]["standard_uncertainty"]
    assert abs(data["friction"] - FRICTION) < 4 * sigma["friction"]
    assert abs(data["cutting_force"] - CUTTING) < 4 * sigma["cutting_force"]
    assert data["diagnostics"]["r_squared"] > 0.99
    assert data["diagnostics"]["residual_std_N"] == pytest.approx(0.02, rel=0.2)
    assert plot.read_bytes()[:4] == b"\x89PNG"


# --- bad inputs -------------------------------------------------------------------------


def assert_refused(result, out, *fragments):
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]  # no temp left


BAD_RECORDINGS = {
    "wrong columns": ("angle,force\n" + "".join(f"{0.1 * i},{i}\n" for i in range(10)),
                      ["columns: got 'angle,force'", "angle_rad,force_N"]),
    "too short": ("angle_rad,force_N\n" + "".join(f"{0.1 * i},{i}\n" for i in range(4)),
                  ["4 samples", "at least 5"]),
    "not increasing": ("angle_rad,force_N\n0,1\n0.1,1\n0.3,1\n0.2,1\n0.4,1\n0.5,1\n",
                       ["line 5", "strictly increasing"]),
    "non-numeric": ("angle_rad,force_N\n0,1\n0.1,1\n0.2,abc\n0.3,1\n0.4,1\n",
                    ["line 4", "force_N", "'abc'", "finite number"]),
    "short span": ("angle_rad,force_N\n" + "".join(f"{0.01 * i},{i}\n" for i in range(6)),
                   ["span of 0.05 rad", "at least 0.1 rad"]),
    "degrees": ("angle_rad,force_N\n" + "".join(f"{18 * i},{0.1 * i}\n" for i in range(11)),
                ["span of 180 rad", "at most 6.283 rad", "degrees?"]),
}


@pytest.mark.parametrize("problem", sorted(BAD_RECORDINGS))
def test_needle_refuses_bad_recordings(tmp_path, problem):
    text, fragments = BAD_RECORDINGS[problem]
    air, _ = write_recordings(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    out = tmp_path / "needle.yaml"
    result = run("calibrate", "needle", "--air", air, "--tissue", bad, "--radius", RADIUS, "--out", out)
    assert_refused(result, out, "--tissue", "bad.csv", *fragments)


@pytest.mark.parametrize("radius, fragment", [("-8.88", "got -8.88"), ("0", "got 0.0")])
def test_needle_refuses_non_positive_radius(tmp_path, radius, fragment):
    air, tissue = write_recordings(tmp_path)
    out = tmp_path / "needle.yaml"
    result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", radius, "--out", out)
    assert_refused(result, out, "--radius", fragment, "positive number (mm)")


def test_needle_refuses_an_output_named_for_another_format(tmp_path):
    air, tissue = write_recordings(tmp_path)
    out = tmp_path / "needle.json"  # the fitted block is YAML, to paste into a scenario
    result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", RADIUS, "--out", out)
    assert_refused(result, out, "--out", "a JSON file name; expected a YAML file name (.yaml, .yml)")


def test_needle_refuses_missing_file(tmp_path):
    _, tissue = write_recordings(tmp_path)
    out = tmp_path / "needle.yaml"
    result = run("calibrate", "needle", "--air", tmp_path / "nope.csv", "--tissue", tissue,
                 "--radius", RADIUS, "--out", out)
    assert_refused(result, out, "--air", "nope.csv", "cannot be read (No such file or directory)")


def _mutate_markers_missing(folder, data):
    data["experiments"][0]["markers"] = "missing.csv"


def _mutate_unknown_key(folder, data):
    data["fit"]["grdi"] = 5


def _mutate_marker_columns(folder, data):
    (folder / "markers0.csv").write_text("x,y,xd,yd\n1,2,3,4\n")


def _mutate_marker_outside(folder, data):
    (folder / "markers0.csv").write_text("x,y,x_def,y_def\n10,10,10,10\n120,10,121,10\n")


def _mutate_material_given(folder, data):
    data["tissue"]["material"] = {"lame_lambda": 0.2, "lame_mu": 0.1}


def _mutate_region_without_material(folder, data):
    data["tissue"]["regions"] = [{"circle": {"center": [45.0, 30.0], "radius": 14.0}}]


def _mutate_region_outside(folder, data):
    data["tissue"]["regions"] = [{**STIFF_DISC, "circle": {"center": [145.0, 30.0], "radius": 14.0}}]


def _mutate_regions_cover_the_tissue(folder, data):
    material = STIFF_DISC["material"]
    data["tissue"]["regions"] = [{"polygon": [[-5, -5], [60, -5], [60, 65], [-5, 65]], "material": material},
                                 {"polygon": [[50, -5], [105, -5], [105, 65], [50, 65]], "material": material}]


def _mutate_fitted_region_missing(folder, data):
    data["tissue"]["regions"] = [STIFF_DISC]
    data["fit"]["regions"] = [0, 1]


def _mutate_fitted_region_start(folder, data):
    data["tissue"]["regions"] = [{**STIFF_DISC, "material": {"model": "neo-hookean", "lame_lambda": 0.8,
                                                             "lame_mu": 5.0}}]
    data["fit"]["regions"] = [0]


def _mutate_fitted_region_without_regions(folder, data):
    data["fit"]["regions"] = [0]


def _mutate_fitted_region_twice(folder, data):
    data["tissue"]["regions"] = [STIFF_DISC]
    data["fit"]["regions"] = [0, 0]


def _mutate_bad_range(folder, data):
    data["fit"]["lame_mu"] = [2.0, 0.01]


def _mutate_bad_model(folder, data):
    data["fit"]["model"] = "mooney-rivlin"


BAD_CALIBRATIONS = {
    "missing markers file": (_mutate_markers_missing, ["experiments[0].markers", "missing.csv",
                                                       "cannot be read (No such file or directory)"]),
    "unknown key": (_mutate_unknown_key, ["fit", "unknown key 'grdi'", "expected one of"]),
    "marker columns": (_mutate_marker_columns, ["experiments[0].markers", "'x,y,xd,yd'",
                                                "'x,y,x_def,y_def'"]),
    "marker outside": (_mutate_marker_outside, ["line 3, x, y: got the rest position [120, 10] mm",
                                                "inside [0, 100] x [0, 60]"]),
    "material given": (_mutate_material_given, ["tissue.material", "fit.model"]),
    "region without material": (_mutate_region_without_material, ["tissue.regions[0].material", "missing"]),
    "region outside": (_mutate_region_outside, ["tissue.regions[0].circle", "expected a region overlapping the tissue"]),
    "regions cover the tissue": (_mutate_regions_cover_the_tissue, ["tissue.regions", "2 regions covering the whole "
                                                                     "tissue", "leave some of the tissue"]),
    "fitted region missing": (_mutate_fitted_region_missing, [
        "fit.regions[1]: got 1, expected an index of tissue.regions (it has 1 region: 0 to 0)"]),
    "fitted region start": (_mutate_fitted_region_start, [
        "tissue.regions[0].material.lame_mu: got 5.0, expected a start within fit.lame_mu [0.01, 2] MPa"]),
    "fitted region without regions": (_mutate_fitted_region_without_regions, [
        "fit.regions[0]: got 0, expected none (tissue.regions is empty)"]),
    "fitted region twice": (_mutate_fitted_region_twice, ["fit.regions: got [0, 0], expected each region at most once"]),
    "range reversed": (_mutate_bad_range, ["fit.lame_mu", "[2.0, 0.01]", "low < high"]),
    "unknown model": (_mutate_bad_model, ["fit.model", "'mooney-rivlin'", "neo-hookean"]),
}


@pytest.mark.parametrize("problem", sorted(BAD_CALIBRATIONS))
def test_material_refuses_bad_files(tmp_path, problem):
    mutate, fragments = BAD_CALIBRATIONS[problem]
    path = tmp_path / "calib.yaml"
    (tmp_path / "markers0.csv").write_text("x,y,x_def,y_def\n10,10,10.5,10.2\n50,30,50.3,30.1\n")
    data = {"tissue": {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"]},
            "experiments": [{"loads": load_block(LOADS["left-pull"]), "markers": "markers0.csv"}],
            "fit": dict(FIT)}
    mutate(tmp_path, data)
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--plot-dir", tmp_path / "plots")
    assert_refused(result, out, *fragments)
    assert not (tmp_path / "plots").exists()


# --- shipped example --------------------------------------------------------------------

SAMPLES = Path(__file__).resolve().parents[1] / "sample_runs" / "calibration"


def test_shipped_example_inputs_load_and_outputs_match_the_truth():
    """sample_runs/calibration: the inputs validate, the needle fit reproduces needle.yaml,
    and the shipped fitted values lie within 3 reported sigma of the generating values."""
    problem = calibration.load_material_calibration(SAMPLES / "calibration.yaml")
    assert [len(e.markers) for e in problem.experiments] == [20, 20]
    assert problem.discretization.spacing == pytest.approx(3.0)  # default: min(W, H) / 20
    fitted = yaml.safe_load((SAMPLES / "fitted.yaml").read_text())
    for name in ("lame_lambda", "lame_mu"):
        sigma = fitted["fit"]["standard_uncertainty"][name]
        assert abs(fitted["material"][name] - getattr(TRUE, name)) < 3 * sigma
    shipped = yaml.safe_load((SAMPLES / "needle.yaml").read_text())
    result = calibration.calibrate_needle(SAMPLES / "air.csv", SAMPLES / "tissue.csv", 8.88)
    assert result.friction == pytest.approx(shipped["friction"], rel=1e-5)
    assert result.cutting_force == pytest.approx(shipped["cutting_force"], rel=1e-5)
    assert abs(result.friction - FRICTION) < 3 * result.standard_uncertainty[0]
    assert abs(result.cutting_force - CUTTING) < 3 * result.standard_uncertainty[1]


def test_shipped_skin_layered_example_fits_the_truth_around_the_scenes_skin_layer():
    """sample_runs/calibration/skin_layered.yaml: the subcutaneous moduli fitted around the skin
    layer lie within 3 reported sigma of configs/skin_layered.yaml's material, its regions are
    the scene's, and the shipped uncertainty file takes its spread for that scene."""
    from stitchplan.config import load_scenario
    from stitchplan.config.uncertainty import check_against_scenario, load_uncertainty

    configs = SAMPLES.parents[1] / "configs"
    scene = load_scenario(configs / "skin_layered.yaml")
    fitted = yaml.safe_load((SAMPLES / "fitted_skin_layered.yaml").read_text())
    for name in ("lame_lambda", "lame_mu"):
        sigma = fitted["fit"]["standard_uncertainty"][name]
        assert abs(fitted["material"][name] - getattr(scene.tissue.material, name)) < 3 * sigma
    assert fitted["fit"]["identifiable"] and fitted["fit"]["warnings"] == []
    problem = calibration.load_material_calibration(SAMPLES / "skin_layered.yaml")
    assert problem.tissue.regions == scene.tissue.regions
    resolved = load_uncertainty(configs / "uncertainty" / "uncertainty_skin_layered.yaml")
    assert resolved.sources["lame_mu"] == "calibration" and resolved.calibration_regions == scene.tissue.regions
    check_against_scenario(resolved, scene, configs / "skin_layered.yaml")


def test_shipped_inclusion_example_fits_both_materials_near_the_truth():
    """sample_runs/calibration/inclusion.yaml: the block's moduli and the inclusion's, fitted
    together, lie within 3 reported sigma of generate.py's truth; fitted_inclusion.yaml's
    region is the file's circle at the fitted moduli, the poorly determined lame_lambda of the
    inclusion said so."""
    truth = {"lame_lambda": 0.756604, "lame_mu": 0.590752}  # generate.py's INCLUSION
    problem = calibration.load_material_calibration(SAMPLES / "inclusion.yaml")
    assert problem.fit.regions == (0,) and [len(e.markers) for e in problem.experiments] == [40, 40, 40]
    fitted = yaml.safe_load((SAMPLES / "fitted_inclusion.yaml").read_text())
    fit = fitted["fit"]
    for name in ("lame_lambda", "lame_mu"):
        assert abs(fitted["material"][name] - getattr(TRUE, name)) < 3 * fit["standard_uncertainty"][name]
        region = fit["fitted_regions"][0]
        assert abs(region[name] - truth[name]) < 3 * region["standard_uncertainty"][name]
        assert fitted["regions"][0]["material"][name] == region[name]
    assert fitted["regions"][0]["circle"] == {"center": [45.0, 30.0], "radius": 14.0}
    assert fit["identifiable"] and fit["warnings"][0] == (
        "tissue.regions[0].lame_lambda is poorly determined: standard uncertainty 0.439 MPa is 85 % of its "
        "value; add markers or experiments")
    # at twice the spacing both lame_mu move by over a third of their sigma (benchmarks/calibration_spread.py
    # finds the inclusion's biased at the default spacing)
    moved = fit["discretization_estimate"]["change_over_standard_uncertainty"]
    assert [w.split(" = ")[0] for w in fit["warnings"][1:]] == [name for name, share in moved.items() if share > 1 / 3]
    assert sorted(name for name, share in moved.items() if share > 1 / 3) == ["lame_mu", "tissue.regions[0].lame_mu"]


# --- layering -------------------------------------------------------------------------

PACKAGE = Path(__file__).resolve().parents[1] / "stitchplan"
ABOVE_CALIBRATION = ("stitchplan.study", "stitchplan.io", "stitchplan.cli")


def _imported_modules(path: Path) -> set[str]:
    """Absolute names of every module a file imports, at module or function level."""
    import ast

    package = "stitchplan." + ".".join(path.relative_to(PACKAGE).parent.parts)
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package.rstrip(".").split(".")
            base = base[:len(base) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            names.update([module] + [f"{module}.{alias.name}" for alias in node.names])
    return names


@pytest.mark.parametrize("path", sorted((PACKAGE / "calibration").glob("*.py")), ids=lambda p: p.name)
def test_calibration_imports_no_layer_above_it(path):
    upward = {name for name in _imported_modules(path)
              if any(name == top or name.startswith(top + ".") for top in ABOVE_CALIBRATION)}
    assert not upward, f"{path.name} imports {sorted(upward)}"


def test_needle_report_carries_the_fit_and_rounds_it(tmp_path):
    from stitchplan.io.calibration_reports import (
        needle_report,
        needle_summary_line,
        write_needle_outputs,
    )

    air, tissue = write_recordings(tmp_path)
    result = calibration.calibrate_needle(air, tissue, RADIUS)
    report = needle_report(result)
    assert report["friction"] == pytest.approx(result.friction, rel=1e-5)
    assert report["cutting_force"] == pytest.approx(result.cutting_force, rel=1e-5)
    assert report["diagnostics"]["air"] == str(air)
    assert f"friction {result.friction:.6g}" in needle_summary_line(result)
    out = tmp_path / "needle.yaml"
    write_needle_outputs(result, out)
    assert yaml.safe_load(out.read_text())["friction"] == report["friction"]


@pytest.mark.parametrize("fitted, on_bound", [
    ((0.196, 0.15), set()),  # well inside ranges that span decades
    ((0.01, 0.15), {"lame_lambda"}),  # at the low end
    ((0.196, 100.0), {"lame_mu"}),  # at the high end
])
def test_the_bound_warning_names_only_a_modulus_at_its_bound(fitted, on_bound):
    """The margin is relative to the value: a range of decades ([0.01, 1e6] MPa) used to flag
    a fit of 0.196 MPa as lying on the bound."""
    from types import SimpleNamespace

    from stitchplan.calibration.inputs import FitSettings
    from stitchplan.calibration.fit_statistics import Statistics, fit_warnings
    from stitchplan.calibration.material_fit import Refinement

    fit = FitSettings("neo-hookean", (0.01, 1e6), (0.001, 100.0))
    stats = Statistics((0.01, 0.01), 0.1, 0.01)
    refinement = Refinement(SimpleNamespace(status=1, nfev=10), 0)
    warnings = fit_warnings(np.array(fitted), stats, fit, refinement)
    assert {name for name in ("lame_lambda", "lame_mu") if any(f"{name} = " in w and "bound" in w
                                                               for w in warnings)} == on_bound


# --- search ranges the fit can resolve, negative needle fits, one recording twice -------


def _calibration_with_fit(folder, **fit) -> Path:
    """A calibration file on one small marker file with the given search ranges."""
    (folder / "markers0.csv").write_text("x,y,x_def,y_def\n10,10,10.5,10.2\n50,30,50.3,30.1\n")
    data = {"tissue": {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"]},
            "experiments": [{"loads": load_block(LOADS["left-pull"]), "markers": "markers0.csv"}],
            "fit": {**FIT, **fit}}
    path = folder / "calib.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("fit, fragments", [
    # the geometric middle of [1e-200, 1e-199] underflowed to 0.0: a traceback from Material
    ({"lame_mu": [1e-200, 1e-199]}, ["fit.lame_mu[0]", "got 1e-200", "at least 1e-06"]),
    ({"lame_mu": [0.0, 2.0]}, ["fit.lame_mu[0]", "got 0.0", "at least 1e-06"]),
    ({"lame_lambda": [1e-9, 2.0]}, ["fit.lame_lambda[0]", "got 1e-09", "0 or a number of at least 1e-06"]),
    # hundreds of decades: every grid point failed, or the trust region overflowed
    ({"lame_lambda": [0.01, 1e300]}, ["fit.lame_lambda[1]", "got 1e+300", "at most 1e+06"]),
    ({"lame_mu": [0.01, 1e7]}, ["fit.lame_mu[1]", "got 10000000.0", "at most 1e+06"]),
])
def test_material_refuses_search_ranges_the_fit_cannot_resolve(tmp_path, fit, fragments):
    path = _calibration_with_fit(tmp_path, **fit)
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--spacing", 10)
    assert_refused(result, out, str(path), *fragments)


def test_search_range_bounds_are_accepted_and_the_start_point_lies_inside(tmp_path):
    from stitchplan.calibration.inputs import _start_point

    problem = calibration.load_material_calibration(
        _calibration_with_fit(tmp_path, lame_lambda=[0.0, 1e6], lame_mu=[1e-6, 1e6]))
    assert problem.fit.lame_mu == (1e-6, 1e6) and problem.fit.grid_scale == "linear"
    # sqrt(low * high) under- and overflows where sqrt(low) * sqrt(high) does not
    for low, high in [(1e-200, 1e-199), (10.0, 1e308), (1.0, math.nextafter(1.0, 2.0))]:
        start = _start_point(calibration.FitSettings("neo-hookean", (low, high), (low, high)))
        assert all(low <= value <= high and value > 0 for value in start)


def _needle_run(tmp_path, tissue_force):
    """calibrate needle on the noise-free air recording and a tissue recording of the given
    force (N) at the tissue angles of write_recordings."""
    air, tissue = write_recordings(tmp_path)
    angle = np.loadtxt(tissue, delimiter=",", skiprows=1)[:, 0]
    rows = "".join(f"{float(a)!r},{float(f)!r}\n" for a, f in zip(angle, tissue_force(angle)))
    tissue.write_text("angle_rad,force_N\n" + rows)
    out, plot = tmp_path / "needle.yaml", tmp_path / "forces.png"
    result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", RADIUS,
                 "--out", out, "--plot", plot)
    return result, out, plot


@pytest.mark.parametrize("tissue_force, fragments", [
    # a constant force less the growing background: friction = -0.035 / 8.88 N/mm (the audit's case)
    (lambda a: 0.5 + 0.0 * a, ["friction -0.003941", "does not grow with the inserted length"]),
    # below the background at the entry: a negative cutting force
    (lambda a: BACKGROUND[0] + BACKGROUND[1] * a - 0.2 + FRICTION * RADIUS * a,
     ["cutting force -0.2", "starts below the air background"]),
])
def test_needle_fit_with_a_negative_value_fails_and_writes_nothing(tmp_path, tissue_force, fragments):
    result, out, plot = _needle_run(tmp_path, tissue_force)
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    tissue, air = tmp_path / "tissue.csv", tmp_path / "air.csv"
    assert len(lines) == 1 and lines[0].startswith(f"error: --tissue {tissue} and --air {air}: needle fit: the fit "
                                                   "gave "), result.output
    assert "expected >= 0" in lines[0] and "Traceback" not in result.output
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert not out.exists() and not plot.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith((".needle.yaml.", ".forces.png."))]


def test_needle_fit_of_a_tissue_recording_equal_to_the_air_one_says_it_shows_no_force(tmp_path):
    """One recording twice, the second 1 uN up (an exact copy is refused as one before the fit):
    friction and cutting force zero to within their uncertainty, either sign; the error says
    so, not that the recording starts below the air's."""
    air, tissue = write_recordings(tmp_path, noise=(0.01, 0.01))
    rows = air.read_text().splitlines()
    tissue.write_text("\n".join([rows[0], *(f"{a},{float(f) + 1e-6!r}" for a, f in
                                            (row.split(",") for row in rows[1:]))]) + "\n")
    out, plot = tmp_path / "needle.yaml", tmp_path / "forces.png"
    result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", RADIUS,
                 "--out", out, "--plot", plot)
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1, result.output
    assert "standard uncertainty, the tissue recording shows no force above the air's" in lines[0], lines[0]
    assert "starts below" not in lines[0] and "is --tissue the recording" not in lines[0]
    assert not out.exists() and not plot.exists()


def test_needle_refuses_one_recording_as_both_air_and_tissue(tmp_path):
    air, _ = write_recordings(tmp_path)
    link = tmp_path / "link.csv"
    link.symlink_to(air)
    out = tmp_path / "needle.yaml"
    for tissue in (air, link):
        result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", RADIUS, "--out", out)
        assert_refused(result, out, f"--tissue: got {tissue}", f"the same file as --air ({air})")


def test_needle_refuses_a_copy_of_the_air_recording_as_the_tissue_one(tmp_path):
    """The same file was refused, a copy of it was fitted: friction and cutting force of ~1e-17
    written with a warning."""
    air, _ = write_recordings(tmp_path)
    copy = tmp_path / "copy.csv"
    copy.write_bytes(air.read_bytes())
    out = tmp_path / "needle.yaml"
    result = run("calibrate", "needle", "--air", air, "--tissue", copy, "--radius", RADIUS, "--out", out)
    assert_refused(result, out, f"--tissue: {copy}: got the same angles and forces as --air's {air}; expected the "
                                "recording in tissue, not a copy of the one in air")


def test_the_fits_uncertainties_and_correlation_are_those_of_linear_least_squares():
    """fit_statistics.statistics on a straight line y = a x + b fitted to noisy points: the
    standard uncertainties and the correlation of (a, b) are scipy's curve_fit's (residual
    variance over m - 2 degrees of freedom)."""
    from scipy.optimize import curve_fit

    from stitchplan.calibration.fit_statistics import statistics

    rng = np.random.default_rng(5)
    x = np.linspace(1.0, 4.0, 7)
    y = 0.8 * x + 0.3 + rng.normal(0.0, 0.05, x.size)
    (a, b), covariance = curve_fit(lambda x, a, b: a * x + b, x, y,
                                   jac=lambda x, a, b: np.column_stack([x, np.ones_like(x)]))
    residual = a * x + b - y
    stats = statistics(residual, np.column_stack([x, np.ones_like(x)]), np.array([a, b]))
    np.testing.assert_allclose(stats.uncertainty, np.sqrt(np.diag(covariance)), rtol=1e-9)
    assert stats.correlation == pytest.approx(covariance[0, 1] / math.sqrt(covariance[0, 0] * covariance[1, 1]),
                                              rel=1e-9)
    ratio_gradient = np.array([1.0 / b, -a / b**2])  # of a / b, by the delta method
    assert stats.ratio_uncertainty == pytest.approx(math.sqrt(ratio_gradient @ covariance @ ratio_gradient), rel=1e-9)


def test_the_uncertainties_and_correlations_of_more_moduli_are_those_of_linear_least_squares():
    """The same with four parameters (the tissue's pair and a fitted region's): y = a x + b +
    c x^2 + d sin x, its m - 4 degrees of freedom and every correlation as curve_fit's."""
    from scipy.optimize import curve_fit

    from stitchplan.calibration.fit_statistics import statistics

    rng = np.random.default_rng(6)
    x = np.linspace(1.0, 4.0, 12)
    columns = np.column_stack([x, np.ones_like(x), x**2, np.sin(x)])
    y = columns @ [0.8, 0.3, -0.1, 0.5] + rng.normal(0.0, 0.05, x.size)
    theta, covariance = curve_fit(lambda x, *p: columns @ p, x, y, p0=np.ones(4), jac=lambda x, *p: columns)
    stats = statistics(columns @ theta - y, columns, theta)
    spread = np.sqrt(np.diag(covariance))
    np.testing.assert_allclose(stats.uncertainty, spread, rtol=1e-9)
    np.testing.assert_allclose(stats.correlations, covariance / np.outer(spread, spread), rtol=1e-9, atol=1e-12)
    assert stats.correlation == pytest.approx(stats.correlations[0, 1], rel=1e-12)
    assert stats.separable


def test_the_grid_skips_only_points_softer_in_both_moduli_than_a_failure():
    """Under force loads a grid point softer in lame_lambda and lame_mu than one whose solve
    failed is not tried; every other point is: with the forward model failing below
    mu = 0.05 MPa whatever lambda, the grid's cost is known exactly where mu >= 0.05 (by brute
    force over the grid) and its best point is the best of those."""
    from types import SimpleNamespace

    from stitchplan.calibration.inputs import FitSettings
    from stitchplan.calibration.material_fit import (
        ForwardFailure,
        grid_axes,
        grid_search,
    )

    fit = FitSettings("neo-hookean", (0.01, 2.0), (0.01, 2.0), grid_points=6)

    def cost(theta):
        return np.array([theta[0] - 0.02, theta[1] - 0.3])

    def evaluate(theta, quick=False):
        if theta[1] < 0.05:
            raise ForwardFailure("pull", theta, "det F < 0")
        return cost(theta), None, None

    misfit = SimpleNamespace(force_controlled=True, evaluate=evaluate, labels=("pull",))
    search = grid_search(misfit, fit, lambda *args: None)
    lambdas, mus = grid_axes(fit)
    expected = np.array([[float(cost((lam, mu)) @ cost((lam, mu))) if mu >= 0.05 else np.nan for mu in mus]
                         for lam in lambdas])
    np.testing.assert_array_equal(np.isnan(search.cost), np.isnan(expected))
    np.testing.assert_allclose(search.cost[~np.isnan(expected)], expected[~np.isnan(expected)], rtol=1e-15)
    i, j = np.unravel_index(np.nanargmin(expected), expected.shape)
    assert search.best == (lambdas[i], mus[j])
