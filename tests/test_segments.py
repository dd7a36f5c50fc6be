"""Load segments act on exactly the segment given, whatever the spacing, and `deform`
converges at the smooth-solution rate although the solution is singular at the segment ends.

Every segment end is a particle (grid lines through the ends), the particles are graded
toward the ends inside an edge (stitchplan.tissue.particles.end_zones), force segments are
integrated over exactly their length, and displacement segments are held at every particle
on them by the transformation method. benchmarks/deform_segments.py compares the same
treatment with scikit-fem on the 100 x 60 mm slab.
"""

from __future__ import annotations

import numpy as np
import pytest

from stitchplan.config.scenario import parse_scenario
from stitchplan.geometry.segments import on_segment
from stitchplan.tissue.deform import external_forces, interpolate, run_deform
from stitchplan.tissue.model import model_for_scenario

ALIGNED = (4.0, 8.0)  # on the grid lines of spacings 2, 1, 0.5 (and 4 / 3 of them)
UNALIGNED = (4.3, 7.9)  # ends between the grid lines of every spacing used here


def slab(kind: str, span: tuple[float, float], value, spacing: float, load_steps: int = 1,
         probes=((0.0, 2.0), (0.0, 10.0), (2.0, 6.1), (5.0, 2.0), (8.0, 8.0))):
    """A 12 x 12 mm slab of the phantom material clamped on the right, loaded on the left edge."""
    raw = {"tissue": {"size": [12.0, 12.0], "thickness": 10.0, "clamped": ["right"],
                      "material": {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151,
                                   "lame_mu": 0.147688}},
           "loads": [{"segment": [[0.0, span[0]], [0.0, span[1]]], kind: list(value)}],
           "load_steps": load_steps, "probes": [list(p) for p in probes],
           "discretization": {"spacing": spacing}}
    return parse_scenario(raw)


@pytest.mark.parametrize("span", [ALIGNED, UNALIGNED])
@pytest.mark.parametrize("spacing", [2.0, 1.0])
def test_segment_ends_are_particles_and_held_particles_cover_exactly_the_segment(span, spacing):
    model = model_for_scenario(slab("displacement", span, (-0.5, 0.3), spacing))
    held = model.particles[model.boundary.indices[model.boundary.group == 0]]
    assert np.allclose(held[:, 0], 0.0, atol=0.0)
    assert held[:, 1].min() == pytest.approx(span[0], abs=1e-12)
    assert held[:, 1].max() == pytest.approx(span[1], abs=1e-12)
    # and every particle on the segment is held
    on = on_segment(model.particles, (0.0, span[0]), (0.0, span[1]), 1e-9)
    assert on.sum() == len(held)


def test_prescribed_displacement_holds_at_the_ends_and_between_particles():
    """u = g to round-off at the segment's ends and at every particle on it. Between particles
    the transformation method (eq. 3.24-3.38) does not collocate g: u - g there is the RK
    interpolation error of a field that is singular just outside the segment, largest in the
    first interval next to each end. Measured max |u - g| / |g| over 201 points: 2.1 % at
    spacing 2 mm, 1.0 % at 1 mm, 0.49 % at 0.6 mm (halving with the spacing). Asserted: at
    most 2.5 % at 2 mm and at least a factor 1.6 smaller at 1 mm."""
    g = np.array([-1.6, 1.2])
    deviations = []
    for spacing in (2.0, 1.0):
        result = run_deform(slab("displacement", UNALIGNED, g, spacing, load_steps=2))
        model = result.model
        held = model.particles[model.boundary.indices[model.boundary.group == 0]]
        ends = np.array([[0.0, UNALIGNED[0]], [0.0, UNALIGNED[1]]])
        at_particles = interpolate(model, result.coefficients, np.vstack([ends, held]))
        np.testing.assert_allclose(at_particles, np.broadcast_to(g, at_particles.shape), rtol=0.0, atol=1e-10)
        along = np.column_stack([np.zeros(201), np.linspace(*UNALIGNED, 201)])  # incl. the midpoint
        deviation = np.linalg.norm(interpolate(model, result.coefficients, along) - g, axis=1).max()
        deviations.append(deviation / np.linalg.norm(g))
    assert deviations[0] <= 0.025
    assert deviations[1] <= deviations[0] / 1.6


@pytest.mark.parametrize("span", [ALIGNED, UNALIGNED])
def test_force_segment_acts_on_exactly_its_length(span):
    """sum_I f_I = F and sum_I f_I X_I = F x (segment midpoint) to round-off: the quadrature
    covers exactly the segment (partition of unity and linear reproduction of the RK
    functions turn both sums into integrals of h0 and h0 X over it)."""
    force = np.array([-3.0, 1.0])
    scenario = slab("force", span, force, 1.0)
    model = model_for_scenario(scenario)
    forces = external_forces(model, scenario)  # (NP, 2)
    np.testing.assert_allclose(forces.sum(axis=0), force, rtol=0.0, atol=1e-12)
    midpoint = np.array([0.0, 0.5 * (span[0] + span[1])])
    np.testing.assert_allclose(forces.T @ model.particles, np.outer(force, midpoint), rtol=0.0, atol=1e-11)


