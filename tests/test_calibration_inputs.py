"""Calibration inputs the fit cannot use, and fits it must not report as identified.

Markers that did not move or moved implausibly far are refused as input errors; a modulus
fitted on a bound of its search range is not identified, and the advice stays within the
moduli a range may reach; a forward solve that fails at a grid or refinement point never
escapes as an unexplained Newton failure; the numbers of marker files and force recordings
are plain decimals, the rule of the --center-path files.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from stitchplan import calibration
from stitchplan.calibration.inputs import Experiment, FitSettings
from stitchplan.calibration.fit_statistics import Statistics, fit_warnings
from stitchplan.calibration.material_fit import ForwardFailure, Refinement, refine
from stitchplan.errors import InputError, SolverDivergence

from test_calibration import FIT, LOADS, RADIUS, assert_refused, load_block, run, write_calibration, write_recordings

TISSUE_BLOCK = {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"]}


def marker_calibration(folder, rows: str, fit: dict | None = None):
    """A calibration file of one left-pull experiment on the marker rows given (CSV text)."""
    (folder / "markers0.csv").write_text("x,y,x_def,y_def\n" + rows)
    data = {"tissue": TISSUE_BLOCK,
            "experiments": [{"name": "left-pull", "loads": load_block(LOADS["left-pull"]),
                             "markers": "markers0.csv"}],
            "fit": fit or dict(FIT), "discretization": {"spacing": 10.0}}
    path = folder / "calib.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


MOVED = "10,10,10.5,10.2\n50,30,50.3,30.1\n"


def test_a_marker_column_named_twice_is_refused_as_named_twice(tmp_path):
    """As a --center-path's: the header said only that it was not x,y,x_def,y_def."""
    path = marker_calibration(tmp_path, MOVED)
    (tmp_path / "markers0.csv").write_text("x,x,x_def,y_def\n" + MOVED)
    with pytest.raises(InputError) as error:
        calibration.load_material_calibration(path)
    markers = tmp_path / "markers0.csv"
    assert error.value.lines == [(f"{path}: experiments[0].markers: {markers}: line 1, column 2: got 'x' again, "
                                  "expected each column once (the header lacks y)")]


# --- markers that did not move ----------------------------------------------------------


@pytest.mark.parametrize("fit", [dict(FIT), {**FIT, "lame_lambda": [0.01, 1e6], "lame_mu": [0.01, 1e6]}])
def test_markers_that_did_not_move_are_refused(tmp_path, fit):
    """They used to fit the stiffest corner of the range (2 MPa, or 1e6 MPa) as identifiable."""
    path = marker_calibration(tmp_path, "10,10,10,10\n50,30,50,30\n80,20,80,20\n", fit)
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert_refused(result, out, f"{path}: experiments[0].markers: {tmp_path / 'markers0.csv'}: x_def,y_def",
                   "got every marker at its rest position", "largest displacement 0 mm over 3 markers",
                   "expected markers the experiment's loads displace")


def test_one_marker_that_did_not_move_is_data():
    """A marker by the clamped edge may well stay put: only all of them at rest is refused."""
    from stitchplan.calibration.inputs import check_displacements

    rest = np.array([[99.0, 30.0], [10.0, 10.0]])
    check_displacements(rest, rest + [[0.0, 0.0], [0.5, 0.2]], np.array([2, 3]), 100.0, "markers.csv")


# --- moduli on a bound of their search range ----------------------------------------------


def test_a_modulus_fitted_on_its_bound_is_not_identified(tmp_path):
    """Noise-free markers of lame_mu 0.1477 MPa fitted within [0.01, 0.1]: the fit ends on
    0.1, which is no estimate (the best fit lies beyond), so no uncertainties either."""
    path = write_calibration(tmp_path, [LOADS["left-pull"]], fit={**FIT, "lame_mu": [0.01, 0.1]})
    result = calibration.fit_material(calibration.load_material_calibration(path))
    assert result.lame_mu == pytest.approx(0.1)
    assert result.identifiable is False
    assert result.standard_uncertainty == (None, None)
    bound = [w for w in result.warnings if w.startswith("lame_mu = 0.1 MPa lies on the high bound")]
    assert bound and "not identified" in bound[0] and "raise fit.lame_mu[1] (up to 1e+06 MPa)" in bound[0]


