"""Assembled internal force and tangent stiffness (eq. 3.44-3.57) on a small slab: the
tangent is the derivative of the force, the matrix-free product is the matrix, K is
symmetric, and the force is the derivative of the stored energy."""

from __future__ import annotations

import numpy as np
import pytest

from stitchplan.tissue.assembly import Assembler, stiffness_at_rest
from stitchplan.tissue.material import first_piola
from stitchplan.config.scenario import Discretization, Material, Tissue
from stitchplan.tissue.model import build_tissue_model

SIZE = (20.0, 10.0)  # mm
RIGHT_EDGE = ((20.0, 0.0), (20.0, 10.0))  # prescribed-displacement segment
STEP = 1e-6  # mm, central differences on the coefficients

CASES = [
    pytest.param("saint-venant-kirchhoff", 1, 2.0, id="svk-linear"),
    pytest.param("neo-hookean", 1, 2.0, id="neo-hookean-linear"),
    pytest.param("neo-hookean", 2, 3.0, id="neo-hookean-quadratic"),
]


def small_model(material: str, basis_order: int = 1, dilation: float = 2.0, clamped=("left",),
                segments=(RIGHT_EDGE,), integration: str = "gauss"):
    """9 x 5 particles, clamped left edge and a prescribed right edge: 35 free particles."""
    tissue = Tissue(SIZE, 2.0, Material(material, 0.5, 0.3), tuple(clamped))
    discretization = Discretization(spacing=2.5, dilation=dilation, basis_order=basis_order,
                                    integration=integration)
    return build_tissue_model(tissue, discretization, tuple(segments))


def moderate_state(model, rng):
    """Free coefficients (2 n_free,) and prescribed g (Nb, 2): a smooth bend-and-shear field
    plus noise; |F - I| up to ~0.3, det F well above zero."""
    def smooth(points):
        x, y = points[:, 0] / SIZE[0], points[:, 1] / SIZE[1]
        return np.stack([1.5 * x * y - 0.8 * y, 3.0 * x * x + 0.5 * x * y], axis=1)

    free_points = model.particles[model.boundary.free_indices]
    free = smooth(free_points) + 0.15 * rng.standard_normal(free_points.shape)
    prescribed = smooth(model.particles[model.boundary.indices])
    return free.ravel(), prescribed


def internal_force(model, assembler, free, prescribed):
    coefficients = model.coefficients(free.reshape(-1, 2), prescribed)
    return assembler.update(model.deformation_gradient(coefficients))


@pytest.mark.parametrize("material, basis_order, dilation, integration", [
    *[pytest.param(*case.values, "gauss", id=case.id) for case in CASES],
    pytest.param("saint-venant-kirchhoff", 1, 2.0, "vci", id="svk-linear-vci"),
    pytest.param("neo-hookean", 1, 2.0, "vci", id="neo-hookean-linear-vci"),
])
def test_tangent_matches_finite_differences_of_internal_force(material, basis_order, dilation, integration, rng):
    """K = dF_int/dd, also for the nonsymmetric Petrov-Galerkin tangent of integration vci."""
    model = small_model(material, basis_order, dilation, integration=integration)
    assembler = Assembler(model)
    free, prescribed = moderate_state(model, rng)
    deformation_gradient = model.deformation_gradient(model.coefficients(free.reshape(-1, 2), prescribed))
    jacobian = np.linalg.det(deformation_gradient)
    assert 0.4 < jacobian.min() and np.abs(deformation_gradient - np.eye(2)).max() > 0.15  # moderate, not tiny

    _, tangent = assembler.force_and_tangent(deformation_gradient)
    tangent = tangent.toarray()
    finite_difference = np.empty_like(tangent)
    for j in range(len(free)):
        step = np.zeros_like(free)
        step[j] = STEP
        finite_difference[:, j] = (internal_force(model, assembler, free + step, prescribed)
                                   - internal_force(model, assembler, free - step, prescribed)) / (2 * STEP)
    # observed ~1e-10 relative; a missing geometric (stress) term is O(|S| / |A|) ~ 1e-2
    np.testing.assert_allclose(tangent, finite_difference, rtol=0, atol=1e-6 * np.abs(tangent).max())


@pytest.mark.parametrize("material, basis_order, dilation", CASES)
def test_tangent_product_equals_tangent_matrix_and_is_symmetric(material, basis_order, dilation, rng):
    model = small_model(material, basis_order, dilation)
    assembler = Assembler(model)
    free, prescribed = moderate_state(model, rng)
    internal_force(model, assembler, free, prescribed)
    matrix = assembler.tangent_matrix()
    scale = abs(matrix).max()
    for _ in range(3):
        vector = rng.standard_normal(len(free))
        np.testing.assert_allclose(assembler.tangent_product(vector), matrix @ vector, rtol=0,
                                   atol=1e-13 * scale * np.abs(vector).sum())
    np.testing.assert_allclose(matrix.toarray(), matrix.T.toarray(), rtol=0, atol=1e-13 * scale)


