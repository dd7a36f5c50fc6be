"""The mortar needle coupling (needle/coupling.py) on small scenes:

- its multiplier elements: whole track segments, each at least the local particle spacing
  long, no more multipliers than the track's length in spacings plus one (the inf-sup
  bound), weights that make g_j a weighted mean of the violation and a partition of unity;
- its loads: friction x needle length on every segment, the cutting force spread over
  `cutting_length` mm of needle behind the tip, in total the insertion force; the smooth
  profile's and the ramp's total cutting force on the track at several depths (also across a
  wound's gap) and the smooth density's share on each segment;
- the multiplier field it converges to is smooth (no checkerboard: the inf-sup condition
  holds) and the track stays on the needle between the needle points;
- `center_sensitivity` (the planner's Jacobian) against central finite differences of the
  re-equilibrated state, for both couplings and the mortar's arc-length element ends;
- `multiplier_ends: arc`: element ends at exact arc lengths a local spacing apart;
- the residual's coupling terms, kept on joined rows for speed, against their definitions
  written out point by point, for both couplings;
- the residual's derivative in the centre, the follower loads' turn with it included, against
  central differences;
- segments longer than two particle spacings split into pieces with two Gauss points each
  (track_layout.segment_subintervals): their loads, constraint and centre columns.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_simulation import advance_one, dense_rest_stiffness, small_scene, started

from stitchplan.needle import coupling as coupling_module
from stitchplan.needle.coupling import MULTIPLIER_ORDER
from stitchplan.needle import load_quadrature
from stitchplan.needle.load_quadrature import cutting_share
from stitchplan.needle.track_layout import MULTIPLIER_SPACINGS, segment_subintervals
from stitchplan.needle.equilibrium import NeedleInsertion


@pytest.fixture(scope="module")
def mortar():
    """The small scene on a 2 mm grid (the 1.6 mm steps shorter than the spacing), 6 steps."""
    return started(small_scene(spacing=2.0, coupling="mortar"), steps=6)


def test_multiplier_elements_span_whole_segments_at_least_a_spacing_long(mortar):
    coupling = mortar.coupling
    segments = len(coupling.points) - 1
    lengths = np.linalg.norm(np.diff(coupling.points, axis=0), axis=1)
    shares = coupling._partition()  # P (Q, m): phi_j at each Gauss point (the same partition again)
    assert shares.shape == (2 * segments, coupling.multiplier_count)
    np.testing.assert_allclose(shares.sum(axis=1), 1.0, atol=1e-14)  # partition of unity
    weights = coupling.weights
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-14)  # g_j: a weighted mean
    # the nodes of the piecewise-linear field sit at needle points, at least a spacing apart
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    nodes = coupling.multiplier_nodes
    assert np.all(np.min(np.abs(nodes[:, None] - arc[None, :]), axis=1) <= 1e-12)
    spacing = coupling.local_spacing(coupling.points).max()
    assert np.all(np.diff(nodes) >= MULTIPLIER_SPACINGS * spacing - 1e-9)
    # inf-sup bound: no more multipliers than the spacings along the track, plus one
    assert 2 <= coupling.multiplier_count <= arc[-1] / (MULTIPLIER_SPACINGS * spacing) + 1


@pytest.mark.parametrize("multiplier_ends", ["segments", "arc"])
def test_multiplier_length_keeps_the_elements_when_the_particles_are_refined(multiplier_ends):
    """`needle.multiplier_length: 3` with 1.6 mm steps, 6 steps: on 2 mm and 1 mm grids the
    elements are the same (whole segments: 2 of them, 3.2 mm; arc ends: cut every 3 mm
    from the tip), none shorter than 3 mm; on a 4 mm grid the local spacing is longer and
    sets them (at least 4 mm), as without the key."""
    def nodes_at(spacing: float) -> tuple[np.ndarray, np.ndarray, float]:
        scene = small_scene(spacing=spacing, coupling="mortar", multiplier_ends=multiplier_ends,
                            multiplier_length=3.0)
        coupling = started(scene, steps=6).coupling
        lengths = np.linalg.norm(np.diff(coupling.points, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(lengths)])
        return coupling.multiplier_nodes, arc, coupling.local_spacing(coupling.points).max()

    fine, fine_arc, _ = nodes_at(1.0)
    medium, medium_arc, _ = nodes_at(2.0)
    coarse, coarse_arc, coarse_spacing = nodes_at(4.0)
    assert len(fine) == len(medium) >= 3
    # the same elements: at the same needle points (segments) or arc lengths (arc) from the tip
    if multiplier_ends == "segments":
        np.testing.assert_array_equal(np.searchsorted(fine_arc, fine - 1e-9),
                                      np.searchsorted(medium_arc, medium - 1e-9))
        interior = np.diff(fine)
    else:  # the track's length moves a little with the discretization; the cuts keep their distance from the tip
        np.testing.assert_allclose(fine_arc[-1] - fine[1:-1], medium_arc[-1] - medium[1:-1], atol=1e-12)
        interior = np.diff(fine)[1:]  # the first element holds the remainder at the entry
    assert np.all(interior >= 3.0 - 1e-9)
    assert coarse_spacing == 4.0 and np.all(np.diff(coarse)[1 if multiplier_ends == "arc" else 0:] >= 4.0 - 1e-9)
    assert len(coarse) < len(fine)


def test_arc_ends_cut_the_track_every_local_spacing_from_the_tip():
    """`multiplier_ends: arc` on a 2 mm grid with 1.6 mm steps, 6 steps: the element ends sit at exact arc lengths one local spacing apart counted from the
    tip (not at needle points), the remainder (< 1 spacing) joins the element at the entry;
    each multiplier's weights are a phi_j-weighted mean over Gauss points it covers; every
    segment carries at least two constraint Gauss points and a segment longer than half an
    element more."""
    insertion = started(small_scene(spacing=2.0, coupling="mortar", multiplier_ends="arc"), steps=6)
    coupling = insertion.coupling
    lengths = np.linalg.norm(np.diff(coupling.points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    spacing = coupling.local_spacing(0.5 * (coupling.points[:-1] + coupling.points[1:]))
    assert np.ptp(spacing) == 0.0  # one spacing along this track: element lengths are exact
    nodes = coupling.multiplier_nodes
    assert nodes[0] == 0.0 and nodes[-1] == pytest.approx(arc[-1], abs=1e-12)
    np.testing.assert_allclose(np.diff(nodes)[1:], MULTIPLIER_SPACINGS * spacing[0], rtol=1e-12)
    assert MULTIPLIER_SPACINGS * spacing[0] <= nodes[1] < 2 * MULTIPLIER_SPACINGS * spacing[0]
    assert np.min(np.abs(nodes[1:-1, None] - arc[None, :])) > 1e-3  # cut inside segments here
    assert coupling.multiplier_count == len(nodes) == int(arc[-1] / (MULTIPLIER_SPACINGS * spacing[0])) + 1
    shares, weights = coupling._partition(), coupling.weights  # the same partition again
    np.testing.assert_allclose(shares.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-14)
    assert np.all((shares > 0).sum(axis=0) >= 2)  # every hat holds Gauss points
    per_segment = np.bincount(coupling._constraint_segment)
    assert len(per_segment) == len(lengths) and per_segment.min() >= 2
    assert coupling.quadrature_points().shape == (per_segment.sum(), 2)
    # the Gauss weights integrate each segment's length exactly
    np.testing.assert_allclose(np.bincount(coupling._constraint_segment, coupling._constraint_length), lengths,
                               rtol=1e-12)
    assert insertion.last_violation <= insertion.constraint_tolerance


def test_loads_add_up_to_friction_and_cutting_force_and_the_cut_sits_behind_the_tip(mortar):
    coupling, needle, geometry = mortar.coupling, mortar.needle, mortar.geometry
    segments = len(coupling.points) - 1
    loads = coupling.loads
    total = needle.friction * geometry.insertion_step * segments + needle.cutting_force
    assert loads.magnitudes.sum() == pytest.approx(total, rel=1e-12)
    # the cutting force sits on the last ceil(cutting_length / (R step)) segments of the track:
    # on their friction Gauss points where a segment is wholly covered, on points of its own
    # on the partly covered one at the zone's far end
    friction = 0.5 * needle.friction * geometry.insertion_step
    cutting = loads.magnitudes - np.concatenate([np.full(2 * segments, friction),
                                                 np.zeros(len(loads.magnitudes) - 2 * segments)])
    covered = int(np.ceil(needle.cutting_length / geometry.insertion_step - 1e-9))
    carrying = np.flatnonzero(cutting > 1e-12)
    cut = loads.points[carrying]
    assert np.all(carrying[carrying < 2 * segments] >= 2 * (segments - covered))
    start, end = coupling.points[-covered - 1:-1], coupling.points[-covered:]
    for point in cut:
        t = np.einsum("ij,ij->i", point - start, end - start) / np.einsum("ij,ij->i", end - start, end - start)
        off = np.linalg.norm(start + t[:, None] * (end - start) - point, axis=1)
        assert np.any((off <= 1e-9) & (t >= 0.0) & (t <= 1.0))
    np.testing.assert_allclose(cutting.sum(), needle.cutting_force, rtol=1e-12)


def _segment_of(coupling, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The track segment each reference point lies on (inside its chord), (n,), and the
    point's fraction t along it from its start, (n,)."""
    start, end = coupling.points[:-1], coupling.points[1:]
    chord = end - start
    t = np.einsum("pij,ij->pi", points[:, None, :] - start[None], chord) / np.einsum("ij,ij->i", chord, chord)
    off = np.linalg.norm(start[None] + t[..., None] * chord[None] - points[:, None, :], axis=2)
    off[(t < 0.0) | (t > 1.0)] = np.inf
    assert np.all(off.min(axis=1) <= 1e-9)  # every load point on the track
    segment = off.argmin(axis=1)
    return segment, t[np.arange(len(points)), segment]


