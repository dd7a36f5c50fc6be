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
from .config import Discretization, Scenario, ScenarioError, Tissue
from .material import NeoHookean, SaintVenantKirchhoff, make_material
from .quadrature import cell_quadrature
from .shape_functions import ShapeFunctions, SingularMomentMatrix, rk_shape_functions


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

    @property
    def n_particles(self) -> int:
        return len(self.particles)

    @property
    def n_free(self) -> int:
        return self.boundary.n_free

    def shape_functions_at(self, points: np.ndarray, gradients: bool = False) -> ShapeFunctions:
        return rk_shape_functions(np.atleast_2d(points), self.particles, self.support, self.volumes,
                                  self.discretization.basis_order, gradients, self.tree,
                                  self.basis_scale)

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
) -> TissueModel:
    """Discretize the slab: particles, quadrature, shape functions and the essential boundary."""
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
    try:
        shape = rk_shape_functions(points, particles, support, volumes, order, True, tree,
                                   float(support.mean()))
    except SingularMomentMatrix as error:
        raise ScenarioError(
            f"discretization: dilation {discretization.dilation:g} with spacing "
            f"{discretization.spacing:g} mm gives a singular RK moment matrix ({error})"
        ) from None
    constrained = boundary_particles(particles, tissue, prescribed_segments, spacing)
    at_boundary = rk_shape_functions(particles[constrained.indices], particles, support, volumes,
                                     order, False, tree, float(support.mean())).values
    boundary = transformation(at_boundary, constrained, len(particles))
    gradient = _gradient_operator(shape, boundary.free_map)
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
    )


def model_for_scenario(scenario: Scenario) -> TissueModel:
    segments = tuple(load.segment for load in scenario.loads if load.displacement is not None)
    return build_tissue_model(scenario.tissue, scenario.discretization, segments)


def _gradient_operator(shape: ShapeFunctions, free_map: sp.csr_matrix) -> sp.csr_matrix:
    """Rows (q, 2 i + J) -> d u_i / d X_J, columns interleaved free dofs (2 p + i)."""
    n_points = shape.values.shape[0]
    n_free = free_map.shape[1]
    blocks = [(shape.grad_x @ free_map).tocoo(), (shape.grad_y @ free_map).tocoo()]
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
