"""RK shape functions (thesis eq. 3.18-3.23): reproducing conditions to round-off and
exact gradients against finite differences, on a small regular particle grid."""

from __future__ import annotations

import numpy as np
import pytest

from stitchplan.tissue.kernel import cubic_spline, tensor_kernel
from stitchplan.tissue.particles import grid_particles
from stitchplan.tissue.shape_functions import SingularMomentMatrix, rk_shape_functions, rk_shape_pairs

SIZE = (10.0, 8.0)  # mm
SPACING = 2.0  # mm -> 6 x 5 particles
ROUND_OFF = 1e-12

# (basis order, dilation): a quadratic basis needs 3 x 3 particles at a corner, so dilation > 2
CASES = [(1, 2.0), (1, 2.5), (2, 2.5), (2, 3.0)]


def particle_grid(dilation: float):
    particles, volumes, dx, dy = grid_particles(SIZE, SPACING)
    support = np.full(len(particles), dilation * max(dx, dy))
    return particles, support, volumes


def evaluation_points(rng: np.random.Generator) -> np.ndarray:
    """Random interior points, points a hair inside each edge, points exactly on the edges,
    exactly at the four corners and exactly at particles (where kernel breakpoints sit)."""
    width, height = SIZE
    inside = rng.uniform((0.0, 0.0), SIZE, size=(40, 2))
    gaps = np.array([1e-12, 1e-9, 1e-6, 1e-3])
    along_x = rng.uniform(0.0, width, size=len(gaps))
    along_y = rng.uniform(0.0, height, size=len(gaps))
    near_edges = np.concatenate([
        np.stack([gaps, along_y], axis=1),  # left
        np.stack([width - gaps, along_y], axis=1),  # right
        np.stack([along_x, gaps], axis=1),  # bottom
        np.stack([along_x, height - gaps], axis=1),  # top
    ])
    on_edges = np.array([[0.0, 3.3], [width, 5.1], [7.7, 0.0], [2.9, height]])
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
    at_particles = np.array([[2.0, 2.0], [4.0, 6.0], [8.0, 0.0]])
    return np.concatenate([inside, near_edges, on_edges, corners, at_particles])


