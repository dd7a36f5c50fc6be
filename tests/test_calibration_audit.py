"""`calibrate material` on the inputs an audit found mishandled: the discretization estimate
that made the resource guard refuse a valid fit, the marker count of a fit with regions, a
region that holds no tissue behind earlier ones, solver settings that stop the model or the
grid, markers given in metres, a marker on a clamp that moved, and experiments of one name.

Each scene is the 100 x 60 mm block of test_calibration at a 10 mm spacing (or a refusal made
before any solve), so the file runs in seconds.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from stitchplan import calibration
from stitchplan.calibration.fit_statistics import fit_warnings, statistics
from stitchplan.calibration.inputs import FitSettings
from stitchplan.config.scenario import load_scenario
from stitchplan.errors import InputError

from test_calibration import (
    FIT,
    LOADS,
    STIFF_DISC,
    assert_refused,
    load_block,
    run,
    write_calibration,
)

TISSUE_BLOCK = {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"]}
SPREAD = "10,10,10.5,10.2\n50,30,50.3,30.1\n80,50,80.1,49.9\n"  # three markers over the block


def calibration_file(folder, rows=SPREAD, experiments=1, extra=None, tissue=None, fit=None):
    """A calibration of `experiments` left-pull experiments on the marker rows given (each its
    own copy of them, its measured x moved by k x 1e-4 mm, so that no experiment repeats
    another's markers), at a 10 mm spacing."""
    entries = []
    for k in range(experiments):
        moved = [line.split(",") for line in rows.strip().splitlines()]
        text = "".join(f"{x},{y},{float(x_def) + 1e-4 * k!r},{y_def}\n" for x, y, x_def, y_def in moved)
        (folder / f"markers{k}.csv").write_text("x,y,x_def,y_def\n" + text)
        entries.append({"name": f"pull {k}", "loads": load_block(LOADS["left-pull"]), "markers": f"markers{k}.csv"})
    data = {"tissue": tissue or dict(TISSUE_BLOCK), "experiments": entries, "fit": fit or dict(FIT),
            "discretization": {"spacing": 10.0}, **(extra or {})}
    path = folder / "calib.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def with_changes(path, change):
    """The calibration file at `path` rewritten with `change(data)` applied."""
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# --- 1: the discretization estimate and the resource guard ------------------------------


@pytest.mark.parametrize("where", ["option", "file"])
def test_a_fit_whose_estimate_would_be_too_coarse_runs_and_records_the_estimate_not_made(tmp_path, where):
    """At a 20 mm spacing (--spacing or the file's) on the 60 mm high block the fit is sound;
    its estimate at 40 mm is above half the smaller side. The guard refused the fit for the
    estimate's spacing ("--spacing: got 40 mm"); now the fit runs and the estimate is recorded
    as not made, why in fit.discretization_estimate.failure, and said as a failed one is."""
    path = write_calibration(tmp_path, [LOADS["left-pull"], LOADS["top-press"]], noise=0.05)
    options = ["--spacing", "20"] if where == "option" else []
    if where == "file":
        with_changes(path, lambda data: data["discretization"].update(spacing=20.0))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, *options)
    assert result.exit_code == 0, result.output
    assert "got 40 mm" not in result.output
    assert "no discretization estimate (the fit at 40 mm failed)" in result.output
    fitted = yaml.safe_load(out.read_text())
    block = fitted["fit"]["discretization_estimate"]
    assert block["spacing_mm"] == 40.0 and block["moduli"] is None and block["change"] is None
    assert block["failure"] == ("its model at 40 mm would be too coarse for the tissue (100 x 60 mm): a spacing may "
                                "be at most half the smaller side, 30 mm, so that three particles span it")
    assert any(w.startswith("no discretization estimate: the fit at twice the spacing (40 mm) failed (its model at "
                            "40 mm would be too coarse") for w in fitted["fit"]["warnings"])
    assert fitted["diagnostics"]["discretization"]["spacing_mm"] == 20.0
    assert fitted["fit"]["identifiable"] is True