@pytest.mark.parametrize("material", ["saint-venant-kirchhoff", "neo-hookean"])
def test_internal_force_is_the_stored_energy_gradient(material, rng):
    """f_int = d/dd sum_q w_q W(F_q): the assembly integrates the same energy it differentiates."""
    model = small_model(material)
    assembler = Assembler(model)
    free, prescribed = moderate_state(model, rng)

    def stored_energy(x):
        coefficients = model.coefficients(x.reshape(-1, 2), prescribed)
        return model.quadrature_weights @ model.material.energy(model.deformation_gradient(coefficients))

    force = internal_force(model, assembler, free, prescribed)
    finite_difference = np.array([
        (stored_energy(free + STEP * e) - stored_energy(free - STEP * e)) / (2 * STEP)
        for e in np.eye(len(free))
    ])
    np.testing.assert_allclose(force, finite_difference, rtol=0, atol=1e-6 * np.abs(force).max())


@pytest.mark.parametrize("integration", ["gauss", "vci"])
def test_internal_force_reads_the_gradient_operator_itself(integration, rng):
    """f_int = B^T (w P) is taken on the transposed view of B (or B~), no copy of it kept, and
    equals the product with an explicit CSR B^T to the last bit (the same terms added in the
    same order), so residuals, and the runs and plans made of them, are those of a CSR B^T."""
    model = small_model("saint-venant-kirchhoff", integration=integration)
    assembler = Assembler(model)
    test = model.gradient if model.test_gradient is None else model.test_gradient
    assert np.shares_memory(assembler.gradient_t.data, test.data)
    free, prescribed = moderate_state(model, rng)
    force = internal_force(model, assembler, free, prescribed)
    coefficients = model.coefficients(free.reshape(-1, 2), prescribed)
    stress = first_piola(model.material, model.deformation_gradient(coefficients))
    explicit = test.T.tocsr() @ (stress * model.quadrature_weights[:, None, None]).reshape(-1)
    assert np.array_equal(force, explicit)


@pytest.mark.parametrize("material", ["saint-venant-kirchhoff", "neo-hookean"])
def test_reference_tangent_is_positive_definite_once_clamped(material):
    """At F = I the clamped slab has no rigid modes left: K is SPD (the transformation method
    removed the constrained coefficients from the unknowns)."""
    model = small_model(material, segments=())
    assembler = Assembler(model)
    _, tangent = assembler.force_and_tangent(np.broadcast_to(np.eye(2), (len(model.quadrature_weights), 2, 2)))
    eigenvalues = np.linalg.eigvalsh(tangent.toarray())
    assert eigenvalues[0] > 1e-6 * eigenvalues[-1]


@pytest.mark.parametrize("material, basis_order, dilation", CASES)
def test_stiffness_at_rest_is_the_tangent_at_zero_deformation(material, basis_order, dilation):
    """K0 from the direction gradients' isotropic blocks equals B^T diag(w A) B at F = I."""
    model = small_model(material, basis_order, dilation)
    assembler = Assembler(model)
    _, tangent = assembler.force_and_tangent(np.broadcast_to(np.eye(2), (len(model.quadrature_weights), 2, 2)))
    at_rest = stiffness_at_rest(model)
    assert abs(at_rest - tangent).max() < 1e-13 * abs(tangent).max()


def test_stiffness_at_rest_of_material_regions():
    """Each quadrature point's own lambda and mu (a layered tissue, PointwiseMaterial)."""
    from conftest import CONFIGS
    from stitchplan.config.scenario import load_scenario
    from stitchplan.needle.prepared_tissue import PreparedTissue
    from stitchplan.tissue.material import PointwiseMaterial

    model = PreparedTissue(load_scenario(CONFIGS / "skin_layered.yaml")).model
    assert isinstance(model.material, PointwiseMaterial) and len(model.material.parts) > 1
    assembler = Assembler(model)
    _, tangent = assembler.force_and_tangent(np.broadcast_to(np.eye(2), (len(model.quadrature_weights), 2, 2)))
    assert abs(stiffness_at_rest(model) - tangent).max() < 1e-13 * abs(tangent).max()


@pytest.mark.parametrize("material", ["saint-venant-kirchhoff", "neo-hookean"])
def test_rigid_rotation_gives_no_internal_force(material):
    """d_I = (R - I) X_I + c reproduces F = R exactly (linear reproduction), so S = 0 and f_int = 0
    at every particle of an unconstrained slab, however large the rotation."""
    model = small_model(material, clamped=(), segments=())
    assert model.n_free == model.n_particles
    assembler = Assembler(model)
    angle = 1.2
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    coefficients = model.particles @ (rotation - np.eye(2)).T + np.array([3.0, -1.0])
    deformation_gradient = model.deformation_gradient(coefficients)
    np.testing.assert_allclose(deformation_gradient, np.broadcast_to(rotation, deformation_gradient.shape),
                               atol=1e-13)
    force = assembler.update(deformation_gradient)
    # scale: the force a 1 % strain would produce on one particle, lame_mu x spacing x thickness
    assert np.abs(force).max() < 1e-10 * 0.3 * 2.5 * 2.0


