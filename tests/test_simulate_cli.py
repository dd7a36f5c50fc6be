"""`stitchplan simulate` on real files in tmp_path: the summary JSON (every key of the format),
the HDF5 run log, the PNG, the options that reach the simulation, and bad needle geometry
ending in one error line, exit code 2 and no output."""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

import stitchplan
from stitchplan.cli import app
from stitchplan.needle.newton import NEWTON_TOLERANCES

TRACK_TOLERANCE = NEWTON_TOLERANCES["mortar"][1] * 8.0  # |g| <= tolerance x R, R = 8 mm here

SUMMARY_KEYS = ("desired_exit", "desired_exit_def", "achieved_exit_def", "achieved_exit", "exit_error_mm",
                "exit_error_material_mm", "steps", "particles", "wall_seconds")


def scene_raw(**needle) -> dict:
    """40 x 30 mm phantom block, 8 mm needle from (0, 22) turning cw in 0.2 rad steps, 5 mm
    spacing (63 particles): a whole insertion in well under a second."""
    return {"name": "cli-small",
            "tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                       "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
            "discretization": {"spacing": 5.0},
            "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2,
                       "friction": 0.0602, "cutting_force": 0.7, **needle}}


def invoke(*args):
    return CliRunner().invoke(app, ["simulate", *map(str, args)])


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """One `simulate` run with every output; returns (folder, scenario path, CLI result)."""
    import yaml

    folder = tmp_path_factory.mktemp("simulate")
    scenario = folder / "scene.yaml"
    scenario.write_text("# small scene for the CLI test\n" + yaml.safe_dump(scene_raw(), sort_keys=False))
    result = invoke(scenario, "--out", folder / "run.h5", "--summary", folder / "summary.json",
                    "--plot", folder / "run.png", "--plot-steps", "3,7")
    return folder, scenario, result


def test_simulate_summary_has_every_contract_key(simulated):
    folder, _, result = simulated
    assert result.exit_code == 0, result.output
    assert result.output.startswith("simulate: 15 steps, 63 particles, exit error")
    summary = json.loads((folder / "summary.json").read_text())
    for key in SUMMARY_KEYS:
        assert key in summary, key
    for key in ("desired_exit", "desired_exit_def", "achieved_exit_def", "achieved_exit"):
        assert len(summary[key]) == 2 and all(math.isfinite(v) for v in summary[key])
    np.testing.assert_allclose(summary["desired_exit"], [0.0, 6.0], atol=1e-9)
    assert summary["exit_error_mm"] == pytest.approx(
        np.hypot(*np.subtract(summary["achieved_exit_def"], summary["desired_exit_def"])), rel=1e-12)
    assert summary["exit_error_material_mm"] == pytest.approx(
        np.hypot(*np.subtract(summary["achieved_exit"], summary["desired_exit"])), rel=1e-12)
    assert summary["steps"] == 15 and summary["particles"] == 63
    # the printed line carries the summary's discretization error estimate
    assert f"discretization error estimate {summary['exit_error_estimate_mm']:.4f} mm" in result.output
    assert 0.0 < summary["wall_seconds"] < 600.0
    assert abs(summary["achieved_exit"][0]) <= 1e-9  # out through the left edge
    assert summary["max_constraint_violation_mm"] <= TRACK_TOLERANCE  # converged
    assert (summary["solver"]["needle_residual_tolerance"], summary["solver"]["needle_constraint_tolerance"]) == (
        NEWTON_TOLERANCES["mortar"])


def test_simulate_writes_the_run_log(simulated):
    folder, scenario, _ = simulated
    with h5py.File(folder / "run.h5") as run:
        assert run.attrs["stitchplan_version"] == stitchplan.__version__
        assert run.attrs["command"] == "simulate" and run.attrs["scenario_name"] == "cli-small"
        text = run["scenario/text"][()]
        assert (text.decode() if isinstance(text, bytes) else text) == scenario.read_text()
        steps = run["steps"]
        for name in ("step", "rotation", "needle_points", "newton_iterations", "constraint_violation",
                     "insertion_force", "friction_force", "cutting_force", "minres_iterations"):
            assert steps[name].shape == (15,), name
        for name in ("center", "needle_tip", "tip_reference", "tip_spatial", "exit_displacement"):
            assert steps[name].shape == (15, 2), name
        np.testing.assert_array_equal(steps["step"][:], np.arange(1, 16))
        np.testing.assert_allclose(steps["rotation"][:], 0.2 * np.arange(1, 16), atol=1e-12)
        assert np.all(steps["constraint_violation"][:] <= TRACK_TOLERANCE)
        assert np.all(np.diff(steps["insertion_force"][:]) > 0)  # friction grows with the length
        assert run["particles/displacement"].shape == (16, 63, 2)  # rest + one state per step
        assert run["needle/trajectory_reference"].shape == (16, 2)


