"""configs/thesis/: the thesis's simulation scenes (table 5.1, section 5.1.1, figures 5.9-5.10)
load, state the thesis's parameters under the documented readings, and have a valid needle
geometry with the desired exit the comments describe, and the table 5.1 reading converges on
its slowest block. The results are benchmarks/thesis_table.py's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stitchplan.config.scenario import load_scenario, with_discretization
from stitchplan.needle.geometry import scenario_needle
from stitchplan.needle.insertion import run_insertion
from stitchplan.planning.move_limits import center_moves

THESIS = Path(__file__).resolve().parent.parent / "configs" / "thesis"
TABLE51_HEIGHTS = (100.0, 50.0, 40.0, 30.0)
SECTION511_ENTRIES = (30.0, 25.0, 20.0, 18.0)


def test_every_thesis_config_loads_with_a_valid_needle_and_a_stated_reading():
    paths = sorted(THESIS.glob("*.yaml"))
    assert len(paths) == len(TABLE51_HEIGHTS) + len(SECTION511_ENTRIES) + 1
    for path in paths:
        scenario = load_scenario(path)
        geometry = scenario_needle(scenario)  # raises InputError if the needle cannot enter/exit
        assert 2 * geometry.step <= geometry.exit_rotation <= geometry.arc
        assert scenario.tissue.domain.edges_at(tuple(geometry.desired_exit)), path.name
        assert scenario.tissue.clamped == ("right",)
        # each file says how it reads the thesis's unstated thickness and units
        assert "thickness" in scenario.source_text and "Reading" in scenario.source_text, path.name


@pytest.mark.parametrize("height", TABLE51_HEIGHTS)
def test_table51_blocks_share_one_reading_and_a_symmetric_stitch(height):
    """Table 5.1: the SH 1/2 needle and section 5.2's identified parameters, one thickness and
    law for all four blocks (cut from one phantom), entry at mid-height + r, the SH 1/2
    files' discretization."""
    scenario = load_scenario(THESIS / f"table51_100x{height:g}.yaml")
    tissue, needle = scenario.tissue, scenario.needle
    assert tissue.size == (100.0, height)
    assert tissue.thickness == 5.0 and tissue.material.model == "neo-hookean"
    # discretized for the needle as the same blocks 10 mm thick (configs/sh12_*.yaml)
    sh12 = load_scenario(THESIS.parent / "sh12_100x40.yaml")
    assert scenario.discretization == sh12.discretization
    assert needle.cutting_ramp == sh12.needle.cutting_ramp
    assert needle.multiplier_length == sh12.needle.multiplier_length
    assert (tissue.material.lame_lambda, tissue.material.lame_mu) == (0.189151, 0.147688)
    assert (needle.radius, needle.step, needle.friction, needle.cutting_force) == (8.88, 0.08, 0.0602, 0.7)
    assert needle.turn == "cw" and needle.arc == pytest.approx(math.pi)
    geometry = scenario_needle(scenario)
    np.testing.assert_allclose(geometry.center, [0.0, height / 2], atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit, [0.0, height / 2 - 8.88], atol=1e-9)
    assert geometry.exit_rotation == pytest.approx(math.pi)


def test_the_table51_reading_converges_on_the_narrowest_block():
    """The thickness was chosen so that every block converges (benchmarks/thesis_table.md's
    sweep): the 100 x 30 block, the slowest, changes its unplanned exit error by less than 2 %
    from the file's spacing to half of it, with the changes over h, h/sqrt2, h/2 shrinking
    (observed 1.790, 1.806, 1.813 mm; at the 2.76 mm read before, +9 % and on to a run that
    stops at h/4)."""
    scenario = load_scenario(THESIS / "table51_100x30.yaml")
    spacing = scenario.discretization.spacing
    errors = [run_insertion(with_discretization(scenario, spacing=spacing * factor)).exit_error_mm
              for factor in (1.0, 1 / math.sqrt(2.0), 0.5)]
    changes = np.diff(errors)
    assert abs(errors[2] - errors[0]) < 0.02 * errors[0]
    assert changes[0] * changes[1] > 0 and abs(changes[1]) < abs(changes[0])


