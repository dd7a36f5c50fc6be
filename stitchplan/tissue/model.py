"""The discretized tissue: particles, quadrature, shape functions and essential boundaries.

Everything here lives in the reference configuration and is computed once per
discretization (Total-Lagrangian formulation); the solver only refills values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .boundary_conditions import EssentialBoundary, boundary_particles, transformation
from ..config import Discretization, Scenario, ScenarioError, Tissue
from .material import NeoHookean, SaintVenantKirchhoff, make_material
from .quadrature import cell_quadrature, natural_boundary_quadrature
from .shape_functions import (ShapeFunctions, ShapePairs, SingularMomentMatrix, rk_shape_functions,
                              rk_shape_pairs)


def grid_particles(size: tuple[float, float], spacing: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Particles on a regular grid covering [0, W] x [0, H], and their tributary areas.

    The spacing is adjusted per direction so the grid ends exactly on the edges.
    Returns particles (NP, 2), volumes (NP,), dx, dy.
    """
    width, height = size
    nx = max(int(round(width / spacing)), 1)
    ny = max(int(round(height / spacing)), 1)
    x = np.linspace(0.0, width, nx + 1)
    y = np.linspace(0.0, height, ny + 1)
    particles = np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1).reshape(-1, 2)
    dx, dy = width / nx, height / ny
    wx = np.full(nx + 1, dx)
    wx[[0, -1]] *= 0.5
    wy = np.full(ny + 1, dy)
    wy[[0, -1]] *= 0.5
    volumes = np.outer(wx, wy).ravel()
    return particles, volumes, dx, dy


@dataclass(frozen=True)
class GradedParticles:
    """Particles at the corners of the leaf cells of a balanced quadtree over the slab."""

    particles: np.ndarray  # (NP, 2)
    volumes: np.ndarray  # (NP,) tributary areas: a quarter of each adjacent leaf cell
    local_spacing: np.ndarray  # (NP,) largest side of the leaf cells meeting at the particle
    cells: np.ndarray  # (nc, 4) leaf cells: x0, y0, width, height (mm)
    fine_spacing: float  # leaf side near the needle (mm)
    coarse_spacing: float  # leaf side far from it (mm)