@pytest.mark.parametrize("cutting_length", [2.4, 10.0])  # 1.6 mm segments: own Gauss points / the friction ones
@pytest.mark.parametrize("profile, ramp", [("uniform", False), ("uniform", True), ("smooth", False),
                                           ("smooth", True)])
@pytest.mark.parametrize("pieces", [1, 3])  # each segment's Gauss points: two, or two on each of three pieces
def test_cutting_force_on_the_track_at_each_depth(monkeypatch, profile, ramp, cutting_length, pieces):
    """The cutting force on the track after each needle point (no equilibrium needed: the
    loads depend on the reference track only), 8 steps with a wound's gap at the 4th: without
    the ramp the whole force; with it cutting_force x the profile's share of [0, l] inside
    (smooth: z / l - sin(2 pi z / l) / 2 pi) to < 0.5 %. The smooth density's force on each
    segment is its integral over the segment's needle length (s from the tip), within 0.5 %
    of the force: zero at the tip, the most at l / 2 behind it; the uniform one's centroid lies
    half its zone behind the tip."""
    monkeypatch.setattr(load_quadrature, "CUTTING_PROFILE", profile)
    monkeypatch.setattr(coupling_module, "segment_subintervals", lambda length, spacing: pieces)
    scenario = small_scene(spacing=4.0, coupling="mortar", cutting_length=cutting_length, cutting_ramp=ramp)
    insertion = NeedleInsertion(scenario)
    coupling, geometry, needle = insertion.coupling, insertion.geometry, insertion.needle
    insertion.add_point(geometry.entry.copy())
    checked = 0
    for step in range(1, 9):
        gap = step == 4  # the tip crosses a wound: that segment carries nothing
        insertion.add_point(geometry.tip(step * geometry.step), gap=gap, fraction=0.0 if gap else 1.0)
        segments = len(coupling.points) - 1
        needle_length = geometry.insertion_step * coupling.segment_fraction
        count = 2 * pieces  # Gauss points per segment
        assert len(coupling.gauss) == count
        friction = np.repeat(needle.friction * needle_length / count, count)
        magnitudes = coupling.loads.magnitudes
        cutting = magnitudes - np.concatenate([friction, np.zeros(len(magnitudes) - count * segments)])
        inside = float(needle_length.sum())
        expected = needle.cutting_force * (cutting_share(inside, cutting_length, profile) if ramp else 1.0)
        rtol = 1e-12 if profile == "uniform" or not ramp else 5e-3
        assert cutting.sum() == pytest.approx(expected, rel=rtol)
        assert np.all(cutting >= -1e-15)
        carrying = np.flatnonzero(cutting > 0.0)
        behind = np.concatenate([np.cumsum(needle_length[::-1])[::-1][1:], [0.0]])  # tip to each segment's end
        if profile == "uniform":
            # spread evenly over the zone behind the tip: its centroid half the zone behind it
            segment, t = _segment_of(coupling, coupling.loads.points[carrying])
            behind_tip = behind[segment] + (1.0 - t) * needle_length[segment]
            zone = min(cutting_length, inside)
            assert np.average(behind_tip, weights=cutting[carrying]) == pytest.approx(zone / 2.0, rel=1e-9)
        if profile == "smooth":
            # the force on each segment against the density's integral over its needle length
            per_segment = np.bincount(_segment_of(coupling, coupling.loads.points[carrying])[0], cutting[carrying],
                                      minlength=segments)
            share = np.array([cutting_share(b + n, cutting_length) - cutting_share(b, cutting_length)
                              for b, n in zip(behind, needle_length)])  # the track's segments: a few
            scale = needle.cutting_force if ramp else needle.cutting_force / cutting_share(inside, cutting_length)
            np.testing.assert_allclose(per_segment, scale * share, atol=5e-3 * needle.cutting_force)
            checked += int(np.count_nonzero(share))
    if profile == "smooth":
        assert checked >= 8  # segments with a share were compared, the gap's not among them