@pytest.mark.parametrize("entry_y", SECTION511_ENTRIES)
def test_section511_scenes_read_the_moduli_in_n_per_cm2(entry_y):
    """Section 5.1.1 (figures 5.1-5.9): r = 20 mm, step 0.1 rad, friction 0.02 N/mm, threshold
    0.03 N; lambda 9.263 and mu 1.029 read as N/cm^2 (x 0.01 MPa) with unit thickness 1 cm;
    neo-Hookean, as table 5.1's blocks, because Saint Venant-Kirchhoff collapses in front of
    the tip when refined at this softness."""
    scenario = load_scenario(THESIS / f"needle20_entry{entry_y:g}.yaml")
    tissue, needle = scenario.tissue, scenario.needle
    assert tissue.size == (100.0, 100.0) and tissue.thickness == 10.0
    assert tissue.material.model == "neo-hookean"
    assert tissue.material.lame_lambda == pytest.approx(9.263e-2, rel=1e-12)
    assert tissue.material.lame_mu == pytest.approx(1.029e-2, rel=1e-12)
    assert (needle.radius, needle.step, needle.friction, needle.cutting_force) == (20.0, 0.1, 0.02, 0.03)
    assert needle.entry == (0.0, entry_y) and needle.turn == "cw"
    geometry = scenario_needle(scenario)
    # centre (0, y - 20); the circle first leaves through the bottom edge
    np.testing.assert_allclose(geometry.center, [0.0, entry_y - 20.0], atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit,
                               [math.sqrt(400.0 - (entry_y - 20.0) ** 2), 0.0], atol=1e-9)


def test_figure510_enters_the_top_edge_and_exits_the_free_left_edge():
    scenario = load_scenario(THESIS / "needle20_fig510.yaml")
    reference = load_scenario(THESIS / "needle20_entry30.yaml")
    assert scenario.tissue == reference.tissue
    geometry = scenario_needle(scenario)
    assert geometry.entry_edge == "top"
    np.testing.assert_allclose(geometry.center, [0.0, 100.0], atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit, [0.0, 80.0], atol=1e-9)


def test_figure510_plan_leans_the_needle_and_verifies_within_the_move_limits(tmp_path):
    """Figure 5.10's soft free edge carries the desired exit further than the move limits let
    the centre follow (upright: planned 2.5 mm off, README "Reproducing the thesis"); leaning
    the needle at entry (planner.aim_entry_tilt in the file), `plan` verifies its trajectory
    on the refined model within 0.01 mm with every centre move within the limits."""
    import json

    from typer.testing import CliRunner

    from stitchplan.cli import app

    summary = tmp_path / "summary.json"
    result = CliRunner().invoke(app, ["plan", str(THESIS / "needle20_fig510.yaml"), "--export",
                                      str(tmp_path / "t.csv"), "--summary", str(summary)])
    assert result.exit_code == 0, result.output
    plan = json.loads(summary.read_text())
    scale = 0.1 / 0.08  # the limits are stated per 0.08 rad; the file's step is 0.1 rad
    # the limits hold on the numbers a robot reads: the exported centres, rounded to 1e-9 mm
    table = np.genfromtxt(tmp_path / "t.csv", delimiter=",", names=True)
    moves, second = center_moves(np.column_stack([table["center_x_mm"], table["center_y_mm"]]))
    assert moves.max() == plan["max_center_step_mm"] <= 0.28 * scale
    assert second.max() == plan["max_center_second_difference_mm"] <= 0.14 * scale
    assert moves.max() > 0.28 * scale - 1e-6  # the limit was reached: the test tells
    assert plan["verified_exit_error_mm"] <= 0.01 and plan["verification_spacing_mm"] == 1.25
    assert plan["unplanned_exit_error_mm"] > 4.0
    assert 0.0 < plan["needle_entry_tilt_rad"] <= 0.35
