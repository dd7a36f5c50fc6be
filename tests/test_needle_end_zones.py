"""Particles graded toward the needle's entry and exit (discretization.needle_end_levels,
stitchplan.needle.geometry.needle_end_zones): the leaf side there falls one level per
halving of the spacing, and level 0 leaves the needle zone as it was."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stitchplan.config.scenario import load_scenario, with_discretization
from stitchplan.needle.geometry import needle_zone, scenario_needle
from stitchplan.resources.model_size import model_size
from stitchplan.tissue.model import model_for_scenario

from conftest import CONFIGS


def _scene(levels: int, factor: float = 1.0):
    base = load_scenario(CONFIGS / "needle20_entry30.yaml")
    base = with_discretization(base, spacing=base.discretization.spacing * factor)
    return replace(base, discretization=base.discretization.replaced(needle_end_levels=levels))


def _spacing_at(model, point) -> float:
    """The local particle spacing (support / dilation) of the particle nearest `point`."""
    nearest = int(np.argmin(np.linalg.norm(model.particles - point, axis=1)))
    return float(model.support[nearest]) / 2.0


@pytest.mark.parametrize("levels", [1, 2])
def test_the_exit_spacing_falls_one_level_per_halving(levels):
    spacings = []
    for factor in (1.0, 0.5):
        scenario = _scene(levels, factor)
        exit_point = scenario_needle(scenario).desired_exit
        model = model_for_scenario(scenario, needle_zone(scenario))
        needle = scenario.discretization.needle_spacing
        spacings.append(_spacing_at(model, exit_point))
        assert spacings[-1] == pytest.approx(needle / 2 ** (levels + (factor == 0.5)), rel=0.2)
        assert model_size(scenario).particles == model.n_particles  # the guard counts them
    assert spacings[1] / spacings[0] == pytest.approx(0.25, rel=0.2)  # spacing^2


def test_level_zero_leaves_the_needle_zone_as_it_was():
    plain, graded = _scene(0), _scene(2)
    assert needle_zone(plain)[2] == ()
    zones = needle_zone(graded)[2]
    assert len(zones) >= 1 and min(z.spacing for z in zones) < graded.discretization.needle_spacing
    coarse = model_for_scenario(plain, needle_zone(plain))
    fine = model_for_scenario(graded, needle_zone(graded))
    exit_point = scenario_needle(graded).desired_exit
    assert _spacing_at(coarse, exit_point) == pytest.approx(plain.discretization.needle_spacing, rel=0.2)
    assert fine.n_particles > coarse.n_particles


def test_the_end_zones_leave_the_needle_zone_as_it_was():
    """At 1/sqrt(2) of the default spacing the coarse cells are rounded a little larger than
    the lattice base; the end zones' extra levels must not refine the whole needle disk one
    level further (it did: +1 075 particles on this scene), only the entry and exit."""
    plain, graded = _scene(0, 2 ** -0.5), _scene(2, 2 ** -0.5)
    coarse = model_for_scenario(plain, needle_zone(plain)).n_particles
    fine = model_for_scenario(graded, needle_zone(graded)).n_particles
    assert 0 < fine - coarse < 0.15 * coarse