def test_the_track_stays_on_the_needle_between_the_multiplier_nodes():
    """After 10 steps on a 1 mm grid every needle point is within a hundredth of the spacing
    of the needle, though only the weighted means of the violation are held to zero."""
    insertion = started(small_scene(spacing=1.0, coupling="mortar"), steps=10)
    u = insertion.displacement(insertion.points)
    distance = np.abs(np.linalg.norm(insertion.points + u - insertion.center, axis=1) - insertion.geometry.radius)
    assert distance.max() <= 0.01 * 1.0
    assert insertion.last_violation <= insertion.constraint_tolerance


def normalised_schur_minimum(insertion: NeedleInsertion) -> float:
    """Smallest eigenvalue of D^-1/2 S D^-1/2, S = G^T K0^-1 G, D = diag S: the discrete
    inf-sup constant squared (up to scaling). It stays away from zero for a multiplier
    space the particles can resolve and drops to round-off when they cannot."""
    state = insertion.residuals(insertion.free, insertion.multipliers, insertion.center)
    g = insertion.coupling.constraint_matrix(state.normal).toarray()
    schur = g.T @ np.linalg.solve(dense_rest_stiffness(insertion), g)
    scale = 1.0 / np.sqrt(np.diag(schur))
    return float(np.linalg.eigvalsh(scale[:, None] * schur * scale[None, :]).min())