def test_markers_against_the_loads_fit_the_stiffest_material_and_are_not_identified(tmp_path):
    """Markers displaced opposite to what the loads do: every softer material fits worse, the
    fit ends on 1e6 MPa, the largest a range may reach, and must not advise widening it."""
    path = write_calibration(tmp_path, [LOADS["left-pull"]],
                             fit={**FIT, "lame_lambda": [0.01, 1e6], "lame_mu": [0.01, 1e6]})
    markers = tmp_path / "markers0.csv"
    rows = np.loadtxt(markers, delimiter=",", skiprows=1)
    rows[:, 2:] = 2 * rows[:, :2] - rows[:, 2:]  # the displacements reversed
    markers.write_text("x,y,x_def,y_def\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in rows))
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out)
    assert result.exit_code == 0, result.output
    fit = yaml.safe_load(out.read_text())["fit"]
    assert fit["identifiable"] is False
    assert fit["standard_uncertainty"] == {"lame_lambda": None, "lame_mu": None}
    bound = [w for w in fit["warnings"] if "bound of its search range" in w]
    assert len(bound) == 2
    for warning in bound:
        assert "no search may go past 1e+06 MPa" in warning
        assert "widen" not in warning and "raise" not in warning


@pytest.mark.parametrize("fitted, ranges, advice", [
    ((2.0, 0.15), ((0.01, 2.0), (0.01, 2.0)), "raise fit.lame_lambda[1] (up to 1e+06 MPa)"),
    ((1e6, 0.15), ((0.01, 1e6), (0.01, 2.0)), "no search may go past 1e+06 MPa"),
    ((0.2, 0.01), ((0.01, 2.0), (0.01, 2.0)), "lower fit.lame_mu[0] (down to 1e-06 MPa)"),
    ((0.2, 1e-6), ((0.01, 2.0), (1e-6, 2.0)), "no search may go below 1e-06 MPa"),
    ((0.01, 0.15), ((0.01, 2.0), (0.01, 2.0)), "lower fit.lame_lambda[0] (down to 0 MPa)"),
    # the least squares ends a fit pressing on 0 at a few 1e-14 MPa, not at 0
    ((5e-14, 0.15), ((0.0, 2.0), (0.01, 2.0)), "a negative lame_lambda (Poisson's ratio below 0) is no tissue's"),
])
def test_the_bound_advice_stays_within_the_moduli_a_range_may_reach(fitted, ranges, advice):
    fit = FitSettings("saint-venant-kirchhoff", *ranges)
    stats = Statistics((0.01, 0.01), 0.1, 0.01)  # well determined, but for the bound
    warnings = fit_warnings(np.array(fitted), stats, fit, Refinement(SimpleNamespace(status=1, nfev=10), 0), False)
    bound = [w for w in warnings if "bound of its search range" in w]
    assert len(bound) == 1 and "not identified" in bound[0] and advice in bound[0], warnings
    assert "widen" not in bound[0]
    assert not any("poorly determined" in w for w in warnings)  # no estimate to judge


def test_a_fit_inside_its_ranges_stays_identified():
    fit = FitSettings("saint-venant-kirchhoff", (0.0, 2.0), (0.01, 2.0))
    stats = Statistics((0.01, 0.001), 0.1, 0.01)
    refinement = Refinement(SimpleNamespace(status=1, nfev=10), 0)
    assert fit_warnings(np.array([0.19, 0.15]), stats, fit, refinement, False) == []


# --- implausible deformed positions, and forward solves that fail -------------------------


@pytest.mark.parametrize("row, fragments", [
    ("10,20,1e300,20", ["line 4, x_def: got 1e+300", "rest position x = 10 mm"]),
    ("10,20,5000,20", ["line 4, x_def: got 5000", "rest position x = 10 mm"]),
    ("10,20,-500,20", ["line 4, x_def: got -500"]),
    ("10,20,10.5,125", ["line 4, y_def: got 125", "rest position y = 20 mm"]),
])
def test_implausible_deformed_positions_are_refused(tmp_path, row, fragments):
    """1e300 used to end in an unexplained Newton failure (exit 1), 5000 and -500 in a fit."""
    path = marker_calibration(tmp_path, MOVED + row + "\n")
    out = tmp_path / "fitted.yaml"
    result = run("calibrate", "material", path, "--out", out, "--spacing", 6)
    assert_refused(result, out, f"{path}: experiments[0].markers: {tmp_path / 'markers0.csv'}: ", *fragments,
                   "expected a deformed position within 100 mm (the tissue's size)")