def test_the_guard_refuses_a_calibration_by_the_fits_own_models(tmp_path):
    """--max-particles 100 against the default 3 mm models: one line, the first experiment's
    model's (the other's names the same field: the guard says a field once), none for the
    estimate's coarser models at 6 mm (two more lines, naming a `discretization.spacing: got
    6 mm` the file never gave)."""
    path = calibration_file(tmp_path, experiments=2)
    with_changes(path, lambda data: data.pop("discretization"))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--max-particles", 100)
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1, result.output
    for k, line in enumerate(lines):
        assert line.startswith("error: ") and "tissue.size: got [100, 60] mm" in line, line
        assert f"(estimated experiments[{k}]: " in line, line
    assert "twice the spacing" not in result.output and "got 6 mm" not in result.output
    assert not out.exists()


def test_the_estimates_coarser_models_still_count_in_the_memory_held_at_once():
    """The guard's runs held in one process: a model held beside them (the estimate's, at a
    coarser spacing) gets no line of its own, even one too coarse for the tissue, but its
    memory counts with the rest."""
    from stitchplan.config import Discretization, Scenario, Tissue
    from stitchplan.resources.costs import estimate, held_in_one_process
    from stitchplan.resources.limits import Limits
    from stitchplan.resources.guard import check_resources

    tissue = Tissue((100.0, 60.0), 10.0, clamped=("right",))
    loads = LOADS["left-pull"]
    fine, coarse = (estimate(Scenario(tissue=tissue, discretization=Discretization(spacing=spacing), loads=loads),
                             "deform", label) for spacing, label in ((20.0, "fit"), (40.0, "estimate")))
    check_resources([fine], memory=1e12, space=None, in_one_process=True, beside=[coarse])  # no refusal
    with pytest.raises(InputError) as error:  # alone, the 40 mm model is too coarse
        check_resources([coarse], memory=1e12, space=None, in_one_process=True)
    assert "discretization.spacing: got 40 mm, expected at most half the tissue's smaller side" in str(error.value)
    # too little memory for both together, enough for the fit's alone: refused, counting the estimate's
    both = held_in_one_process([fine.memory_bytes, coarse.memory_bytes])
    memory = both / Limits().memory_share - 1.0
    check_resources([fine], memory=memory, space=None, in_one_process=True)
    with pytest.raises(InputError) as error:
        check_resources([fine], memory=memory, space=None, in_one_process=True, beside=[coarse])
    assert "when they run at once" in str(error.value) and "estimate: " in str(error.value)


# --- 2: the markers a fit of regions needs ----------------------------------------------


def test_a_fit_of_regions_needs_a_marker_more_per_region(tmp_path):
    """Two markers fit the tissue's two moduli with an uncertainty (4 coordinates for 2), not
    four moduli with a region's (4 coordinates for 4: no residual degree of freedom, null
    uncertainties). The refusal counts P = 2 + 2 x the fitted regions, before any solve."""
    tissue = {**TISSUE_BLOCK, "regions": [STIFF_DISC]}
    path = calibration_file(tmp_path, rows="10,10,10.5,10.2\n50,30,50.3,30.1\n", tissue=tissue,
                            fit={**FIT, "regions": [0]})
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert_refused(result, out, "calib.yaml: experiments: 2 markers in all, expected at least 3 (6 coordinates for 4 "
                                "parameters and their uncertainty: the tissue's 2 moduli and 2 for each of the 1 "
                                "region of fit.regions [0])")


def test_the_marker_count_of_the_tissues_moduli_alone_is_unchanged(tmp_path):
    path = calibration_file(tmp_path, rows="10,10,10.5,10.2\n")
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert_refused(result, out, "calib.yaml: experiments: 1 marker in all, expected at least 2 (4 coordinates for 2 "
                                "parameters and their uncertainty)")


# --- 3: a region that holds no tissue behind earlier ones -------------------------------


