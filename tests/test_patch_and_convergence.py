"""Patch tests and the convergence rate under refinement.

All four edges are essential boundaries: every boundary particle gets its own prescribed
displacement (per-particle values for solver.solve_static), so any field can be imposed.

What the linear patch test shows for this discretization (figures in the README):

* the exact linear field d_I = A X_I + c is admissible: the transformation method keeps it
  to round-off;
* at free particles whose kernel support stays clear of the essential boundary the linear
  field is in equilibrium up to the quadrature error of the background cells, which falls
  from ~3e-2 (1 Gauss point per cell) to ~5e-7 (6 x 6 points): RK functions are rational,
  so no Gauss order integrates them exactly;
* at free particles next to the boundary the transformed functions N T (eq. 3.37) vanish
  at the boundary particles but not between them, so the discrete weak form keeps a
  boundary term oint Psi_J P N dGamma that no quadrature order removes (the nodal
  collocation inconsistency of the transformation method). The solved field therefore
  reproduces the linear field only to ~1.4e-3 relative at spacing 5 mm, an error that is
  O(h) and vanishes under refinement, not to round-off, for every quadrature order.

With `integration: vci` (variationally consistent integration of the test functions,
discretization.consistent_test_gradients) both defects are removed: the linear patch, small
or large, is reproduced to round-off at every quadrature order from 1 Gauss point per cell,
on uniform and graded particles, and the manufactured-solution rate stays optimal where
Gauss quadrature's falls off.
"""

from __future__ import annotations

import numpy as np
import pytest

from stitchplan.tissue.assembly import Assembler
from stitchplan.config.scenario import Discretization, Material, Solver, Tissue
from stitchplan.tissue.deform import interpolate
from stitchplan.tissue.model import build_tissue_model
from stitchplan.tissue.material import first_piola_and_tangent
from stitchplan.tissue.quadrature import segment_quadrature
from stitchplan.tissue.solver import solve_static

PATCH_SIZE = (40.0, 30.0)  # mm
SMALL_GRADIENT = 1e-3 * np.array([[1.0, -0.7], [0.4, 0.6]])  # A of u = A X + c
TRANSLATION = np.array([0.3, -0.2])  # c, mm


def patch_model(rectangle_edges, spacing=5.0, quadrature_order=2, material="saint-venant-kirchhoff",
                size=PATCH_SIZE, basis_order=1, dilation=2.0, integration="gauss", needle_spacing=None):
    tissue = Tissue(size, 2.0, Material(material, 0.5, 0.3), ())
    discretization = Discretization(spacing=spacing, dilation=dilation, quadrature_order=quadrature_order,
                                    basis_order=basis_order, integration=integration,
                                    needle_spacing=needle_spacing)
    zone = ((0.5 * size[0], 0.5 * size[1]), 0.2 * min(size), ()) if needle_spacing else None
    return build_tissue_model(tissue, discretization, rectangle_edges(*size), needle_zone=zone)


def solve_with_boundary_field(model, field, load_steps=1):
    """Prescribe u = field(X) at every boundary particle, no external force; returns coefficients."""
    prescribed = field(model.particles[model.boundary.indices])
    # the patch tests check the discretization to round-off: the solves must be converged that far
    solution = solve_static(model, np.zeros(2 * model.n_free), prescribed, load_steps,
                            Solver(residual_tolerance=1e-9))
    return solution.coefficients


def linear_field(gradient, translation=TRANSLATION):
    return lambda points: points @ np.asarray(gradient).T + translation


def interior_samples(rng, size=PATCH_SIZE, count=400):
    return rng.uniform((0.0, 0.0), size, size=(count, 2))


def relative_error(model, coefficients, field, points, translation=TRANSLATION):
    """max |u_h - u| over the points, relative to max |u - c| (the deformation part)."""
    exact = field(points)
    error = np.abs(interpolate(model, coefficients, points) - exact).max()
    return error / np.abs(exact - translation).max()


def test_linear_field_is_admissible_under_the_transformation(rectangle_edges):
    """d = T d_free + T_g g returns the linear coefficients exactly when g = u(X_b)."""
    model = patch_model(rectangle_edges)
    linear = linear_field(SMALL_GRADIENT)(model.particles)
    rebuilt = model.coefficients(linear[model.boundary.free_indices], linear[model.boundary.indices])
    np.testing.assert_allclose(rebuilt, linear, rtol=0, atol=1e-14 * np.abs(linear).max())