@pytest.mark.parametrize("order", [1, 2, 3])
def test_cell_quadrature_integrates_polynomials_exactly_on_oblong_cells(order):
    """The background cells' tensor Gauss rule on a 3 x 2 mm domain in 2 x 3 cells (oblong,
    unlike the patch tests' square ones): every point inside its cell, and x^a y^b integrated
    exactly up to degree 2 order - 1 in each variable: W^(a+1) H^(b+1) / ((a+1)(b+1))."""
    from stitchplan.tissue.quadrature import cell_quadrature

    (width, height), (nx, ny) = (3.0, 2.0), (2, 3)
    points, weights = cell_quadrature((width, height), (nx, ny), order)
    assert len(points) == nx * ny * order**2
    cell = np.floor(points / [width / nx, height / ny]).astype(int)
    assert np.all(np.bincount(cell[:, 0] * ny + cell[:, 1], minlength=nx * ny) == order**2)  # each cell its own
    for a in range(2 * order):
        for b in range(2 * order):
            exact = width ** (a + 1) * height ** (b + 1) / ((a + 1) * (b + 1))
            assert weights @ (points[:, 0] ** a * points[:, 1] ** b) == pytest.approx(exact, rel=1e-12), (a, b)


def test_the_needle_tracks_two_point_rule_integrates_cubics_exactly():
    """load_quadrature.segment_gauss_points: the two-point Gauss rule on each of `pieces`
    pieces of [0, 1], each point weighing 1 / (2 pieces), is exact for cubics."""
    from stitchplan.needle.load_quadrature import segment_gauss_points

    for pieces in (1, 3):
        s = segment_gauss_points(pieces)
        for degree in range(4):
            assert np.sum(s**degree) / (2 * pieces) == pytest.approx(1.0 / (degree + 1), rel=1e-13), (pieces, degree)


@pytest.mark.parametrize("essential", [
    pytest.param((), id="whole-boundary"),
    pytest.param((((3.0, 0.0), (3.0, 2.0)),), id="right-edge-clamped"),
    pytest.param((((1.0, 2.0), (2.5, 2.0)),), id="segment-inside-the-top-edge"),
])
def test_natural_boundary_rule_has_outward_normals_and_satisfies_the_divergence_theorem(essential):
    """quadrature.natural_boundary_quadrature, the boundary side of integration vci, on a
    3 x 2 mm rectangle: every point on the boundary and off the essential pieces, each normal
    the outward one of its edge, and the rule integrates x n_x, y n_y and n exactly as the
    divergence theorem over the kept edges says (x n_x is x on the right edge, 0 on the left)."""
    from stitchplan.tissue.quadrature import natural_boundary_quadrature

    width, height = 3.0, 2.0
    points, normals, weights = natural_boundary_quadrature((width, height), list(essential), interval=0.4, order=3)
    x, y = points[:, 0], points[:, 1]
    on_edge = np.isclose(x, 0.0) | np.isclose(x, width) | np.isclose(y, 0.0) | np.isclose(y, height)
    assert np.all(on_edge) and np.all(weights > 0.0)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=0, atol=1e-15)
    outside = points + 1e-3 * normals  # a step along an outward normal leaves the rectangle
    assert not np.any((outside[:, 0] > 0.0) & (outside[:, 0] < width) & (outside[:, 1] > 0.0)
                      & (outside[:, 1] < height))
    for start, end in essential:  # no point on an essential piece
        (x0, y0), (x1, y1) = start, end
        on_piece = ((np.abs((x1 - x0) * (y - y0) - (y1 - y0) * (x - x0)) < 1e-12)
                    & (x >= min(x0, x1) - 1e-12) & (x <= max(x0, x1) + 1e-12)
                    & (y >= min(y0, y1) - 1e-12) & (y <= max(y0, y1) + 1e-12))
        assert not on_piece.any()
    # per edge (bottom, right, top, left): length kept, and its x n_x and y n_y integrals
    removed = {"right": 2.0 if essential and essential[0][0] == (3.0, 0.0) else 0.0,
               "top": 1.5 if essential and essential[0][0] == (1.0, 2.0) else 0.0}
    kept_right, kept_top = 2.0 - removed["right"], 3.0 - removed["top"]
    # the rule rounds each edge's break points to multiples of 1e-9 x the longest side, so an
    # edge's length comes out within ~2e-9 mm of its own: bounds of 1e-8 (a wrong normal or a
    # piece left in changes these sums by a whole edge)
    assert weights.sum() == pytest.approx(2 * (width + height) - sum(removed.values()), abs=1e-8)
    assert weights @ (x * normals[:, 0]) == pytest.approx(width * kept_right, abs=1e-8)
    assert weights @ (y * normals[:, 1]) == pytest.approx(height * kept_top, abs=1e-8)
    expected_normal_sum = np.array([kept_right - 2.0, kept_top - 3.0])  # the closed boundary's is zero
    np.testing.assert_allclose(weights @ normals, expected_normal_sum, rtol=0, atol=1e-8)