def monomials(points: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Basis fields p(X) and their exact derivatives d/dX, d/dY, each (n, terms)."""
    x, y = points[:, 0], points[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    values = [one, x, y]
    d_dx = [zero, one, zero]
    d_dy = [zero, zero, one]
    if order == 2:
        values += [x * x, x * y, y * y]
        d_dx += [2 * x, y, zero]
        d_dy += [zero, x, 2 * y]
    return np.stack(values, 1), np.stack(d_dx, 1), np.stack(d_dy, 1)


def test_the_cubic_spline_is_eq_3_23_with_its_derivative(rng):
    """The kernel's truncated-power evaluation equals eq. 3.23's two pieces (2/3 - 4 r^2 +
    4 r^3 up to r = 1/2, 4/3 (1 - r)^3 up to 1, zero beyond) at random arguments and at the
    breakpoints, and its derivative matches central differences away from them."""
    z = np.concatenate([rng.uniform(-1.3, 1.3, 2000), [0.0, 0.5, -0.5, 1.0, -1.0, 1.25]])
    r = np.abs(z)
    piecewise = np.where(r <= 0.5, 2 / 3 - 4 * r**2 + 4 * r**3, np.where(r < 1.0, 4 / 3 * (1 - r) ** 3, 0.0))
    phi, dphi = cubic_spline(z)
    np.testing.assert_allclose(phi, piecewise, rtol=0, atol=ROUND_OFF)
    np.testing.assert_allclose(phi[-6:], [2 / 3, 1 / 6, 1 / 6, 0.0, 0.0, 0.0], rtol=0, atol=ROUND_OFF)
    h = 1e-6
    smooth = np.abs(r[:-6, None] - [0.0, 0.5, 1.0]).min(axis=1) > 10 * h
    central = (cubic_spline(z + h, False)[0] - cubic_spline(z - h, False)[0]) / (2 * h)
    np.testing.assert_allclose(dphi[:-6][smooth], central[:-6][smooth], rtol=0, atol=1e-8)
    np.testing.assert_allclose(dphi[-6:], [0.0, -1.0, 1.0, 0.0, 0.0, 0.0], rtol=0, atol=ROUND_OFF)


def test_the_tensor_kernel_is_eq_3_22_with_its_gradient(rng):
    """phi_a(X - X_I) = prod_i (1/a) phi((X_i - X_Ii) / a) (eq. 3.22) for supports that differ
    from pair to pair, as on graded particles, and its gradient against central differences.

    The reproducing conditions cannot see the kernel's scale: a factor common to a point's
    pairs cancels in M(X)^-1, so a kernel off by a power of a passes them on a uniform grid
    and only changes the functions where the supports vary; this compares it with the
    formula itself."""
    support = rng.uniform(0.5, 4.0, size=300)
    offset = rng.uniform(-1.2, 1.2, size=(300, 2)) * support[:, None]  # some pairs outside the support
    phi, grad = tensor_kernel(offset, support)
    expected = np.prod(cubic_spline(offset / support[:, None], derivative=False)[0], axis=1) / support**2
    assert np.count_nonzero(expected) > 100 and np.count_nonzero(expected == 0.0) > 10
    np.testing.assert_allclose(phi, expected, rtol=1e-12, atol=1e-15 * expected.max())
    h = 1e-6
    for k in range(2):
        step = np.zeros(2)
        step[k] = h
        central = (tensor_kernel(offset + step, support, False)[0]
                   - tensor_kernel(offset - step, support, False)[0]) / (2 * h)
        # truncation (h / a)^2 and cancellation 1e-16 / h stay far below 1e-6 of the largest slope
        np.testing.assert_allclose(grad[:, k], central, rtol=0, atol=1e-6 * np.abs(grad).max())


@pytest.mark.parametrize("order, dilation", CASES)
def test_reproduces_complete_polynomials_to_round_off(order, dilation, rng):
    """sum N_I = 1, sum N_I X_I = X (and the quadratics for order 2), also on edges and corners."""
    particles, support, volumes = particle_grid(dilation)
    points = evaluation_points(rng)
    shape = rk_shape_functions(points, particles, support, volumes, order, gradients=False)

    np.testing.assert_allclose(shape.values.sum(axis=1).A1, 1.0, rtol=0, atol=ROUND_OFF)
    np.testing.assert_allclose(shape.values @ particles, points, rtol=0, atol=ROUND_OFF * max(SIZE))
    exact, _, _ = monomials(points, order)
    nodal, _, _ = monomials(particles, order)
    np.testing.assert_allclose(shape.values @ nodal, exact, rtol=0, atol=ROUND_OFF * max(SIZE) ** 2)


@pytest.mark.parametrize("order, dilation", CASES)
def test_gradients_reproduce_polynomial_gradients_to_round_off(order, dilation, rng):
    """sum dN_I = 0 and sum dN_I X_I = identity (plus quadratic gradients for order 2)."""
    particles, support, volumes = particle_grid(dilation)
    points = evaluation_points(rng)
    shape = rk_shape_functions(points, particles, support, volumes, order, gradients=True)

    for grad in (shape.grad_x, shape.grad_y):
        np.testing.assert_allclose(grad.sum(axis=1).A1, 0.0, rtol=0, atol=ROUND_OFF)
    identity_rows = np.broadcast_to(np.eye(2), (len(points), 2, 2))
    jacobian = np.stack([shape.grad_x @ particles, shape.grad_y @ particles], axis=2)  # d X_i / d X_J
    np.testing.assert_allclose(jacobian, identity_rows, rtol=0, atol=ROUND_OFF)
    _, exact_dx, exact_dy = monomials(points, order)
    nodal, _, _ = monomials(particles, order)
    np.testing.assert_allclose(shape.grad_x @ nodal, exact_dx, rtol=0, atol=ROUND_OFF * max(SIZE))
    np.testing.assert_allclose(shape.grad_y @ nodal, exact_dy, rtol=0, atol=ROUND_OFF * max(SIZE))


@pytest.mark.parametrize("order, dilation", CASES)
def test_gradients_match_central_finite_differences(order, dilation, rng):
    """grad N_I against (N_I(X + h e_k) - N_I(X - h e_k)) / 2h for every particle.

    h = 1e-6 mm: the truncation error (h^2 N''') is ~1e-13 and the cancellation error
    ~1e-16/h ~ 1e-10, so the bound 1e-6 x max|grad N| leaves four decades of margin while a
    missing term of the gradient (dM/dX, dH/dX or dphi) shows up at the 1e-2 level."""
    particles, support, volumes = particle_grid(dilation)
    points = evaluation_points(rng)
    h = 1e-6
    shape = rk_shape_functions(points, particles, support, volumes, order, gradients=True)

    for grad, step in ((shape.grad_x, (h, 0.0)), (shape.grad_y, (0.0, h))):
        forward = rk_shape_functions(points + step, particles, support, volumes, order, False).values
        backward = rk_shape_functions(points - step, particles, support, volumes, order, False).values
        finite_difference = ((forward - backward) / (2 * h)).toarray()
        scale = np.abs(grad.toarray()).max()
        assert scale > 0.05  # the comparison is not trivially between zeros
        np.testing.assert_allclose(grad.toarray(), finite_difference, rtol=0, atol=1e-6 * scale)


@pytest.mark.parametrize("order, dilation", CASES)
def test_direct_field_evaluation_equals_the_sparse_matrices(order, dilation, rng):
    """ShapePairs.field (tip tracking's path, no sparse matrices) gives u and du/dX exactly as
    the stored sparse matrices do, for a random coefficient field."""
    particles, support, volumes = particle_grid(dilation)
    points = evaluation_points(rng)
    coefficients = rng.normal(size=(len(particles), 2))
    shape = rk_shape_functions(points, particles, support, volumes, order, gradients=True)
    u, grad = rk_shape_pairs(points, particles, support, volumes, order, gradients=True).field(coefficients)
    np.testing.assert_allclose(u, shape.values @ coefficients, rtol=0, atol=ROUND_OFF)
    np.testing.assert_allclose(grad, np.stack([shape.grad_x @ coefficients, shape.grad_y @ coefficients], axis=2),
                               rtol=0, atol=ROUND_OFF)
    u_only, none = rk_shape_pairs(points, particles, support, volumes, order, gradients=False).field(coefficients)
    assert none is None
    np.testing.assert_allclose(u_only, u, rtol=0, atol=ROUND_OFF)


def test_too_few_particles_for_the_basis_is_reported():
    """At a corner a dilation-2 kernel sees 2 x 2 particles: the quadratic basis (6 terms)
    cannot be reproduced there and the error says where and what to change."""
    particles, support, volumes = particle_grid(2.0)
    with pytest.raises(SingularMomentMatrix, match=r"\(0, 0\) mm .*order-2 basis needs at least 6"):
        rk_shape_functions(np.array([[0.0, 0.0]]), particles, support, volumes, order=2)


@pytest.mark.parametrize("batch", [1, 5])
@pytest.mark.parametrize("order, dilation", CASES)
def test_a_few_points_at_a_time_give_what_many_give(order, dilation, batch, rng):
    """Many points take the batched inverse and the condition estimate, a few LAPACK's
    inverse and eigenvalues, and one point (tip tracking) its sums as dot products: the same
    functions to round-off."""
    particles, support, volumes = particle_grid(dilation)
    points = evaluation_points(rng)
    many = rk_shape_pairs(points, particles, support, volumes, order, gradients=True)
    few = [rk_shape_pairs(points[k:k + batch], particles, support, volumes, order, gradients=True)
           for k in range(0, len(points), batch)]
    np.testing.assert_array_equal(many.cols, np.concatenate([part.cols for part in few]))
    np.testing.assert_allclose(many.values, np.concatenate([part.values for part in few]), rtol=0, atol=ROUND_OFF)
    np.testing.assert_allclose(many.grad, np.concatenate([part.grad for part in few]), rtol=0, atol=ROUND_OFF)


@pytest.mark.parametrize("count", [1, 100])
def test_a_singular_moment_matrix_is_reported_with_its_point(count):
    """Particles on one line leave the linear basis's moment matrix singular everywhere,
    with enough particles in each support: found by the eigenvalues (a few points) and by
    the condition estimate (many)."""
    particles = np.stack([np.linspace(0.0, 10.0, 11), np.full(11, 4.0)], axis=1)
    support, volumes = np.full(11, 2.5), np.ones(11)
    points = np.stack([np.linspace(2.0, 8.0, count), np.full(count, 4.0)], axis=1)
    with pytest.raises(SingularMomentMatrix, match=r"moment matrix M\(X\) is singular at \([0-9.]+, 4\) mm"):
        rk_shape_pairs(points, particles, support, volumes, order=1, gradients=False)


def graded_arrangement(dilation: float = 2.0):
    """Particles graded from 4 mm down to 0.5 mm (three levels) toward a disk in a 40 x 30 mm
    slab: the supports differ by a factor 8, as around a needle or a wound's corner."""
    from stitchplan.tissue.particles import graded_particles

    graded = graded_particles((40.0, 30.0), 4.0, 0.5, np.array([12.0, 20.0]), 3.0)
    return graded.particles, dilation * graded.local_spacing, graded.volumes


@pytest.mark.parametrize("count", [5, 500])  # a few points search one tree, many the support groups
def test_the_support_group_search_finds_every_pair_and_no_other(count, rng):
    """neighbour_pairs through ParticleSearch against a brute-force |X - X_I|_inf < a_I over
    every (point, particle) pair, on graded particles whose supports differ by 8x."""
    from stitchplan.tissue.shape_functions import ParticleSearch, neighbour_pairs

    particles, support, _ = graded_arrangement()
    search = ParticleSearch.of(particles, support)
    assert len(search.groups) >= 3  # the levels are searched apart
    points = rng.uniform((0.0, 0.0), (40.0, 30.0), size=(count, 2))
    rows, cols, indptr = neighbour_pairs(points, particles, support, search)
    inside = np.abs(points[:, None, :] - particles[None, :, :]).max(axis=2) < support * (1.0 - 1e-9)
    expected_rows, expected_cols = np.nonzero(inside)  # by point, then particle
    np.testing.assert_array_equal(rows, expected_rows)
    np.testing.assert_array_equal(cols, expected_cols)
    np.testing.assert_array_equal(np.diff(indptr), inside.sum(axis=1))


def test_cells_find_the_max_norm_ball_and_the_nearest_particle(rng):
    """CellGrid against brute force: pairs within a reach that equals the cell size (points
    on the ball's edge included, particles in the point's own place, a point far outside, a
    point that is not a number) and the nearest particle, the lowest index on a tie."""
    from stitchplan.tissue.neighbours import CellGrid

    particles = np.array([(x, y) for x in np.arange(0.0, 10.5, 1.0) for y in np.arange(0.0, 6.5, 1.0)])
    grid = CellGrid.of(particles, 2.0)
    points = np.vstack([rng.uniform(-1.0, 11.0, size=(200, 2)), particles[:5], [[3.0, 2.0], [5.5, 2.5],
                        [1e12, -3.0], [np.nan, 1.0], [-2.0, 3.0]]])
    rows, cols = grid.within(points, 2.0)
    order = np.lexsort((cols, rows))
    inside = np.abs(points[:, None, :] - particles[None, :, :]).max(axis=2) <= 2.0  # NaN: False
    expected_rows, expected_cols = np.nonzero(inside)
    np.testing.assert_array_equal(rows[order], expected_rows)
    np.testing.assert_array_equal(cols[order], expected_cols)
    assert inside[-5].sum() == 25  # (3, 2): the 5 x 5 particles of the closed ball
    finite = points[:-2]  # (5.5, 2.5) is as near to four particles: the lowest index wins
    distance = ((finite[:, None, :] - particles[None, :, :]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(grid.nearest(finite), distance.argmin(axis=1))
    assert grid.nearest(np.array([[1e12, -3.0]]))[0] == distance[-1].argmin()  # beyond every cell


def test_gradients_on_graded_particles_reproduce_and_match_finite_differences(rng):
    """The moment's gradient from D M + M D^T (the basis gradient a constant map of the
    basis) holds where the supports vary: linear fields' gradients to round-off, and every
    grad N_I against central differences (h = 1e-6 mm, as above)."""
    particles, support, volumes = graded_arrangement()
    points = rng.uniform((0.0, 0.0), (40.0, 30.0), size=(200, 2))
    shape = rk_shape_functions(points, particles, support, volumes, 1, gradients=True)
    jacobian = np.stack([shape.grad_x @ particles, shape.grad_y @ particles], axis=2)
    np.testing.assert_allclose(jacobian, np.broadcast_to(np.eye(2), jacobian.shape), rtol=0, atol=1e-11)
    h = 1e-6
    for grad, step in ((shape.grad_x, (h, 0.0)), (shape.grad_y, (0.0, h))):
        forward = rk_shape_functions(points + step, particles, support, volumes, 1, False).values
        backward = rk_shape_functions(points - step, particles, support, volumes, 1, False).values
        scale = np.abs(grad.toarray()).max()
        np.testing.assert_allclose(grad.toarray(), ((forward - backward) / (2 * h)).toarray(), rtol=0,
                                   atol=1e-6 * scale)


def test_shape_functions_made_in_parts_are_the_whole_bit_for_bit(monkeypatch):
    """A calibration's 200 000 markers made N(X) in one go, peaking at 0.58 GB of moment matrices
    and bases for the 38 MB kept; made in equal parts, each as the whole would be, the matrices
    (and their gradients) are the same to the bit."""
    import stitchplan.tissue.model as tissue_model
    from stitchplan.config.scenario import parse_scenario
    from stitchplan.tissue.model import build_tissue_model

    scenario = parse_scenario({"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                                          "material": {"lame_lambda": 0.2, "lame_mu": 0.1},
                                          "holes": [{"circle": {"center": [20.0, 15.0], "radius": 4.0}}]},
                               "discretization": {"spacing": 2.0}})
    model = build_tissue_model(scenario.tissue, scenario.discretization)
    points = np.random.default_rng(3).uniform((0.0, 0.0), (40.0, 30.0), (2000, 2))
    points = points[scenario.tissue.domain.contains(points)]
    whole = model.shape_functions_at(points, gradients=True)
    monkeypatch.setattr(tissue_model, "POINTS_AT_ONCE", 300)
    parts = model.shape_functions_at(points, gradients=True)
    for name in ("values", "grad_x", "grad_y"):
        a, b = getattr(parts, name), getattr(whole, name)
        assert a.shape == b.shape and (a.indptr == b.indptr).all() and (a.indices == b.indices).all()
        np.testing.assert_array_equal(a.data, b.data)