def test_a_displacement_up_to_the_tissue_size_is_accepted(tmp_path):
    problem = calibration.load_material_calibration(marker_calibration(tmp_path, MOVED + "10,20,-90,20\n"))
    assert problem.experiments[0].measured[-1].tolist() == [-90.0, 20.0]


def _one_experiment_problem(tmp_path, measured_shift=None):
    problem = calibration.load_material_calibration(marker_calibration(tmp_path, MOVED))
    if measured_shift is not None:  # past the reader's checks, as a caller of fit_material may
        experiment = problem.experiments[0]
        moved = Experiment(experiment.name, experiment.loads, experiment.load_steps, experiment.markers,
                           experiment.measured + measured_shift, experiment.source)
        problem = type(problem)(problem.tissue, (moved,), problem.fit, problem.discretization,
                                problem.solver, problem.name, problem.source)
    return problem


def test_a_misfit_that_overflows_everywhere_is_one_clear_error(tmp_path):
    """Measured positions near 1e300 make f = inf at every grid point: the grid's best was its
    nan corner, and the refinement's Jacobian there let a Newton failure escape."""
    problem = _one_experiment_problem(tmp_path, np.array([[1e300, 0.0], [0.0, 0.0]]))
    with pytest.raises(InputError) as raised:
        calibration.fit_material(problem)
    message = str(raised.value)
    assert message.startswith(f"{problem.source}: fit: could not evaluate any moduli in lame_lambda [0.01, 2.0], "
                              "lame_mu [0.01, 2.0]")
    counts = re.search(r"failed at the (\d+) stiffest grid points tried, the (\d+) others softer still", message)
    assert counts and int(counts[1]) + int(counts[2]) == 16, message  # the 4 x 4 grid, every point accounted
    assert "in experiments[0] ('left-pull'): the misfit f = inf overflows" in message


def test_forward_solves_failing_everywhere_name_the_experiment(tmp_path, monkeypatch):
    problem = _one_experiment_problem(tmp_path)

    def diverge(self, theta, jacobian=False, quick=False):
        raise SolverDivergence("Newton failed at load step 2 (load fraction 0.1672)")

    monkeypatch.setattr(calibration.ExperimentModel, "predict", diverge)
    with pytest.raises(InputError) as raised:
        calibration.fit_material(problem)
    message = str(raised.value)
    assert "\n" not in message
    assert message.startswith(f"{problem.source}: fit: could not evaluate any moduli in lame_lambda [0.01, 2.0]")
    assert ("the forward model failed at the 1 stiffest grid point tried, the 15 others softer still (not tried), in "
            "experiments[0] ('left-pull'): Newton failed at load step 2 (load fraction 0.1672); expected ranges "
            "where the tissue can carry the loads") in message


def test_forward_solves_failing_at_the_refinement_start_do_not_escape():
    """refine() covered the residual's solve but not the Jacobian's: a start point whose
    forward model fails ended the fit with the solver's exception."""
    problem = SimpleNamespace(fit=FitSettings("saint-venant-kirchhoff", (0.01, 2.0), (0.01, 2.0)),
                              experiments=[SimpleNamespace(markers=np.zeros((2, 2)))])

    class FailingMisfit:
        measured = np.ones((2, 2))

        def evaluate(self, theta, jacobian=False, quick=False):
            raise ForwardFailure("experiments[0]", theta, "Newton failed")

    refinement = refine(FailingMisfit(), problem, (0.1, 0.1), 1.0, lambda *args: None)
    assert refinement.failed_solves >= 1
    assert refinement.solution.x.tolist() == pytest.approx([0.1, 0.1])


def test_a_failed_refinement_point_costs_more_than_the_start():
    """The penalty residual of a failed point is costlier than the start even when the start
    misses the markers by far more than they moved: least squares never accepts it as a step."""
    problem = SimpleNamespace(fit=FitSettings("saint-venant-kirchhoff", (0.01, 2.0), (0.01, 2.0)),
                              experiments=[SimpleNamespace(markers=np.zeros((2, 2)))])
    start_residual = np.full(4, 500.0)  # 500 mm off: far beyond the markers' 1 mm motion

    class SoftFails:
        measured = np.ones((2, 2))

        def evaluate(self, theta, jacobian=False, quick=False):
            if theta[1] < 0.1 - 1e-12:  # softer than the start: no solution
                raise ForwardFailure("experiments[0]", theta, "Newton failed")
            # the misfit falls towards softer materials, luring the steps into the failures
            return start_residual * theta[1] / 0.1, np.tile([0.0, 5000.0], (4, 1)), []

    refinement = refine(SoftFails(), problem, (0.1, 0.1), float(start_residual @ start_residual),
                        lambda *args: None)
    assert refinement.failed_solves >= 1
    assert refinement.solution.x[1] >= 0.1 - 1e-12