# Largest |f_J| / (|P| h t) of the exact linear field at free particles whose support stays
# clear of the boundary. Observed (independent of the spacing): 2.8e-2, 4.8e-3, 9.9e-5,
# 4.0e-5, 7.1e-6, 4.9e-7; bounds are twice the observation, so a quadrature or assembly
# regression shows up while the decay with the order is asserted below.
INTEGRATION_BOUND = {1: 6e-2, 2: 1e-2, 3: 2e-4, 4: 8e-5, 5: 1.5e-5, 6: 1e-6}


def interior_residual(model) -> float:
    """Largest |f_J| / (|P| h t) of the linear field at free particles clear of the boundary."""
    coefficients = linear_field(SMALL_GRADIENT)(model.particles)
    assembler = Assembler(model)
    force = assembler.update(model.deformation_gradient(coefficients)).reshape(-1, 2)
    first_piola, _ = first_piola_and_tangent(model.material, model.deformation_gradient(coefficients))
    np.testing.assert_allclose(first_piola, np.broadcast_to(first_piola[0], first_piola.shape), atol=1e-14)
    free_points = model.particles[model.boundary.free_indices]
    distance = np.minimum(free_points, np.asarray(model.tissue.size) - free_points).min(axis=1)
    clear = distance >= model.support.max() - 1e-9
    assert clear.sum() >= 10
    scale = np.linalg.norm(first_piola[0]) * model.spacing * model.tissue.thickness
    return np.linalg.norm(force[clear], axis=1).max() / scale


@pytest.mark.parametrize("quadrature_order", range(1, 7))
def test_linear_field_is_in_equilibrium_away_from_the_boundary(rectangle_edges, quadrature_order):
    model = patch_model(rectangle_edges, quadrature_order=quadrature_order)
    assert interior_residual(model) < INTEGRATION_BOUND[quadrature_order]


def test_interior_equilibrium_error_decays_with_the_quadrature_order(rectangle_edges):
    residuals = [interior_residual(patch_model(rectangle_edges, quadrature_order=q)) for q in range(1, 7)]
    assert all(later < earlier for earlier, later in zip(residuals, residuals[1:]))
    assert residuals[-1] < 1e-4 * residuals[0]


def test_linear_field_residual_is_exactly_the_collocation_boundary_term(rectangle_edges):
    """With a fine enough rule the residual of the linear field at the free coefficients is
    f_J = t oint Psi_J P N dGamma (divergence theorem, constant P): the whole patch-test
    defect comes from the transformed test functions Psi = N T not vanishing between the
    boundary particles, not from the assembly."""
    model = patch_model(rectangle_edges, quadrature_order=8)
    assembler = Assembler(model)
    coefficients = linear_field(SMALL_GRADIENT)(model.particles)
    deformation_gradient = model.deformation_gradient(coefficients)
    force = assembler.update(deformation_gradient).reshape(-1, 2)
    first_piola = first_piola_and_tangent(model.material, deformation_gradient)[0][0]  # homogeneous
    boundary_term = np.zeros_like(force)
    for start, end in rectangle_edges(*PATCH_SIZE):
        start, end = np.asarray(start), np.asarray(end)
        tangent = (end - start) / np.linalg.norm(end - start)
        normal = np.array([tangent[1], -tangent[0]])  # outward for the counter-clockwise edges
        points, weights = segment_quadrature(start, end, pieces=64, order=5)
        test_functions = model.shape_functions_at(points).values @ model.boundary.free_map  # Psi_J
        boundary_term += np.outer(test_functions.T @ weights, first_piola @ normal) * model.tissue.thickness
    assert np.abs(force).max() > 1e-3 * np.linalg.norm(first_piola) * model.spacing * model.tissue.thickness
    np.testing.assert_allclose(force, boundary_term, rtol=0, atol=1e-5 * np.abs(force).max())


# Relative interior error of the solved linear patch at spacing 5 mm (40 x 30 mm, 9 x 7
# particles, 48 cells; quadrature points 48, 192, 432, 768, 1200, 1728 for q = 1..6).
# Observed: q=1 7.1e-3; q=2 1.54e-3; q=3..6 1.27e-3-1.32e-3 (the collocation floor).
# Bounds: q=1 is under-integrated (a 5x larger error); from q=2 on the error sits at the
# boundary floor, asserted below 2e-3. No order reaches round-off (see the module docstring).
PATCH_BOUND = {1: 1e-2, 2: 2e-3, 3: 2e-3, 4: 2e-3, 5: 2e-3, 6: 2e-3}