def test_simulate_writes_the_plot(simulated):
    folder, _, _ = simulated
    png = (folder / "run.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_simulate_options_reach_the_simulation(tmp_path, write_scenario):
    """--linear-solver minres, --tip-tracking auto, --condition-numbers and --spacing."""
    scenario = write_scenario(scene_raw(), "scene.yaml")
    summary, run = tmp_path / "summary.json", tmp_path / "run.h5"
    result = invoke(scenario, "--summary", summary, "--out", run, "--linear-solver", "minres",
                    "--tip-tracking", "auto", "--condition-numbers", "--spacing", "8")
    assert result.exit_code == 0, result.output
    data = json.loads(summary.read_text())
    # one factorization: K0's, for MINRES's preconditioner (its backend recorded, none of K + H)
    assert data["minres_iterations"] > 0 and data["solver"]["factorizations"] == 1
    assert data["solver"]["linear_solver_backends"] == [data["solver"]["linear_solver_backend"]]
    assert data["tip_tracking"] == ["inverse-gradient"]
    assert data["discretization"]["spacing_mm"] == pytest.approx(8.0)
    assert data["discretization"]["requested_spacing_mm"] == 8.0
    with h5py.File(run) as handle:
        saddle = handle["steps/condition_saddle"][:]
        preconditioned = handle["steps/condition_preconditioned"][:]
    assert np.all(np.isfinite(saddle)) and np.all(np.isfinite(preconditioned))
    assert np.all(preconditioned < saddle)  # the block preconditioner helps at every step


def test_summary_gives_the_spacing_asked_for_beside_the_one_placed(tmp_path, write_scenario):
    """A spacing that does not divide the tissue's size: the particles are fitted to it (a
    whole number of spacings across), the summary keeps both."""
    scenario = write_scenario(scene_raw(), "scene.yaml")
    summary = tmp_path / "summary.json"
    result = invoke(scenario, "--summary", summary, "--spacing", "7.7", "--no-estimate")
    assert result.exit_code == 0, result.output
    discretization = json.loads(summary.read_text())["discretization"]
    assert discretization["requested_spacing_mm"] == 7.7
    assert discretization["spacing_mm"] != pytest.approx(7.7) and abs(discretization["spacing_mm"] - 7.7) < 1.0


@pytest.mark.parametrize("entry,fragment", [
    ([10.0, 22.0], "needle.entry: got [10.0, 22.0], expected a point on the boundary of the 40 x 30 mm tissue"),
    ([0.0, 30.0], "needle.entry: got [0.0, 30.0], a corner"),
])
def test_bad_needle_geometry_is_one_error_line_and_no_output(tmp_path, write_scenario, entry, fragment):
    scenario = write_scenario(scene_raw(entry=entry), "bad.yaml")
    outputs = [tmp_path / "run.h5", tmp_path / "summary.json", tmp_path / "run.png"]
    result = invoke(scenario, "--out", outputs[0], "--summary", outputs[1], "--plot", outputs[2])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0]
    assert "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]


def test_vci_integration_is_refused_for_the_needle(tmp_path, write_scenario):
    raw = scene_raw()
    raw["discretization"] = {**raw.get("discretization", {}), "integration": "vci"}
    scenario = write_scenario(raw, "scene.yaml")
    result = invoke(scenario, "--summary", tmp_path / "summary.json")
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {scenario}: discretization.integration: got 'vci', expected 'gauss'")
    assert not (tmp_path / "summary.json").exists()


def test_bad_tip_tracking_option_is_refused(tmp_path, write_scenario):
    scenario = write_scenario(scene_raw(), "scene.yaml")
    result = invoke(scenario, "--summary", tmp_path / "summary.json", "--tip-tracking", "newton")
    assert result.exit_code == 2
    assert result.output.strip() == ("error: --tip-tracking: got 'newton', expected one of auto, "
                                     "inverse-gradient, levenberg-marquardt")
    assert not (tmp_path / "summary.json").exists()


SPACING_BOUND = ("expected a positive number of at most 10000 (mm; a spacing beyond 10000 mm, the bound of every "
                 "length of a scene, is a unit mistake)")


@pytest.mark.parametrize("discretization, options, line", [
    ({"spacing": 1e308}, (), "{scenario}: discretization.spacing: got 1e+308, " + SPACING_BOUND),
    ({"spacing": 5.0, "needle_spacing": 2e4}, (), "{scenario}: discretization.needle_spacing: got 20000.0, "
     + SPACING_BOUND),
    ({"spacing": 5.0}, ("--spacing", "1e308"), "--spacing: got 1e+308, " + SPACING_BOUND),
    ({"spacing": 5.0}, ("--spacing", "2e4", "--no-resource-check"), "--spacing: got 20000, " + SPACING_BOUND),
])
def test_a_spacing_beyond_the_scenes_bound_is_refused_naming_its_field(tmp_path, write_scenario, discretization,
                                                                      options, line):
    """A spacing of 1e308 mm passed the file's checks, and its exit error estimate's replay at
    twice it, inf, was refused as `discretization.spacing: got inf`, naming neither the file
    nor the option; a spacing is bounded as every length of a scene is."""
    from stitchplan.cli.options import MAX_SPACING_MM
    from stitchplan.config.blocks import MAX_SCENE_MM

    assert MAX_SPACING_MM == MAX_SCENE_MM
    raw = scene_raw()
    raw["discretization"] = discretization
    scenario = write_scenario(raw, "scene.yaml")
    result = invoke(scenario, "--summary", tmp_path / "summary.json", *options)
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [f"error: {line.format(scenario=scenario)}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def test_a_spacing_below_the_files_needle_spacing_is_refused_naming_the_option_and_file(tmp_path, write_scenario):
    """Refining a file that gives its own needle_spacing past it with --spacing was refused
    as `discretization.needle_spacing: got 2.5, ...`, naming neither the option nor the file."""
    raw = scene_raw()
    raw["discretization"] = {"spacing": 5.0, "needle_spacing": 2.5}
    scenario = write_scenario(raw, "scene.yaml")
    result = invoke(scenario, "--summary", tmp_path / "summary.json", "--spacing", "1.25")
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        f"error: --spacing 1.25 over {scenario}: discretization.needle_spacing: got 2.5, expected a spacing (mm) "
        "no larger than spacing = 1.25 mm"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def test_a_spacing_at_the_scenes_bound_is_still_taken(write_scenario):
    raw = scene_raw()
    raw["discretization"] = {"spacing": 1e4, "needle_spacing": 1e4}
    scenario = write_scenario(raw, "scene.yaml")
    from stitchplan.config.scenario import load_scenario

    assert load_scenario(scenario).discretization.spacing == 1e4