def _halves_and_disc():
    """Two half-plane regions that together cover the disc, then the disc."""
    material = STIFF_DISC["material"]
    return [{"polygon": [[30, 10], [45, 10], [45, 50], [30, 50]], "material": material},
            {"polygon": [[45, 10], [60, 10], [60, 50], [45, 50]], "material": material},
            {"circle": {"center": [45.0, 30.0], "radius": 10.0}, "material": material}]


@pytest.mark.parametrize("regions, fitted, fragments", [
    ([STIFF_DISC, STIFF_DISC], [1], ["tissue.regions[1].circle: got {'center': [45.0, 30.0], 'radius': 14.0}, "
                                     "expected a region overlapping the tissue (this one holds no tissue: "
                                     "tissue.regions[0], listed before it, covers its part of the tissue, and the "
                                     "region listed first wins where regions overlap)"]),
    (_halves_and_disc(), [], ["tissue.regions[2].circle: got", "tissue.regions[0] and tissue.regions[1], listed "
                                                               "before it, cover its part of the tissue"]),
])
def test_a_region_covered_by_earlier_ones_is_refused(tmp_path, regions, fitted, fragments):
    """Regions listed first win: a region inside earlier ones holds no quadrature point. Fitted,
    the fit ran 25 s and ended its moduli anywhere; given, it is a mistake all the same."""
    path = calibration_file(tmp_path, tissue={**TISSUE_BLOCK, "regions": regions}, fit={**FIT, "regions": fitted})
    out = tmp_path / "fitted.yaml"
    assert_refused(run("calibrate", "material", path, "--out", out), out, *fragments)


def test_a_region_partly_covered_by_an_earlier_one_is_accepted(tmp_path):
    material = STIFF_DISC["material"]
    regions = [{"circle": {"center": [40.0, 30.0], "radius": 10.0}, "material": material},
               {"circle": {"center": [50.0, 30.0], "radius": 10.0}, "material": material}]
    path = calibration_file(tmp_path, tissue={**TISSUE_BLOCK, "regions": regions})
    assert len(calibration.load_material_calibration(path).tissue.regions) == 2


def test_a_scenarios_regions_are_not_checked_for_cover(tmp_path):
    """The check is the calibration's: a scenario keeps its regions as they come (its shipped
    configs unchanged)."""
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump({"tissue": {**TISSUE_BLOCK, "regions": [STIFF_DISC, STIFF_DISC],
                                               "material": {"lame_lambda": 0.2, "lame_mu": 0.15}}}))
    assert len(load_scenario(path).tissue.regions) == 2


# --- 4: solver settings -----------------------------------------------------------------


@pytest.mark.parametrize("setting, value", [("residual_tolerance", 1e6), ("increment_tolerance", 0.5),
                                            ("residual_tolerance", 0.01)])
def test_relative_tolerances_that_stop_newton_at_once_are_refused(tmp_path, setting, value):
    """residual_tolerance 1e6 let every solve stop before its first iteration: the model never
    moved and both moduli ended on a bound with a `+nan` correlation."""
    path = calibration_file(tmp_path, extra={"solver": {setting: value}})
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert_refused(result, out, f"calib.yaml: solver.{setting}: got {value}, expected a positive number below 0.01 "
                                "(a relative tolerance)")


def test_a_relative_tolerance_below_the_bound_is_accepted(tmp_path):
    path = calibration_file(tmp_path, extra={"solver": {"residual_tolerance": 5e-3, "increment_tolerance": 1e-3}})
    assert calibration.load_material_calibration(path).solver.residual_tolerance == 5e-3


def test_a_correlation_that_cannot_be_computed_is_said_so_not_printed_as_nan():
    """No marker moving with a modulus (a zero Jacobian column: markers where the tissue is
    held, a model that did not deform) leaves the correlation undefined (nan)."""
    jacobian = np.zeros((6, 2))
    jacobian[:, 0] = [1.0, 0.5, -0.2, 0.3, 0.0, 0.1]
    fit = FitSettings("saint-venant-kirchhoff", (0.01, 2.0), (0.01, 2.0))
    theta = np.array([0.2, 0.15])
    stats = statistics(np.full(6, 0.01), jacobian, theta)
    least_squares = SimpleNamespace(solution=SimpleNamespace(status=1, nfev=5), failed_solves=0)
    warnings = fit_warnings(theta, stats, fit, least_squares, displacements_only=False)
    assert np.isnan(stats.correlation)
    assert not any("nan" in w for w in warnings), warnings
    assert warnings[0].startswith("the data cannot separate the fitted moduli: the correlation of their estimates "
                                  "could not be computed, as no marker moves with lame_mu at the fitted moduli")
    assert stats.insensitive == (1,)