def graded_particles(size: tuple[float, float], spacing: float, fine_spacing: float,
                     center: np.ndarray, radius: float, growth: float = 0.5) -> GradedParticles:
    """A particle set graded toward a disk (the needle's zone): leaf cells of side
    ~`fine_spacing` within `radius` of `center`, the side allowed to grow by `growth` mm per
    mm of distance beyond it, up to ~`spacing` (coarse side = fine x 2^L, L the nearest
    integer); neighbouring leaves differ by at most one level (2:1 balance), so the local
    spacing, and with it the kernel support, varies smoothly.

    Particles sit at the leaf corners (hanging corners included, as meshfree allows), with
    volume a quarter of each adjacent leaf, so the volumes sum to the slab's area.
    """
    from scipy.ndimage import maximum_filter

    width, height = size
    levels = max(int(round(np.log2(spacing / fine_spacing))), 0)
    base = fine_spacing * 2**levels
    nx0, ny0 = max(int(round(width / base)), 1), max(int(round(height / base)), 1)
    n = 2**levels
    fx, fy = nx0 * n, ny0 * n  # finest lattice: fx x fy cells
    fdx, fdy = width / fx, height / fy
    side0 = max(width / nx0, height / ny0)
    xc = (np.arange(fx) + 0.5) * fdx
    yc = (np.arange(fy) + 0.5) * fdy
    distance = np.hypot(xc[:, None] - center[0], yc[None, :] - center[1]) - radius  # (fx, fy)
    target = fine_spacing * (1.0 + 1e-9) + growth * np.maximum(distance, 0.0)
    required = np.clip(np.ceil(np.log2(side0 / target)), 0, levels).astype(int)

    def leaf_levels(required: np.ndarray) -> np.ndarray:
        """Level of the leaf holding each finest cell: the smallest l whose level-l ancestor
        needs no split (no finest cell inside asks for more than l)."""
        leaf = np.full_like(required, levels)
        for level in range(levels - 1, -1, -1):
            b = 2 ** (levels - level)
            block = required.reshape(fx // b, b, fy // b, b).max(axis=(1, 3))
            leaf = np.where(np.repeat(np.repeat(block, b, 0), b, 1) <= level, level, leaf)
        return leaf

    leaf = leaf_levels(required)
    while True:  # 2:1 balance: a leaf's neighbours are at most one level coarser
        balanced = np.maximum(required, maximum_filter(leaf, size=3, mode="nearest") - 1)
        if np.array_equal(balanced, required):
            break
        required = balanced
        leaf = leaf_levels(required)

    corners, sides = [], []
    i, j = np.meshgrid(np.arange(fx), np.arange(fy), indexing="ij")
    for level in range(levels + 1):
        b = 2 ** (levels - level)
        first = (leaf == level) & (i % b == 0) & (j % b == 0)
        corners.append(np.stack([i[first], j[first]], axis=1))
        sides.append(np.full(int(first.sum()), b))
    corner = np.concatenate(corners)  # (nc, 2) lower-left corner on the finest lattice
    side = np.concatenate(sides)  # (nc,) in finest cells
    offsets = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])
    lattice = corner[:, None, :] + offsets[None] * side[:, None, None]  # (nc, 4, 2)
    keys = lattice[..., 0] * (fy + 1) + lattice[..., 1]
    unique, inverse = np.unique(keys.ravel(), return_inverse=True)
    particles = np.stack([unique // (fy + 1) / fx * width, unique % (fy + 1) / fy * height], axis=1)
    cell_w, cell_h = side * fdx, side * fdy
    volumes = np.zeros(len(unique))
    np.add.at(volumes, inverse, np.repeat(cell_w * cell_h / 4.0, 4))
    local = np.zeros(len(unique))
    np.maximum.at(local, inverse, np.repeat(np.maximum(cell_w, cell_h), 4))
    cells = np.column_stack([corner[:, 0] * fdx, corner[:, 1] * fdy, cell_w, cell_h])
    return GradedParticles(particles, volumes, local, cells, max(fdx, fdy), max(fdx, fdy) * n)


def leaf_quadrature(cells: np.ndarray, order: int, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule of `order` points per direction on each of subdivisions^2 sub-cells of every
    leaf cell (nc, 4: x0, y0, width, height). Returns points (n, 2), weights (n,) (mm^2)."""
    unit_points, unit_weights = cell_quadrature((1.0, 1.0), (subdivisions, subdivisions), order)
    origin, extent = cells[:, None, :2], cells[:, None, 2:]  # (nc, 1, 2)
    points = origin + unit_points[None] * extent  # (nc, g, 2)
    weights = unit_weights[None] * (cells[:, 2] * cells[:, 3])[:, None]
    return points.reshape(-1, 2), weights.ravel()


@dataclass
class TissueModel:
    """Particles, RK shape functions at the quadrature points and the boundary transformation.

    The gradient operator `gradient` maps free coefficients (interleaved x, y per free
    particle) to the four displacement-gradient components per quadrature point, rows
    ordered (point, 2 i + J) for du_i/dX_J; it already contains the transformation of
    eq. 3.37, so the solver works on free coefficients only.
    """

    tissue: Tissue
    discretization: Discretization
    material: SaintVenantKirchhoff | NeoHookean
    particles: np.ndarray  # (NP, 2)
    support: np.ndarray  # (NP,)
    volumes: np.ndarray  # (NP,)
    tree: cKDTree
    quadrature_points: np.ndarray  # (nq, 2)
    quadrature_weights: np.ndarray  # (nq,) area x thickness, mm^3
    shape: ShapeFunctions  # raw RK functions at quadrature points
    boundary: EssentialBoundary
    gradient: sp.csr_matrix  # (4 nq, 2 n_free)
    spacing: float
    # gradients of the test functions when they differ from the trial ones (integration
    # "vci"); None: Galerkin, test = trial, symmetric tangent
    test_gradient: sp.csr_matrix | None = None

    @property
    def symmetric(self) -> bool:
        return self.test_gradient is None

    @property
    def n_particles(self) -> int:
        return len(self.particles)

    @property
    def n_free(self) -> int:
        return self.boundary.n_free

    def _shape_pairs(self, points: np.ndarray, gradients: bool) -> ShapePairs:
        return rk_shape_pairs(points, self.particles, self.support, self.volumes,
                              self.discretization.basis_order, gradients, self.tree, self.basis_scale)

    def shape_functions_at(self, points: np.ndarray, gradients: bool = False) -> ShapeFunctions:
        points = np.atleast_2d(points)
        return self._shape_pairs(points, gradients).matrices(len(points), self.n_particles)

    def field_at(self, points: np.ndarray, coefficients: np.ndarray, gradients: bool = False):
        """u(X) (n, 2) from particle coefficients (NP, 2) and, with gradients, du_i/dX_J (n, 2, 2)."""
        return self._shape_pairs(np.atleast_2d(points), gradients).field(coefficients)

    @property
    def basis_scale(self) -> float:
        return float(self.support.mean())

    def coefficients(self, free: np.ndarray, prescribed: np.ndarray) -> np.ndarray:
        """Full particle coefficients d (NP, 2) from free ones (n_free, 2) and prescribed g (Nb, 2)."""
        return self.boundary.full(free, prescribed)

    def deformation_gradient(self, coefficients: np.ndarray) -> np.ndarray:
        """F = I + grad u at the quadrature points, (nq, 2, 2)."""
        gx = self.shape.grad_x @ coefficients  # (nq, 2): du_i/dX
        gy = self.shape.grad_y @ coefficients
        return np.stack([gx, gy], axis=2) + np.eye(2)


def build_tissue_model(
    tissue: Tissue,
    discretization: Discretization,
    prescribed_segments: tuple[tuple[tuple[float, float], tuple[float, float]], ...] = (),
    needle_zone: tuple[tuple[float, float], float] | None = None,
) -> TissueModel:
    """Discretize the slab: particles, quadrature, shape functions and the essential boundary.

    With discretization.needle_spacing set, the particles are graded toward `needle_zone`
    (centre, radius in mm; see graded_particles) and each particle's kernel support is the
    dilation times its local spacing; otherwise they form a uniform grid.
    """
    if discretization.needle_spacing is not None:
        if needle_zone is None:
            raise ScenarioError("discretization.needle_spacing: needs a needle to grade the "
                                "particles toward; remove it or add a `needle:` block")
        graded = graded_particles(tissue.size, discretization.spacing, discretization.needle_spacing,
                                  np.asarray(needle_zone[0], dtype=float), float(needle_zone[1]))
        particles, volumes = graded.particles, graded.volumes
        spacing = graded.fine_spacing
        support = discretization.dilation * graded.local_spacing
        points, weights = leaf_quadrature(graded.cells, discretization.quadrature_order,
                                          discretization.cells_per_spacing)
    else:
        particles, volumes, dx, dy = grid_particles(tissue.size, discretization.spacing)
        spacing = max(dx, dy)
        support = np.full(len(particles), discretization.dilation * spacing)
        n_cells = (
            int(round(tissue.size[0] / dx)) * discretization.cells_per_spacing,
            int(round(tissue.size[1] / dy)) * discretization.cells_per_spacing,
        )
        points, weights = cell_quadrature(tissue.size, n_cells, discretization.quadrature_order)
    tree = cKDTree(particles)
    order = discretization.basis_order
    constrained = boundary_particles(particles, tissue, prescribed_segments, spacing)
    try:  # at the quadrature points, then at the boundary particles (eq. 3.31)
        shape = rk_shape_functions(points, particles, support, volumes, order, True, tree,
                                   float(support.mean()))
        at_boundary = rk_shape_functions(particles[constrained.indices], particles, support, volumes,
                                         order, False, tree, float(support.mean())).values
    except SingularMomentMatrix as error:
        raise ScenarioError(
            f"discretization: dilation {discretization.dilation:g} with spacing "
            f"{discretization.spacing:g} mm (basis order {order}, quadrature order "
            f"{discretization.quadrature_order}) gives a singular RK moment matrix ({error})"
        ) from None
    boundary = transformation(at_boundary, constrained, len(particles))
    free_map = boundary.free_map
    grad_x, grad_y = shape.grad_x @ free_map, shape.grad_y @ free_map
    gradient = _gradient_operator(grad_x, grad_y)
    test_gradient = None
    if discretization.integration == "vci":
        essential = [(np.asarray(a, float), np.asarray(b, float)) for a, b in prescribed_segments]
        essential += [tissue.domain.edge(edge) for edge in tissue.clamped]
        boundary_points, normals, boundary_weights = natural_boundary_quadrature(
            tissue.size, essential, spacing, discretization.quadrature_order + 2)
        at_natural = (rk_shape_functions(boundary_points, particles, support, volumes, order, False, tree,
                                         float(support.mean())).values @ free_map
                      if len(boundary_points) else sp.csr_matrix((0, free_map.shape[1])))
        test_gradient = _gradient_operator(*consistent_test_gradients(
            shape.values @ free_map, grad_x, grad_y, weights, at_natural, normals, boundary_weights))
    return TissueModel(
        tissue=tissue,
        discretization=discretization,
        material=make_material(tissue.material),
        particles=particles,
        support=support,
        volumes=volumes,
        tree=tree,
        quadrature_points=points,
        quadrature_weights=weights * tissue.thickness,
        shape=shape,
        boundary=boundary,
        gradient=gradient,
        spacing=spacing,
        test_gradient=test_gradient,
    )


def model_for_scenario(scenario: Scenario,
                       needle_zone: tuple[tuple[float, float], float] | None = None) -> TissueModel:
    """The model of a scenario's tissue with its displacement segments held; `needle_zone`
    (centre, radius) is where graded particles refine (stitchplan.needle.geometry.needle_zone)."""
    segments = tuple(load.segment for load in scenario.loads if load.displacement is not None)
    return build_tissue_model(scenario.tissue, scenario.discretization, segments, needle_zone)


def consistent_test_gradients(values: sp.csr_matrix, grad_x: sp.csr_matrix, grad_y: sp.csr_matrix,
                              weights: np.ndarray, at_natural: sp.csr_matrix, normals: np.ndarray,
                              boundary_weights: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Variationally consistent integration (VCI) of the free test functions Psi_J = N T_J.

    Gauss quadrature of the rational RK functions breaks the divergence theorem
    int grad Psi_J dOmega = int_Gamma Psi_J N dGamma, and the transformed functions do not
    vanish on the essential boundary between the boundary particles; both make the linear
    patch test fail. The corrected gradients grad Psi_J + xi_J Psi_J, with one constant
    vector xi_J per free function, satisfy the discrete divergence theorem with the
    boundary integral taken over the natural boundary only (where a test function of the
    exact weak form may be non-zero):

        sum_q (grad Psi_J + xi_J Psi_J)(X_q) w_q = sum_b Psi_J(X_b) N_b w_b.

    A constant stress then leaves no residual at the free coefficients, so a linear field
    prescribed on the whole boundary is the discrete solution (to round-off). Only the
    test side is corrected (Petrov-Galerkin): the trial gradients keep reproducing linear
    fields exactly, and the tangent B_test^T A B is no longer symmetric.
    Arguments: (nq, n_free) matrices at the quadrature points, their area weights (nq,), the
    functions at the natural-boundary points (nb, n_free), outward normals (nb, 2) and
    lengths (nb,). Returns the corrected (grad_x, grad_y).
    """
    mass = values.T @ weights  # sum_q Psi_J w_q
    if np.any(mass <= 1e-6 * np.abs(mass).max()):
        bad = int(np.argmin(mass))
        raise ScenarioError(f"discretization.integration: vci needs test functions with a positive "
                            f"integral; free function {bad} has {mass[bad]:.3g} mm^2 (use integration: gauss)")
    corrected = []
    for k, grad in enumerate((grad_x, grad_y)):
        target = at_natural.T @ (normals[:, k] * boundary_weights)
        xi = (target - grad.T @ weights) / mass
        corrected.append((grad + values @ sp.diags(xi)).tocsr())
    return corrected[0], corrected[1]


def _gradient_operator(grad_x: sp.spmatrix, grad_y: sp.spmatrix) -> sp.csr_matrix:
    """Rows (q, 2 i + J) -> d u_i / d X_J, columns interleaved free dofs (2 p + i), from the
    (nq, n_free) gradient matrices of the free functions."""
    n_points, n_free = grad_x.shape
    blocks = [grad_x.tocoo(), grad_y.tocoo()]
    rows, cols, vals = [], [], []
    for component in range(2):  # i
        for direction, block in enumerate(blocks):  # J
            rows.append(4 * block.row + 2 * component + direction)
            cols.append(2 * block.col + component)
            vals.append(block.data)
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(4 * n_points, 2 * n_free),
    )