@pytest.mark.parametrize("quadrature_order", range(1, 7))
def test_linear_patch_small_gradient(rectangle_edges, rng, quadrature_order):
    model = patch_model(rectangle_edges, quadrature_order=quadrature_order)
    field = linear_field(SMALL_GRADIENT)
    coefficients = solve_with_boundary_field(model, field)
    error = relative_error(model, coefficients, field, interior_samples(rng))
    assert error < PATCH_BOUND[quadrature_order]


def test_linear_patch_error_vanishes_under_refinement(rectangle_edges, rng):
    """The patch-test defect is a consistency error of order h: halving the spacing halves it."""
    field = linear_field(SMALL_GRADIENT)
    samples = interior_samples(rng)
    spacings = np.array([10.0, 5.0, 2.5])
    errors = [relative_error(model, solve_with_boundary_field(model, field), field, samples)
              for model in (patch_model(rectangle_edges, spacing=s, quadrature_order=3) for s in spacings)]
    slope = np.polyfit(np.log(spacings), np.log(errors), 1)[0]  # observed 1.16: 2.9e-3, 1.3e-3, 5.9e-4
    assert slope > 0.9
    assert errors[-1] < 1e-3


LARGE_HOMOGENEOUS = np.array([[1.2, 0.05], [0.0, 1.0]]) - np.eye(2)  # 20 % stretch plus 5 % shear


@pytest.mark.parametrize("material", ["saint-venant-kirchhoff", "neo-hookean"])
def test_large_homogeneous_deformation_patch(rectangle_edges, rng, material):
    """A homogeneous F is an exact nonlinear solution; the solve reproduces it to the same
    collocation floor as the small patch (observed 6.6e-4 relative for SVK, 8.8e-4 neo-Hookean)."""
    model = patch_model(rectangle_edges, quadrature_order=3, material=material)
    field = linear_field(LARGE_HOMOGENEOUS)
    coefficients = solve_with_boundary_field(model, field, load_steps=2)
    assert relative_error(model, coefficients, field, interior_samples(rng)) < 2e-3
    deformation_gradient = model.deformation_gradient(coefficients)
    assert np.abs(deformation_gradient - (np.eye(2) + LARGE_HOMOGENEOUS)).mean() < 5e-3


# --- convergence under refinement against an analytical solution -----------------------

SQUARE = (40.0, 40.0)
AMPLITUDE = 1e-6  # 1/mm: strains ~4e-5, so the SVK nonlinearity is ~1e-5 of the response


def harmonic_field(points: np.ndarray) -> np.ndarray:
    """u = eps (x^2 - y^2, -2 x y) about the centre: harmonic and divergence free, so it solves
    the Navier equations without body force for any Lame constants."""
    x, y = points[:, 0] - SQUARE[0] / 2, points[:, 1] - SQUARE[1] / 2
    return AMPLITUDE * np.stack([x * x - y * y, -2.0 * x * y], axis=1)


def l2_error(model, coefficients) -> float:
    """Relative L2 norm of u_h - u over the quadrature points."""
    difference = model.shape.values @ coefficients - harmonic_field(model.quadrature_points)
    weights = model.quadrature_weights
    exact = harmonic_field(model.quadrature_points)
    return float(np.sqrt(weights @ (difference**2).sum(1) / (weights @ (exact**2).sum(1))))


@pytest.mark.parametrize("quadrature_order", [2, 3])
def test_linear_basis_converges_at_second_order(rectangle_edges, quadrature_order):
    """Fitted log-log slope of the L2 error over spacings 10, 5, 2.5 mm.

    Observed: 1.96 with q = 2 (errors 2.2e-2, 5.2e-3, 1.4e-3) and 2.35 with q = 3 (1.9e-2,
    3.8e-3, 7.3e-4). With q = 2 the local slope keeps falling on finer grids (1.84, 1.63,
    1.54 down to 0.625 mm) as the quadrature error takes over; with q = 3 it stays >= 2.1."""
    spacings = np.array([10.0, 5.0, 2.5])
    errors = []
    for spacing in spacings:
        model = patch_model(rectangle_edges, spacing=spacing, quadrature_order=quadrature_order, size=SQUARE)
        errors.append(l2_error(model, solve_with_boundary_field(model, harmonic_field)))
    slope = np.polyfit(np.log(spacings), np.log(errors), 1)[0]
    assert slope >= 1.8
    assert errors[-1] < 2e-3


# --- variationally consistent integration (integration: vci) ----------------------------