def test_inf_sup_the_mortar_multipliers_stay_resolvable_where_needle_points_do_not():
    """Needle points 0.4 mm apart (step 0.05 rad) on 2 mm and 1 mm grids: the point coupling's
    normalised Schur complement is singular to round-off (1e-12 and 3e-8: its multipliers are
    closer than the particles resolve); the mortar coupling's smallest eigenvalue is 6e-3
    and 4e-3 with 5 and 9 multipliers, above 1e-3 and losing less than half of itself as
    the spacing halves and the multipliers double (an unstable space loses orders of
    magnitude)."""
    minimum = {}
    for spacing in (2.0, 1.0):
        for coupling in ("points", "mortar"):  # 1271 particles at 1 mm: dense K0 solves of ~2 s
            insertion = NeedleInsertion(small_scene(step=0.05, spacing=spacing, coupling=coupling))
            for rotation in np.arange(25) * 0.05:
                insertion.add_point(insertion.geometry.tip(rotation))
            minimum[coupling, spacing] = normalised_schur_minimum(insertion)
    assert max(minimum["points", 2.0], minimum["points", 1.0]) < 1e-6
    assert min(minimum["mortar", 2.0], minimum["mortar", 1.0]) > 1e-3
    assert minimum["mortar", 1.0] > 0.5 * minimum["mortar", 2.0]


@pytest.mark.parametrize("coupling", ["points", "mortar", "mortar-arc"])
def test_center_sensitivity_matches_finite_differences(coupling):
    """d u(X_exit) / dC, the planner's Jacobian, against central differences of the
    re-equilibrated state (centre moved by +-1e-4 mm): within 1e-3 of its norm (observed
    1.7e-4 points, 1.1e-4 mortar). The sensitivity leaves out only the follower loads' own
    stiffness (d f_needle / du, of order the needle force over R), as Newton does."""
    options = {"coupling": "mortar", "multiplier_ends": "arc"} if coupling == "mortar-arc" else {"coupling": coupling}
    insertion = started(small_scene(spacing=2.0, **options), steps=5)
    target = insertion.geometry.desired_exit
    jacobian = insertion.center_sensitivity(target, refactor=True)
    base = insertion.snapshot()
    h = 1e-4
    columns = []
    for j in range(2):
        values = []
        for sign in (1.0, -1.0):
            insertion.restore(base)
            insertion.move_center(base.center + sign * h * np.eye(2)[j])
            insertion.equilibrate(5 * insertion.geometry.step, 5)
            values.append(insertion.displacement(target)[0])
        columns.append((values[0] - values[1]) / (2 * h))
    difference = np.column_stack(columns)
    assert np.linalg.norm(difference) > 0.05  # the exit follows the centre visibly
    assert np.linalg.norm(jacobian - difference) <= 1e-3 * np.linalg.norm(difference)


