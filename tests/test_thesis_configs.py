"""configs/thesis/: the thesis's simulation scenes (table 5.1, section 5.1.1, figures 5.9-5.10)
load, state the thesis's parameters under the documented readings, and have a valid needle
geometry with the desired exit the comments describe. No runs here: the results are
benchmarks/thesis_table.py's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stitchplan.config.scenario import load_scenario
from stitchplan.needle.geometry import scenario_needle

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
    law for all four blocks (cut from one phantom), entry at mid-height + r."""
    scenario = load_scenario(THESIS / f"table51_100x{height:g}.yaml")
    tissue, needle = scenario.tissue, scenario.needle
    assert tissue.size == (100.0, height)
    assert tissue.thickness == 2.76 and tissue.material.model == "neo-hookean"
    assert (tissue.material.lame_lambda, tissue.material.lame_mu) == (0.189151, 0.147688)
    assert (needle.radius, needle.step, needle.friction, needle.cutting_force) == (8.88, 0.08, 0.0602, 0.7)
    assert needle.turn == "cw" and needle.arc == pytest.approx(math.pi)
    geometry = scenario_needle(scenario)
    np.testing.assert_allclose(geometry.center, [0.0, height / 2], atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit, [0.0, height / 2 - 8.88], atol=1e-9)
    assert geometry.exit_rotation == pytest.approx(math.pi)


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