# --- numbers in marker files and force recordings ---------------------------------------

PLAIN = "expected a finite number in plain decimals (digits 0-9, like -1.5e-3)"


@pytest.mark.parametrize("cell, problem", [
    ("1_0", f"got '1_0', {PLAIN}"),  # float() reads 10
    ("\u0661\u0660.\u0665", f"got '\u0661\u0660.\u0665', {PLAIN}"),  # Arabic-Indic digits: float() reads 10.5
    ("0x10", f"got '0x10', {PLAIN}"),
    ("nan", "got 'nan', expected a finite number"),
    ("-Infinity", "got '-Infinity', expected a finite number"),
    ("1e999", "got '1e999', expected a finite number"),
    ("", "missing; expected a finite number"),
])
def test_marker_numbers_are_plain_decimals(tmp_path, cell, problem):
    path = marker_calibration(tmp_path, MOVED + f"10,20,{cell},20\n")
    with pytest.raises(InputError) as raised:
        calibration.load_material_calibration(path)
    assert str(raised.value) == (f"{path}: experiments[0].markers: {tmp_path / 'markers0.csv'}: line 4, x_def: "
                                 f"{problem}")


@pytest.mark.parametrize("cell", ["1_0", "\u0661.\u0665"])
def test_force_recording_numbers_are_plain_decimals(tmp_path, cell):
    air, tissue = write_recordings(tmp_path)
    lines = tissue.read_text().splitlines()
    lines[3] = lines[3].split(",")[0] + "," + cell
    tissue.write_text("\n".join(lines) + "\n")
    out = tmp_path / "needle.yaml"
    result = run("calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", RADIUS, "--out", out)
    assert_refused(result, out, f"--tissue: {tissue}: line 4, force_N: got {cell!r}, {PLAIN}")


def test_marker_files_skip_a_spreadsheets_blank_rows_and_need_a_row(tmp_path):
    """Read as the centre path files are: a ',,,' row is a blank line, a header alone is no data."""
    path = marker_calibration(tmp_path, "10,10,10.5,10.2\n,,,\n50,30,50.3,30.1\n")
    assert len(calibration.load_material_calibration(path).experiments[0].markers) == 2
    markers = tmp_path / "markers0.csv"
    markers.write_text("x,y,x_def,y_def\n,,,\n")
    with pytest.raises(InputError) as error:
        calibration.load_material_calibration(path)
    assert error.value.lines == [(f"{path}: experiments[0].markers: {markers}: no rows below the header; "
                                  "expected marker positions at rest and deformed, mm")]


def test_one_marker_file_in_two_experiments_is_refused(tmp_path):
    """The same photographs counted twice would halve the stated scatter of the fit."""
    path = marker_calibration(tmp_path, MOVED)
    data = yaml.safe_load(path.read_text())
    data["experiments"].append({**data["experiments"][0], "name": "copy"})
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError) as raised:
        calibration.load_material_calibration(path)
    assert str(raised.value) == (f"{path}: experiments[1].markers: got {tmp_path / 'markers0.csv'}, the markers of "
                                 "experiments[0] again; expected each experiment's own marker file (its loads move "
                                 "the markers differently)")


def test_a_copy_of_one_experiments_markers_under_another_name_is_refused(tmp_path):
    """The same file under another name says the same photographs (it was accepted: only the
    same path was refused)."""
    path = marker_calibration(tmp_path, MOVED)
    (tmp_path / "copy.csv").write_bytes((tmp_path / "markers0.csv").read_bytes())
    data = yaml.safe_load(path.read_text())
    data["experiments"].append({**data["experiments"][0], "name": "copy", "markers": "copy.csv"})
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError) as raised:
        calibration.load_material_calibration(path)
    assert str(raised.value) == (f"{path}: experiments[1].markers: got {tmp_path / 'copy.csv'}, the same rest and "
                                 f"measured positions as experiments[0]'s {tmp_path / 'markers0.csv'}; expected each "
                                 "experiment's own markers (its loads move the markers differently)")