@pytest.mark.parametrize("cutting_length, pieces", [(3.2, False), (3.0, False), (3.0, True)])
def test_center_columns_on_the_constraint_rows_match_the_solved_ones(monkeypatch, cutting_length, pieces):
    """The centre's columns d(d, lambda)/dC from the kept K^-1 E^T (equilibrium
    CENTER_COLUMNS_ON_ROWS) against the same columns solved with the factor: equal to
    round-off where every load point is a segment Gauss point (cutting length two whole
    1.6 mm steps), and within the finite-difference test's 1e-3 where the cutting force's
    points on a partly covered segment are lumped onto its Gauss points (3 mm)."""
    from stitchplan.needle import equilibrium

    scene = PIECES_SCENE if pieces else {"spacing": 2.0, "coupling": "mortar"}
    insertion = started(small_scene(**scene, cutting_length=cutting_length), steps=3 if pieces else 5)
    lumped = len(insertion.coupling.loads.lumping[0])
    target = insertion.geometry.desired_exit
    on_rows = insertion.center_sensitivity(target, refactor=True)
    monkeypatch.setattr(equilibrium, "CENTER_COLUMNS_ON_ROWS", False)
    solved = insertion.center_sensitivity(target, refactor=True)
    difference = np.linalg.norm(on_rows - solved) / np.linalg.norm(solved)
    if cutting_length == 3.2:
        assert lumped == 0 and difference < 1e-10
    else:
        assert lumped == (4 if pieces else 2) and 0.0 < difference < 1e-3


def test_the_mortar_coupling_adds_a_multiplier_only_once_a_spacing_of_track_has_grown():
    """On a 4 mm grid with 1.6 mm steps the multiplier count grows about every third step
    (track length / spacing + 1), not with every needle point as the point coupling's does."""
    insertion = started(small_scene(spacing=4.0, coupling="mortar"))
    counts = []
    for step in range(1, 9):
        advance_one(insertion, step)
        counts.append(insertion.coupling.multiplier_count)
    assert counts == sorted(counts) and counts[0] == 1 + (MULTIPLIER_ORDER == 1)
    assert counts[-1] <= 8 * 1.6 / (MULTIPLIER_SPACINGS * 4.0) + 2 < 9


# the small scene's 8 mm needle in 0.5 rad steps: 4 mm segments on a 1.5 mm grid, two pieces each
PIECES_SCENE = {"spacing": 1.5, "coupling": "mortar", "step": 0.5}