def test_aligned_and_unaligned_segments_converge_to_their_own_lengths():
    """An unaligned segment is not snapped to the grid: at two spacings its solution differs
    from the aligned segment's by the same amount (the length difference), while the
    discretization changes each by much less."""
    probes = ((2.0, 6.1), (5.0, 2.0))
    results = {(span, h): run_deform(slab("force", span, (-3.0, 1.0), h, probes=probes)).probe_displacements
               for span in (ALIGNED, UNALIGNED) for h in (2.0, 1.0)}
    gap_coarse = results[(ALIGNED, 2.0)] - results[(UNALIGNED, 2.0)]
    gap_fine = results[(ALIGNED, 1.0)] - results[(UNALIGNED, 1.0)]
    scale = np.abs(results[(ALIGNED, 1.0)]).max()
    assert np.abs(gap_fine).max() > 1e-3 * scale  # the two segments do differ
    assert np.abs(gap_coarse - gap_fine).max() < 0.1 * np.abs(gap_fine).max()


def test_displacement_segment_converges_at_rate_1_5_or_better():
    """Max probe error against a run at half the finest spacing, at spacings 2.4, 1.2 and
    0.6 mm (the default, min(W, H)/20); measured slope 1.87 (errors 4.0, 1.6, 0.30 %). With
    segment_end_levels 0 (particles uniform at the singular segment ends) the errors against
    that model's own 0.3 mm run are 10.8, 4.0 and 1.25 %. The same treatment against
    scikit-fem on the 100 x 60 mm slab: benchmarks/results/deform_segments.md."""
    spacings = (2.4, 1.2, 0.6)
    values = {h: run_deform(slab("displacement", UNALIGNED, (-0.3, 0.2), h)).probe_displacements
              for h in (*spacings, 0.3)}
    reference = values[0.3]
    errors = [np.linalg.norm(values[h] - reference, axis=1).max() / np.linalg.norm(reference, axis=1).max()
              for h in spacings]
    assert errors[0] > errors[1] > errors[2]
    slope = np.polyfit(np.log(spacings), np.log(errors), 1)[0]
    assert slope >= 1.5, (errors, slope)


def test_end_grading_refines_only_around_the_segment_ends_and_can_be_switched_off():
    """With segment_end_levels 0 the particles are the tensor grid through the segment ends;
    by default the extra particles all sit near the two ends (within the graded zone)."""
    from dataclasses import replace

    scenario = slab("force", UNALIGNED, (-3.0, 1.0), 1.0)
    plain = replace(scenario, discretization=scenario.discretization.replaced(segment_end_levels=0))
    grid = model_for_scenario(plain).particles
    graded = model_for_scenario(scenario).particles
    lines_y = np.unique(grid[:, 1])
    assert len(grid) == len(np.unique(grid[:, 0])) * len(lines_y)
    assert {UNALIGNED[0], UNALIGNED[1]} <= set(np.round(lines_y, 12))
    assert len(graded) > len(grid)
    extra = graded[~(graded[:, None, :] == grid[None]).all(axis=2).any(axis=1)]
    ends = np.array([[0.0, UNALIGNED[0]], [0.0, UNALIGNED[1]]])
    assert np.min(np.linalg.norm(extra[:, None] - ends[None], axis=2), axis=1).max() < 4.0


def test_graded_lattice_balance_filter_matches_the_3x3_maximum_filter():
    """The 2:1 balance of the graded lattice takes each cell's 3 x 3 neighbourhood maximum
    (edges repeated) in numpy; it equals scipy.ndimage's maximum filter in 'nearest' mode."""
    from scipy.ndimage import maximum_filter

    from stitchplan.tissue.particles import _neighbourhood_max

    rng = np.random.default_rng(3)
    for shape in [(1, 1), (1, 6), (5, 3), (24, 17)]:
        levels = rng.integers(0, 6, shape)
        np.testing.assert_array_equal(_neighbourhood_max(levels), maximum_filter(levels, size=3, mode="nearest"))


def test_a_zone_is_refined_to_its_own_level_where_the_coarse_cells_are_a_little_wider():
    """Coarse cells 4 % wider than the base (grid lines fitted to a 10.4 mm edge) would ask a
    half-spacing zone for a quarter-spacing leaf (ceil(log2(1.04 / 0.5)) = 2) whenever a
    finer zone makes that level exist: each zone stops at its own level, so the disk's leaves
    stay half the coarse side while the point zone's go on to an eighth."""
    from stitchplan.tissue.particles import RefinementZone, graded_lattice

    disk = RefinementZone(np.array([3.0, 5.0]), 1.5, 0.5)
    point = RefinementZone(np.array([9.0, 2.0]), 0.0, 0.125)
    alone = graded_lattice((10.4, 10.0), 1.0, (disk,))
    together = graded_lattice((10.4, 10.0), 1.0, (disk, point))
    cells = together.cells
    sides = np.maximum(cells[:, 2], cells[:, 3])
    centres = cells[:, :2] + 0.5 * cells[:, 2:]
    in_disk = np.hypot(*(centres - disk.center).T) <= disk.radius
    assert np.allclose(sides[in_disk], 0.52)  # 1.04 / 2: the disk's own level, not 0.26
    assert np.isclose(sides.min(), 0.13)  # the point's three levels
    alone_sides = np.maximum(alone.cells[:, 2], alone.cells[:, 3])
    alone_centres = alone.cells[:, :2] + 0.5 * alone.cells[:, 2:]
    assert np.allclose(alone_sides[np.hypot(*(alone_centres - disk.center).T) <= disk.radius], 0.52)