def test_a_grid_stopped_by_a_low_iteration_limit_names_solver_max_iterations(tmp_path):
    """solver.max_iterations 1: every solve of the grid fails on the limit; the refusal named
    the search ranges and the loads instead."""
    path = calibration_file(tmp_path, extra={"solver": {"max_iterations": 1}})
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert_refused(result, out, "calib.yaml: solver.max_iterations: got 1, expected enough Newton iterations for the "
                                "forward model to converge (the default is 25): every solve the fit's grid tried "
                                "stopped at Newton's iteration limit (", "no convergence in 1 iteration (")
    assert "expected ranges where the tissue can carry the loads" not in result.output


def test_a_grid_failing_otherwise_keeps_naming_the_ranges(tmp_path):
    """Loads the tissue cannot carry in the ranges (a hundredfold pull on a soft range) fail on
    inverted material, not on the iteration limit: the refusal names the ranges as before."""
    path = calibration_file(tmp_path, fit={"lame_lambda": [0.001, 0.002], "lame_mu": [0.001, 0.002], "grid": 2},
                            extra={"solver": {"max_iterations": 5}})
    with_changes(path, lambda data: data["experiments"][0]["loads"][0].update(force=[-200.0, 0.0]))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--no-estimate")
    assert_refused(result, out, "calib.yaml: fit: could not evaluate any moduli",
                   "expected ranges where the tissue can carry the loads")


# --- 5, 6: markers in metres, a marker on a clamp that moved -----------------------------


def test_markers_in_metres_get_a_hint(tmp_path):
    """Rest positions all within 0.08 x 0.05 mm of a corner of the 100 x 60 mm block (metres read
    as mm): the fit ends on a bound; the warning says what to check."""
    path = write_calibration(tmp_path, [LOADS["left-pull"]], noise=0.0)
    for csv in tmp_path.glob("markers*.csv"):
        rows = np.loadtxt(csv, delimiter=",", skiprows=1)
        csv.write_text("x,y,x_def,y_def\n" + "".join(",".join(f"{v:.12g}" for v in row) + "\n"
                                                     for row in 1e-3 * rows))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--no-estimate")
    assert result.exit_code == 0, result.output
    hint = "experiments[0].markers: "
    expected = ("markers0.csv: x, y: the 20 markers' rest positions span only ", " mm, less than 1/100 of the "
                "tissue's 100 x 60 mm in both directions: are they in m rather than mm? (marker files are read in mm)")
    warnings = yaml.safe_load(out.read_text())["fit"]["warnings"]
    assert warnings[0].startswith(hint) and all(part in warnings[0] for part in expected), warnings
    assert f"warning: {warnings[0]}" in result.output


def test_markers_over_the_tissue_get_no_metres_hint(tmp_path):
    path = write_calibration(tmp_path, [LOADS["left-pull"]], markers=3)
    assert calibration.load_material_calibration(path).warnings == []


def test_a_marker_on_a_clamped_edge_that_moved_is_warned_about(tmp_path):
    """The model holds the clamped edge fixed: a marker there that moved 0.5 mm is misfit
    whatever the moduli. One that stayed says nothing."""
    rows = SPREAD + "100,30,100.5,30\n100,10,100,10\n"
    path = calibration_file(tmp_path, rows=rows)
    problem = calibration.load_material_calibration(path)
    assert problem.warnings == [
        f"experiments[0].markers: {tmp_path / 'markers0.csv'}: line 5, x_def, y_def: the marker at rest at [100, 30] "
        "mm lies on the clamped edge 'right' (tissue.clamped[0]), which the model holds fixed, yet moved by 0.5 mm "
        "to [100.5, 30]: its move is misfit whatever the moduli (does the clamp slip, or does the marker lie off "
        "the clamped edge?)"]
    with_changes(path, lambda data: data["tissue"].update(clamped=[{"segment": [[100.0, 20.0], [100.0, 40.0]]}]))
    (warning,) = calibration.load_material_calibration(path).warnings
    assert "lies on a clamped segment (tissue.clamped[0])" in warning
    (tmp_path / "markers0.csv").write_text("x,y,x_def,y_def\n" + SPREAD + "100,30,100,30\n")
    assert calibration.load_material_calibration(path).warnings == []