@pytest.mark.parametrize("coupling", ["points", "mortar", "mortar-arc", "mortar-pieces", "mortar-arc-pieces"])
def test_the_coupling_terms_match_their_definitions_point_by_point(coupling):
    """The track's rows are kept as joined CSR blocks, a step's new points are evaluated
    together, and the residual's coupling terms come from one product with all of the
    track's rows and one with their transpose: against the definitions written out with
    each point's own shape-function row, mid-ramp (both load sets carry), off equilibrium:
    E = N (x) I_2, g = W^T (|x_q - C| - R_q), G lambda = sum_q N_q^T (mu_q n_q),
    f_needle = sum over both load sets of factor m_l N_l^T a_0(x_l) (eq. 3.64), the centre
    derivatives, and the tip's row."""
    options = ({"coupling": "mortar", "multiplier_ends": "arc"} if coupling == "mortar-arc" else
               PIECES_SCENE if coupling == "mortar-pieces" else
               {**PIECES_SCENE, "multiplier_ends": "arc"} if coupling == "mortar-arc-pieces" else {"coupling": coupling})
    pieces = coupling.endswith("pieces")
    insertion = started(small_scene(**{"spacing": 2.0, **options}), steps=3 if pieces else 4)
    track, model, geometry = insertion.coupling, insertion.model, insertion.geometry
    assert len(track.gauss) == (4 if pieces else 2)
    track.load_factor = 0.25
    rng = np.random.default_rng(3)
    free = 0.05 * rng.standard_normal(insertion.free.shape)
    multipliers = rng.standard_normal(track.multiplier_count)
    center = insertion.center + np.array([0.1, -0.05])

    def rows_at(points):  # each point on its own
        return np.vstack([(model.shape_functions_at(point[None]).values @ model.boundary.free_map).toarray()
                          for point in points])

    values, needle_force, constraint_force = track.residual_terms(free, multipliers, center)
    rows = rows_at(track.quadrature_points())
    np.testing.assert_allclose(track.expanded_rows.toarray(), np.kron(rows, np.eye(2)), rtol=0, atol=1e-14)
    relative = track.quadrature_points() + rows @ free - center
    rho = np.linalg.norm(relative, axis=1)
    normal = relative / rho[:, None]
    np.testing.assert_allclose(values.violation, track.weights.T @ (rho - track.target_radius), rtol=0, atol=1e-13)
    np.testing.assert_allclose(values.normal, normal, rtol=0, atol=1e-13)
    carried = track.weights @ multipliers
    np.testing.assert_allclose(constraint_force, (rows.T @ (carried[:, None] * normal)).ravel(), rtol=0, atol=1e-12)
    expected = np.zeros_like(needle_force)
    for loads, factor in ((track.loads, 0.25), (track.previous_loads, 0.75)):
        load_rows = rows_at(loads.points)
        spatial = loads.points + load_rows @ free - center
        tangent = geometry.tangent(np.arctan2(spatial[:, 1], spatial[:, 0]))
        expected += (load_rows.T @ (factor * loads.magnitudes[:, None] * tangent)).ravel()
    assert len(track.previous_loads.magnitudes) and np.abs(expected).max() > 0.0
    np.testing.assert_allclose(needle_force, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    projection = (carried / rho)[:, None, None] * (np.eye(2) - normal[:, :, None] * normal[:, None, :])
    np.testing.assert_allclose(track.center_derivative(multipliers, normal, rho),
                               -np.einsum("qp,qij->pij", rows, projection).reshape(-1, 2), rtol=0, atol=1e-12)
    np.testing.assert_allclose(track.tip_row, rows_at(track.points[-1:])[0], rtol=0, atol=1e-15)
    assert insertion.tip_displacement() == pytest.approx(insertion.displacement(track.points[-1])[0], abs=1e-13)


def test_the_aim_s_closed_form_spectral_norm():
    from stitchplan.needle.steering import spectral_norm

    rng = np.random.default_rng(5)
    for matrix in [*rng.standard_normal((20, 2, 2)), np.eye(2), np.zeros((2, 2)), np.array([[1.0, 1.0], [1.0, 1.0]])]:
        assert spectral_norm(matrix) == pytest.approx(np.linalg.norm(matrix, 2), rel=1e-12, abs=1e-15)


def test_a_segment_is_split_into_pieces_where_it_is_longer_than_two_spacings():
    """Two Gauss points per piece, at most one particle spacing apart on average: the SH 1/2
    needle's 0.71 mm segments stay whole at its 0.888 and 0.444 mm needle spacings, split in 2
    and 4 at 0.222 and 0.111 mm; the 20 mm needle's 2 mm segments likewise at 2.5 ... 0.3125 mm."""
    assert [segment_subintervals(0.7104, h) for h in (0.888, 0.444, 0.222, 0.111)] == [1, 1, 2, 4]
    assert [segment_subintervals(2.0, h) for h in (2.5, 1.25, 0.625, 0.3125)] == [1, 1, 2, 4]
    assert segment_subintervals(2.0, 1.0) == 1  # exactly two spacings: one piece


def test_pieces_carry_the_loads_and_hold_the_track_on_the_chord(monkeypatch):
    """4 mm segments on a 1.5 mm grid, 3 steps: four Gauss points per segment at the two-point
    rule's places in each half, equal weights; friction x needle length on each segment,
    the cutting force in total on the last cutting_length mm behind the tip (partly covered
    tip segment: points of its own, lumped onto the two Gauss points around each); each
    point asked to lie on the chord, sqrt(R^2 - t (1 - t) c^2) from the centre; after the
    steps the needle points lie closer to the needle than with one piece per segment."""
    insertion = started(small_scene(**PIECES_SCENE, cutting_length=3.0), steps=3)
    track, needle, geometry = insertion.coupling, insertion.needle, insertion.geometry
    segments = len(track.points) - 1
    two_point = 0.5 + np.array([-0.5, 0.5]) / np.sqrt(3.0)
    np.testing.assert_allclose(track.gauss, np.concatenate([two_point / 2, (1 + two_point) / 2]), rtol=0, atol=1e-15)
    loads = track.loads
    on_segments = loads.magnitudes[:4 * segments].reshape(segments, 4)
    friction = needle.friction * geometry.insertion_step
    np.testing.assert_allclose(on_segments[:-1].sum(axis=1), friction, rtol=1e-12)  # not cut: friction alone
    assert loads.magnitudes.sum() == pytest.approx(friction * segments + needle.cutting_force, rel=1e-12)
    indices, weights = loads.lumping
    assert len(indices) == 4 and np.all(indices[:, 1] == indices[:, 0] + 1)
    assert np.all(indices >= 4 * (segments - 1))  # on the tip segment's points
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    lumped = (weights[:, :, None] * track.segment_points[indices]).sum(axis=1)
    np.testing.assert_allclose(lumped, loads.points[4 * segments:], rtol=0, atol=1e-12)  # linear along the segment
    t = np.tile(track.gauss, segments)
    chord = 2.0 * geometry.radius * np.sin(0.5 * geometry.step)
    np.testing.assert_allclose(track.target_radius, np.sqrt(geometry.radius**2 - t * (1 - t) * chord**2), rtol=1e-14)

    def off_the_needle(run: NeedleInsertion) -> np.ndarray:
        u = run.displacement(run.points)
        return np.abs(np.linalg.norm(run.points + u - run.center, axis=1) - geometry.radius)

    monkeypatch.setattr(coupling_module, "segment_subintervals", lambda length, spacing: 1)
    whole = started(small_scene(**PIECES_SCENE, cutting_length=3.0), steps=3)
    assert len(whole.coupling.gauss) == 2
    # the needle points held closer than by two points per segment (0.029 against 0.043 mm)
    assert off_the_needle(insertion).max() < 0.8 * off_the_needle(whole).max()


def test_split_segments_make_the_exit_error_converge_as_the_needle_zone_is_refined(monkeypatch):
    """The small scene (1.6 mm segments) with particles 0.8, 0.4 and 0.2 mm apart around the
    needle (2 mm away from it; the ramp, elements fixed at 2 mm): with the segments split into
    pieces (1, 2, 4) the exit error's changes shrink at a rate near 3.5 (observed 2.5e-3 then
    2.2e-4 mm); with two Gauss points per segment at every level they do not shrink like a
    convergent sequence (6.0e-3 then 3.9e-3 mm, and 3.9e-3 again at 0.1 mm: the log-singular
    displacement of point forces, benchmarks/results/needle_fem_reference.md)."""
    from stitchplan.config.scenario import with_discretization
    from stitchplan.needle.insertion import run_insertion

    base = small_scene(spacing=2.0, coupling="mortar", cutting_ramp=True, multiplier_length=2.0)

    def changes() -> np.ndarray:
        errors = [run_insertion(with_discretization(base, needle_spacing=spacing)).exit_error_mm
                  for spacing in (0.8, 0.4, 0.2)]
        return np.diff(errors)

    split = changes()
    monkeypatch.setattr(coupling_module, "segment_subintervals", lambda length, spacing: 1)
    whole = changes()
    assert split[0] * split[1] > 0 and np.log2(split[0] / split[1]) > 2.0
    assert whole[0] * whole[1] > 0 and np.log2(whole[0] / whole[1]) < 1.0
    assert abs(split[1]) < 0.2 * abs(whole[1])


@pytest.mark.parametrize("coupling", ["points", "mortar", "mortar-pieces"])
def test_the_residuals_centre_derivative_matches_finite_differences(coupling):
    """d r_u / dC = d (G lambda) / dC - d f_needle / dC (the planner's right-hand sides for the
    centre's columns) against central differences of the residual in the centre, at a
    deformed state off equilibrium with random multipliers, mid-ramp (both load sets carry).
    The friction and the cutting force follow the needle's tangent at their points, which
    turns with C: leaving that term out moves the planner's Jacobian by only ~3e-4 of its
    norm, below what the finite-difference check of center_sensitivity can see, so it is
    checked here on its own, and on the constraint rows (center_derivative_on_rows: exact
    where every load point is a segment Gauss point, cutting length two whole 1.6 mm steps)."""
    options = ({**PIECES_SCENE, "cutting_length": 8.0} if coupling == "mortar-pieces"  # two whole 4 mm steps
               else {"spacing": 2.0, "coupling": coupling, "cutting_length": 3.2})
    insertion = started(small_scene(**options), steps=3 if coupling == "mortar-pieces" else 4)
    track = insertion.coupling
    track.load_factor = 0.25
    rng = np.random.default_rng(11)
    free = 0.05 * rng.standard_normal(insertion.free.shape)
    multipliers = rng.standard_normal(track.multiplier_count)
    center = insertion.center + np.array([0.1, -0.05])
    values, _, _ = track.residual_terms(free, multipliers, center)
    turn = track.needle_force_center_derivative(free, center)  # d f_needle / dC, (2 n_free, 2)
    exact = track.center_derivative(multipliers, values.normal, values.rho) - turn
    h = 1e-6
    needle_columns, residual_columns = [], []
    for j in range(2):
        step = h * np.eye(2)[j]
        plus, minus = (track.residual_terms(free, multipliers, center + sign * step) for sign in (1.0, -1.0))
        needle_columns.append((plus[1] - minus[1]) / (2 * h))
        residual_columns.append(((plus[2] - plus[1]) - (minus[2] - minus[1])) / (2 * h))
    needle_difference, residual_difference = np.column_stack(needle_columns), np.column_stack(residual_columns)
    assert np.abs(turn).max() > 1e-3 and np.abs(exact).max() > 1e-2
    # central differences: truncation h^2 / R^2 and cancellation 1e-16 |f| / h, below 1e-8 here
    np.testing.assert_allclose(turn, needle_difference, rtol=0, atol=1e-7 * np.abs(turn).max())
    np.testing.assert_allclose(exact, residual_difference, rtol=0, atol=1e-7 * np.abs(exact).max())
    on_rows = track.center_derivative_on_rows(free, multipliers, values.normal, values.rho, center)
    if coupling != "points":
        assert on_rows is not None and len(track.loads.lumping[0]) == 0
        np.testing.assert_allclose(track.expanded_rows_t @ on_rows, residual_difference, rtol=0,
                                   atol=1e-7 * np.abs(exact).max())


def test_the_step_records_log_the_forces_the_loads_apply():
    """Each step's friction_force and cutting_force (the run log's columns) are what the
    track's loads apply: with `cutting_ramp` the cutting force grows over the first
    cutting_length mm of needle inside (here 1.6 mm steps into a 4 mm cutting length:
    0.4, 0.8, then the whole force), not the needle block's nominal value from the first
    step on; the two add up to the loads' total."""
    from stitchplan.needle.insertion import run_insertion

    scenario = small_scene(spacing=4.0, coupling="mortar", cutting_length=4.0, cutting_ramp=True)
    needle = scenario.needle
    records = []
    run_insertion(scenario, on_step=records.append)
    assert len(records) >= 4
    step_length = needle.radius * needle.step  # 1.6 mm
    for record in records[:4]:
        inside = record.step * step_length
        assert record.friction_force == pytest.approx(needle.friction * inside, rel=1e-12)
        assert record.cutting_force == pytest.approx(needle.cutting_force * min(inside / 4.0, 1.0), rel=1e-9)


def test_a_singular_moment_matrix_met_during_a_step_names_the_step(monkeypatch):
    """Shape functions asked for during a step where too few particles see the point (the
    exit search's boundary samples on a hole's wall, met on a finely graded inclusion around
    a hole) ended the run with the bare moment-matrix line: the step and the angle are named,
    as for the step's other failures, and the planner can take it as a failed pass."""
    from stitchplan.errors import InsertionFailure
    from stitchplan.needle import insertion as module
    from stitchplan.tissue.shape_functions import SingularMomentAt

    track = module._Run.track_in_tissue

    def failing_at_step_3(self, step, rotation):
        if step == 3:
            raise SingularMomentAt("moment matrix M(X) is singular at (44.87, 12) mm", np.array([44.87, 12.0]))
        return track(self, step, rotation)

    monkeypatch.setattr(module._Run, "track_in_tissue", failing_at_step_3)
    scenario = small_scene(spacing=4.0, coupling="mortar")
    with pytest.raises(InsertionFailure) as failed:
        module.run_insertion(scenario)
    rotation = 3 * scenario.needle.step
    assert str(failed.value) == f"step 3 (needle rotation {rotation:.3f} rad): moment matrix M(X) is singular at (44.87, 12) mm"