@pytest.mark.parametrize("quadrature_order", [1, 2, 3])
@pytest.mark.parametrize("needle_spacing", [None, 1.25], ids=["uniform", "graded"])
def test_vci_passes_the_linear_patch_test_to_round_off(rectangle_edges, rng, quadrature_order, needle_spacing):
    """Observed 2e-14 (uniform, 5 mm) to 1e-12: the Gauss defect of ~1e-3 is gone."""
    model = patch_model(rectangle_edges, quadrature_order=quadrature_order, integration="vci",
                        needle_spacing=needle_spacing)
    field = linear_field(SMALL_GRADIENT)
    coefficients = solve_with_boundary_field(model, field)
    assert relative_error(model, coefficients, field, interior_samples(rng)) < 1e-10


@pytest.mark.parametrize("material", ["saint-venant-kirchhoff", "neo-hookean"])
def test_vci_reproduces_a_large_homogeneous_deformation_to_round_off(rectangle_edges, rng, material):
    model = patch_model(rectangle_edges, quadrature_order=2, material=material, integration="vci")
    field = linear_field(LARGE_HOMOGENEOUS)
    coefficients = solve_with_boundary_field(model, field, load_steps=2)
    assert relative_error(model, coefficients, field, interior_samples(rng)) < 1e-10
    np.testing.assert_allclose(model.deformation_gradient(coefficients),
                               np.broadcast_to(np.eye(2) + LARGE_HOMOGENEOUS, (len(model.quadrature_weights), 2, 2)),
                               rtol=0, atol=1e-10)


def test_vci_test_gradients_satisfy_the_discrete_divergence_theorem():
    """sum_q grad~Psi_J w_q = int over the natural boundary of Psi_J N, checked against an
    independent fine rule on the edges that are not clamped (the right edge is)."""
    size = (20.0, 10.0)
    tissue = Tissue(size, 2.0, Material("saint-venant-kirchhoff", 0.5, 0.3), ("right",))
    model = build_tissue_model(tissue, Discretization(spacing=2.5, quadrature_order=2, integration="vci"))
    weights = model.quadrature_weights / model.tissue.thickness
    sums = []
    for direction in range(2):  # P = e_x (x) e_direction picks d Psi_J / d X_direction, component x
        unit = np.zeros(4)
        unit[direction] = 1.0
        sums.append((model.test_gradient.T @ np.kron(weights, unit))[0::2])
    expected = np.zeros((model.n_free, 2))
    natural = [((0.0, 0.0), (20.0, 0.0), (0.0, -1.0)), ((20.0, 10.0), (0.0, 10.0), (0.0, 1.0)),
               ((0.0, 10.0), (0.0, 0.0), (-1.0, 0.0))]
    for start, end, normal in natural:
        points, lengths = segment_quadrature(start, end, pieces=64, order=5)
        psi = model.shape_functions_at(points).values @ model.boundary.free_map
        expected += np.outer(psi.T @ lengths, normal)
    scale = np.abs(expected).max()
    # the two boundary rules (VCI's: order 4 per 2.5 mm; here: order 5 per 0.3 mm) differ by
    # the integration error of the rational RK functions, observed 5e-6 x scale
    np.testing.assert_allclose(np.stack(sums, axis=1), expected, rtol=0, atol=5e-5 * scale)
    # the uncorrected Gauss sums miss it by far more
    plain = (model.gradient.T @ np.kron(weights, [1.0, 0.0, 0.0, 0.0]))[0::2]
    assert np.abs(plain - expected[:, 0]).max() > 100 * 5e-5 * scale


def test_vci_keeps_the_optimal_rate_where_gauss_quadrature_loses_it(rectangle_edges):
    """Manufactured solution, q = 2, spacings 10 ... 1.25 mm: the last local slope is
    observed 2.45 with vci against 1.63 with Gauss (errors 1.4e-4 against 4.7e-4)."""
    spacings = np.array([10.0, 5.0, 2.5, 1.25])
    slopes, finest = {}, {}
    for integration in ("gauss", "vci"):
        errors = []
        for spacing in spacings:
            model = patch_model(rectangle_edges, spacing=spacing, quadrature_order=2, size=SQUARE,
                                integration=integration)
            errors.append(l2_error(model, solve_with_boundary_field(model, harmonic_field)))
        slopes[integration] = np.log(errors[-2] / errors[-1]) / np.log(spacings[-2] / spacings[-1])
        finest[integration] = errors[-1]
    assert slopes["vci"] >= 2.2 and slopes["gauss"] < 1.9, slopes
    assert finest["vci"] < 0.5 * finest["gauss"], finest