def test_the_inputs_warnings_lead_the_fits(tmp_path):
    rows = SPREAD + "100,30,100.5,30\n"
    path = calibration_file(tmp_path, rows=rows)
    result = calibration.fit_material(calibration.load_material_calibration(path), estimate=False)
    assert result.warnings[0].startswith("experiments[0].markers: ") and "clamped edge 'right'" in result.warnings[0]


# --- 7: experiment names ----------------------------------------------------------------


def test_two_experiments_of_one_name_are_refused(tmp_path):
    path = calibration_file(tmp_path, experiments=3)
    with_changes(path, lambda data: data["experiments"][2].update(name="pull 0"))
    out = tmp_path / "fitted.yaml"
    assert_refused(run("calibrate", "material", path, "--out", out), out,
                   "calib.yaml: experiments[2].name: got 'pull 0', expected a name of its own (experiments[0] has it "
                   "too; fitted.yaml's results per experiment are told apart by it)")


def test_a_name_that_is_an_unnamed_experiments_index_is_refused(tmp_path):
    """fitted.yaml calls an unnamed experiment by its index: one named `experiments[1]` beside
    an unnamed experiments[1] gave two results of one name."""
    path = calibration_file(tmp_path, experiments=2)
    with_changes(path, lambda data: (data["experiments"][0].update(name="experiments[1]"),
                                     data["experiments"][1].pop("name")))
    out = tmp_path / "fitted.yaml"
    assert_refused(run("calibrate", "material", path, "--out", out), out,
                   "calib.yaml: experiments[0].name: got 'experiments[1]', expected a name of its own (experiments[1], "
                   "unnamed, is called so; fitted.yaml's results per experiment are told apart by it)")


def test_unnamed_experiments_are_told_apart_by_their_index(tmp_path):
    path = calibration_file(tmp_path, experiments=2)
    with_changes(path, lambda data: [experiment.pop("name") for experiment in data["experiments"]])
    assert len(calibration.load_material_calibration(path).experiments) == 2


@pytest.mark.parametrize("markers, warned", [(2, True), (7, True), (8, False), (40, False)])
def test_few_residual_degrees_of_freedom_say_the_interval_is_wider(markers, warned):
    """sigma^2 from 2 x markers - 2 residuals: with 2 markers (2 degrees of freedom) +-1.96
    standard uncertainties covered the truth in ~80 % of noisy fits (Student's t: 95 % needs
    +-4.3); the fit says so where t widens the 95 % interval by more than 10 % (13 degrees of
    freedom or fewer), and not beyond."""
    rng = np.random.default_rng(3)
    jacobian = rng.standard_normal((2 * markers, 2))
    fit = FitSettings("saint-venant-kirchhoff", (0.01, 2.0), (0.01, 2.0))
    theta = np.array([0.2, 0.15])
    stats = statistics(0.01 * rng.standard_normal(2 * markers), jacobian, theta)
    least_squares = SimpleNamespace(solution=SimpleNamespace(status=1, nfev=5), failed_solves=0)
    warnings = fit_warnings(theta, stats, fit, least_squares, displacements_only=False)
    found = [w for w in warnings if "degree(s) of freedom" in w]
    assert bool(found) == warned, warnings
    if markers == 2:
        assert found[0].startswith("the standard uncertainties rest on 2 degree(s) of freedom only")
        assert "+-4.3 standard uncertainties" in found[0]
