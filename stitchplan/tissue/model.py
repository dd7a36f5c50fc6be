"""The discretized tissue: particles, quadrature, shape functions and essential boundaries.

Everything here lives in the reference configuration and is computed once per
discretization (Total-Lagrangian formulation); the solver only refills values.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from .boundary_conditions import ConstrainedParticles, EssentialBoundary, boundary_particles, transformation
from ..config import Discretization, Scenario, ScenarioError, Tissue
from ..geometry.edge_grid import concatenated_ranges
from ..geometry.polygon_domain import PolygonDomain
from ..geometry.rectangle import Rectangle
from .material import NeoHookean, PointwiseMaterial, SaintVenantKirchhoff, make_material
from .particles import (END_GROWTH, GradedParticles, end_zones, graded_lattice, graded_particles,
                        grid_particles, leaf_quadrature, segment_breaks)
from .quadrature import cell_quadrature, natural_boundary_quadrature
from .shape_functions import (ParticleSearch, ShapeFunctions, ShapePairs, SingularMomentMatrix,
                              Visibility, rk_shape_functions, rk_shape_pairs, rows_csr)
from .shapes import (fit_particles, lattice_spacing, region_index, shape_breaks, shape_zones,
                     shaped_quadrature)
from .thin_features import refuse_thin_tissue, singular_moment_message

log = logging.getLogger(__name__)

# points whose shape functions are made at once (TissueModel.shape_functions_at)
POINTS_AT_ONCE = 20_000
NO_NEEDLE_TO_GRADE_TOWARD = ("discretization.needle_spacing: needs a needle to grade the "
                             "particles toward; remove it or add a `needle:` block")


@dataclass(frozen=True)
class ModelOutline:
    """What a run's summary tells of its model (io.reports.discretization_summary) without
    its matrices: a replay made in a helper process comes back with it, as the model's
    operators and shape functions are ~27 MB to pickle and send on the refined SH 1/2 model
    (planning/replays.py)."""

    discretization: Discretization
    n_particles: int
    coarsest_spacing: float  # mm: the largest support over the dilation (graded particles)
    needle_spacing: float | None
    quadrature_points: int

    def outline(self) -> ModelOutline:
        return self


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
    material: SaintVenantKirchhoff | NeoHookean | PointwiseMaterial
    particles: np.ndarray  # (NP, 2)
    support: np.ndarray  # (NP,)
    volumes: np.ndarray  # (NP,)
    search: ParticleSearch  # the particles' neighbour search
    quadrature_points: np.ndarray  # (nq, 2)
    quadrature_weights: np.ndarray  # (nq,) area x thickness, mm^3
    shape: ShapeFunctions  # raw RK functions at quadrature points
    boundary: EssentialBoundary
    gradient: sp.csr_matrix  # (4 nq, 2 n_free)
    # d Psi_p / d X_J of the free functions at column 2 p + J, (nq, 2 n_free): the gradient
    # operator's entries without their repetition per displacement component
    direction_gradient: sp.csr_matrix
    spacing: float  # the finest level's lattice step (load-segment ends and corners included)
    # gradients of the test functions when they differ from the trial ones (integration
    # "vci"); None: Galerkin, test = trial, symmetric tangent
    test_gradient: sp.csr_matrix | None = None
    # non-convex tissue: pairs whose segment leaves the tissue are dropped (visibility)
    visibility: Visibility | None = None
    # particles graded toward a needle: the particle spacing in its zone (zone_spacing)
    needle_spacing: float | None = None
    # the shape functions at the particles themselves (NP, NP): made by the build where it
    # checks them (a tissue with a hole or a notch), else by particle_shape_values() when first
    # asked for, and kept (every run's displacements on this model and the plots read them)
    particle_values: sp.csr_matrix | None = None

    @property
    def symmetric(self) -> bool:
        return self.test_gradient is None

    @property
    def n_particles(self) -> int:
        return len(self.particles)

    @property
    def n_free(self) -> int:
        return self.boundary.n_free

    def outline(self) -> ModelOutline:
        """What a run's summary tells of this model, without its matrices."""
        return ModelOutline(self.discretization, self.n_particles,
                            float(self.support.max() / self.discretization.dilation), self.needle_spacing,
                            len(self.quadrature_weights))

    def _shape_pairs(self, points: np.ndarray, gradients: bool) -> ShapePairs:
        return rk_shape_pairs(points, self.particles, self.support, self.volumes,
                              self.discretization.basis_order, gradients, self.search, self.basis_scale,
                              self.visibility)

    def shape_functions_at(self, points: np.ndarray, gradients: bool = False) -> ShapeFunctions:
        """N(X) at `points`, in parts of at most POINTS_AT_ONCE points: the pairs' moment
        matrices and bases take ~3 kB a point while they are made (200 000 markers of a
        calibration peaked at 0.58 GB for the 38 MB kept); the parts are equal, each large
        enough to be made as the whole would be."""
        points = np.atleast_2d(points)
        parts = -(-len(points) // POINTS_AT_ONCE)
        if parts <= 1:
            return self._shape_pairs(points, gradients).matrices(len(points), self.n_particles)
        made = [self._shape_pairs(part, gradients).matrices(len(part), self.n_particles)
                for part in np.array_split(points, parts)]
        stacked = [sp.vstack([getattr(m, name) for m in made], format="csr") for name in ("values", "grad_x", "grad_y")
                   if getattr(made[0], name) is not None]
        return ShapeFunctions(*stacked)

    def particle_shape_values(self) -> sp.csr_matrix:
        """N_J(X_I) at the particles themselves (NP, NP), made once (`particle_values`)."""
        if self.particle_values is None:
            self.particle_values = self.shape_functions_at(self.particles).values
        return self.particle_values

    def free_rows_at(self, points: np.ndarray) -> sp.csr_matrix:
        """N(X) T (n, n_free): the shape functions at reference points acting on the free
        coefficients. Where no boundary particle is among the points' neighbours (along a
        needle's track, mostly) T only renumbers the columns, and the rows are built as such."""
        points = np.atleast_2d(points)
        pairs = self._shape_pairs(points, False)
        columns = self.boundary.free_column[pairs.cols]
        if (columns >= 0).all():
            return rows_csr(pairs.values, columns, pairs.indptr, self.n_free)
        return (pairs.matrices(len(points), self.n_particles).values @ self.boundary.free_map).tocsr()

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
    needle_zone: tuple[tuple[float, float], float, tuple] | None = None,
    force_segments: tuple[tuple[tuple[float, float], tuple[float, float]], ...] = (),
) -> TissueModel:
    """Discretize the slab: particles, quadrature, shape functions and the essential boundary.

    With discretization.needle_spacing set, the particles are graded toward `needle_zone`
    (centre, radius in mm, and the refinement zones at the needle's entry and exit; see
    graded_particles and stitchplan.needle.geometry.needle_zone) and each particle's kernel support is the
    dilation times its local spacing; otherwise they form a uniform grid. Load segments
    (prescribed displacement or force) have a particle on each end whatever the spacing
    (grid lines through the ends), and the particles are graded toward the ends that lie
    inside an edge, where the solution is singular (see end_zones).
    """
    segments = tuple(prescribed_segments) + tuple(force_segments)
    particles, volumes, support, spacing, points, weights = particles_and_quadrature(
        tissue, discretization, segments, needle_zone)
    functions = ParticleFunctions.of(particles, support, volumes, discretization.basis_order, tissue.domain)
    constrained = boundary_particles(particles, tissue, prescribed_segments, spacing)
    shape, at_boundary, particle_values = evaluated_shape_functions(functions, points, constrained, tissue,
                                                                    discretization)
    boundary = transformation(at_boundary, constrained, len(particles))  # T of eq. 3.37
    free_map = boundary.free_map
    grad_x, grad_y = shape.grad_x @ free_map, shape.grad_y @ free_map  # (nq, n_free) each
    gradient = gradient_operator(grad_x, grad_y)
    test_gradient = None
    if discretization.integration == "vci":  # Petrov-Galerkin: only the test side is corrected
        at_natural, normals, boundary_weights = natural_boundary_functions(
            functions, free_map, tissue, discretization, prescribed_segments, spacing)
        test_gradient = gradient_operator(*consistent_test_gradients(
            shape.values @ free_map, grad_x, grad_y, weights, at_natural, normals, boundary_weights))
    return TissueModel(
        tissue=tissue, discretization=discretization, material=material_at(tissue, points),
        particles=particles, support=support, volumes=volumes, search=functions.search,
        quadrature_points=points, quadrature_weights=weights * tissue.thickness,
        shape=shape, boundary=boundary, gradient=gradient, spacing=spacing,
        direction_gradient=direction_gradient_operator(grad_x, grad_y),
        test_gradient=test_gradient, visibility=functions.visibility,
        needle_spacing=(zone_spacing(particles, support / discretization.dilation, needle_zone)
                        if needle_zone is not None and discretization.needle_spacing is not None else None),
        particle_values=particle_values,
    )


class ParticlesAndQuadrature(NamedTuple):
    """The particles of a discretized tissue and its quadrature (particles_and_quadrature)."""

    particles: np.ndarray  # (NP, 2)
    volumes: np.ndarray  # (NP,)
    support: np.ndarray  # (NP,) kernel support radii
    spacing: float  # the finest lattice step, mm
    points: np.ndarray  # (nq, 2) quadrature points
    weights: np.ndarray  # (nq,) area weights


def particles_and_quadrature(tissue: Tissue, discretization: Discretization, segments: tuple,
                             needle_zone: tuple | None) -> ParticlesAndQuadrature:
    """Particles (NP, 2), their volumes (NP,) and kernel supports (NP,), the finest lattice
    step (mm), and the quadrature points (nq, 2) and area weights (nq,): a polygon tissue's or
    one with regions (shaped_discretization), else the rectangle's graded lattice
    (rectangle_lattice) with Gauss points on its leaf cells, or without grading its uniform
    grid (grid_discretization)."""
    if isinstance(tissue.domain, PolygonDomain) or tissue.regions:
        return shaped_discretization(tissue, discretization, segments, needle_zone)
    graded = rectangle_lattice(tissue, discretization, segments, needle_zone)
    if graded is None:
        return grid_discretization(tissue.size, discretization)
    spacing = graded.fine_spacing
    support = discretization.dilation * graded.local_spacing
    points, weights = leaf_quadrature(graded.cells, discretization.quadrature_order,
                                      discretization.cells_per_spacing)
    return ParticlesAndQuadrature(graded.particles, graded.volumes, support, spacing, points, weights)


def rectangle_lattice(tissue: Tissue, discretization: Discretization, segments: tuple,
                      needle_zone: tuple | None) -> GradedParticles | None:
    """A rectangular tissue's graded lattice, with lines through every segment end: toward the
    needle (discretization.needle_spacing) and the segment ends inside an edge (end_zones),
    or toward those ends alone; None without needle grading or load segments (a uniform grid)."""
    breaks = segment_breaks(segments) if segments else ((), ())
    ends = end_zones(tissue, segments, discretization)
    if discretization.needle_spacing is not None:
        if needle_zone is None:
            raise ScenarioError(NO_NEEDLE_TO_GRADE_TOWARD)
        return graded_particles(tissue.size, discretization.spacing, discretization.needle_spacing,
                                np.asarray(needle_zone[0], dtype=float), float(needle_zone[1]),
                                discretization.needle_grading, points=ends + tuple(needle_zone[2]),
                                breaks=breaks)
    if segments:
        return graded_lattice(tissue.size, discretization.spacing, ends, END_GROWTH, breaks)
    return None


def grid_discretization(size: tuple[float, float], discretization: Discretization) -> ParticlesAndQuadrature:
    """The uniform grid's particles, volumes, supports (dilation x the largest line interval),
    that interval, and Gauss points on cells_per_spacing cells per grid interval."""
    particles, volumes, dx, dy = grid_particles(size, discretization.spacing)
    spacing = max(dx, dy)
    support = np.full(len(particles), discretization.dilation * spacing)
    n_cells = (
        int(round(size[0] / dx)) * discretization.cells_per_spacing,
        int(round(size[1] / dy)) * discretization.cells_per_spacing,
    )
    points, weights = cell_quadrature(size, n_cells, discretization.quadrature_order)
    return ParticlesAndQuadrature(particles, volumes, support, spacing, points, weights)


@dataclass(frozen=True, eq=False)
class ParticleFunctions:
    """The RK shape functions of the particles being built, at any reference points: their
    neighbour search, and on a non-convex tissue (a hole or a notch) the visibility criterion."""

    particles: np.ndarray  # (NP, 2)
    support: np.ndarray  # (NP,)
    volumes: np.ndarray  # (NP,)
    order: int  # of the basis
    search: ParticleSearch
    visibility: Visibility | None

    @classmethod
    def of(cls, particles: np.ndarray, support: np.ndarray, volumes: np.ndarray, order: int,
           domain: Rectangle | PolygonDomain) -> ParticleFunctions:
        search = ParticleSearch.of(particles, support)
        visibility = Visibility.of(domain, particles)
        return cls(particles, support, volumes, order, search, visibility)

    def at(self, points: np.ndarray, gradients: bool = False) -> ShapeFunctions:
        """rk_shape_functions at `points`, the basis scaled by the mean support (as the
        model's basis_scale)."""
        return rk_shape_functions(points, self.particles, self.support, self.volumes, self.order, gradients,
                                  self.search, float(self.support.mean()), self.visibility)


def evaluated_shape_functions(functions: ParticleFunctions, points: np.ndarray, constrained: ConstrainedParticles,
                              tissue: Tissue, discretization: Discretization):
    """The shape functions with their gradients at the quadrature points, their values at the
    boundary particles (D^b and D^nb of eq. 3.31-3.32: (Nb, NP)) and, on a tissue with a hole
    or a notch, at every particle (NP, NP; else None). A singular moment matrix is refused
    with the ScenarioError that says why (thin_features.singular_moment_message)."""
    particle_values = None
    try:  # at the quadrature points, then at the boundary particles (eq. 3.31)
        shape = functions.at(points, True)
        at_boundary = functions.at(functions.particles[constrained.indices]).values
        if functions.visibility is not None:  # a hole or a notch: at every particle too, which the runs ask for
            particle_values = functions.at(functions.particles).values
    except SingularMomentMatrix as error:
        point = getattr(error, "point", None)
        local = (float(functions.support[functions.search.nearest(np.atleast_2d(point))[0]])
                 / discretization.dilation if point is not None else discretization.spacing)
        raise ScenarioError(singular_moment_message(tissue, discretization, local, error)) from None
    return shape, at_boundary, particle_values


def natural_boundary_functions(functions: ParticleFunctions, free_map: sp.csr_matrix, tissue: Tissue,
                               discretization: Discretization, prescribed_segments: tuple, spacing: float):
    """The free functions N T (nb, n_free) at the quadrature points of the natural boundary
    (all but the clamped pieces and the prescribed-displacement segments), their outward
    normals (nb, 2) and lengths (nb,): the boundary side of consistent_test_gradients."""
    essential = [(np.asarray(a, float), np.asarray(b, float)) for a, b in prescribed_segments]
    essential += tissue.clamped_pieces()
    domain = tissue.domain
    boundary_points, normals, boundary_weights = natural_boundary_quadrature(
        tissue.bounding_size, essential, spacing, discretization.quadrature_order + 2,
        None if isinstance(domain, Rectangle) else outward_edges(domain))
    at_natural = (functions.at(boundary_points).values @ free_map
                  if len(boundary_points) else sp.csr_matrix((0, free_map.shape[1])))
    return at_natural, normals, boundary_weights


def zone_spacing(particles: np.ndarray, local_spacing: np.ndarray, needle_zone: tuple) -> float | None:
    """The particle spacing in the needle's zone (centre, radius, ...): the median local
    spacing of the particles within it, which finer grading at load-segment ends, corners
    or the needle's entry and exit inside the zone does not move."""
    inside = np.hypot(*(particles - np.asarray(needle_zone[0], dtype=float)).T) <= float(needle_zone[1])
    return float(np.median(local_spacing[inside])) if inside.any() else None


def material_at(tissue: Tissue, points: np.ndarray) -> SaintVenantKirchhoff | NeoHookean | PointwiseMaterial:
    """The tissue's material, or with regions one per quadrature point (the first region
    holding the point, else the tissue's own)."""
    if not tissue.regions:
        return make_material(tissue.material)
    parts = (make_material(tissue.material), *(make_material(region.material) for region in tissue.regions))
    return PointwiseMaterial(parts, region_index(tissue, points) + 1)


def outward_edges(domain: PolygonDomain) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every boundary edge with its outward unit normal (the tissue lies on the edge's left)."""
    edges = []
    for start, end in domain.boundary_segments():
        d = end - start
        edges.append((start, end, np.array([d[1], -d[0]]) / float(np.hypot(*d))))
    return edges


def shaped_discretization(tissue: Tissue, discretization: Discretization, segments: tuple,
                           needle_zone: tuple | None) -> ParticlesAndQuadrature:
    """Particles, supports, spacing and quadrature of a polygon tissue, holes or regions:
    the graded lattice over the bounding box with lines through every polygon vertex and
    segment end, fitted to the shape (stitchplan.tissue.shapes), once the shape has no tissue
    thinner than the lattice resolves (stitchplan.tissue.thin_features)."""
    graded = shaped_lattice(tissue, discretization, segments, needle_zone)
    if isinstance(tissue.domain, PolygonDomain):
        spacing_at = lattice_spacing(graded)  # a KD-tree: a rectangle's commands need not import scipy.spatial
        refuse_thin_tissue(tissue, spacing_at)
        particles, volumes, local = fit_particles(tissue, graded, spacing_at)
    else:  # a rectangle with regions: the lattice fits it
        particles, volumes, local = graded.particles, graded.volumes, graded.local_spacing
    support = discretization.dilation * local
    points, weights = shaped_quadrature(tissue, graded.cells, discretization.quadrature_order,
                                        discretization.cells_per_spacing)
    return ParticlesAndQuadrature(particles, volumes, support, graded.fine_spacing, points, weights)


def shaped_lattice(tissue: Tissue, discretization: Discretization, segments: tuple = (),
                   needle_zone: tuple | None = None) -> GradedParticles:
    """The graded lattice over a shaped tissue's bounding box (in the tissue's coordinates),
    before it is fitted to the shape: lines through the shape's and the segments' vertices,
    graded toward re-entrant corners, segment ends, material interfaces, unresolved round holes
    (shapes.shape_zones) and the needle."""
    domain = tissue.domain
    origin = np.asarray(domain.origin, dtype=float)
    xb, yb = segment_breaks(segments) if segments else ([], [])
    sx, sy = shape_breaks(tissue, discretization.spacing)
    breaks = ([x - origin[0] for x in (*xb, *sx)], [y - origin[1] for y in (*yb, *sy)])
    ends = tuple(zone.shifted(-origin) for zone in (*end_zones(tissue, segments, discretization),
                                                    *shape_zones(tissue, discretization)))
    size = tuple(domain.size)
    if discretization.needle_spacing is not None:
        if needle_zone is None:
            raise ScenarioError(NO_NEEDLE_TO_GRADE_TOWARD)
        needle_ends = tuple(zone.shifted(-origin) for zone in needle_zone[2])
        graded = graded_particles(size, discretization.spacing, discretization.needle_spacing,
                                  np.asarray(needle_zone[0], dtype=float) - origin, float(needle_zone[1]),
                                  discretization.needle_grading, points=ends + needle_ends, breaks=breaks)
    else:
        graded = graded_lattice(size, discretization.spacing, ends, END_GROWTH, breaks)
    cells = graded.cells.copy()
    cells[:, :2] += origin
    return replace(graded, particles=graded.particles + origin, cells=cells)


def load_segments(scenario: Scenario) -> tuple[tuple, tuple]:
    """The scenario's load segments as the model takes them: (held: prescribed displacement,
    pulled: force)."""
    held = tuple(load.segment for load in scenario.loads if load.displacement is not None)
    pulled = tuple(load.segment for load in scenario.loads if load.force is not None)
    return held, pulled


def model_for_scenario(scenario: Scenario,
                       needle_zone: tuple[tuple[float, float], float, tuple] | None = None) -> TissueModel:
    """The model of a scenario's tissue with its displacement segments held; `needle_zone`
    (centre, radius) is where graded particles refine (stitchplan.needle.geometry.needle_zone)."""
    held, pulled = load_segments(scenario)
    return build_tissue_model(scenario.tissue, scenario.discretization, held, needle_zone, pulled)


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


def direction_gradient_operator(grad_x: sp.spmatrix, grad_y: sp.spmatrix) -> sp.csr_matrix:
    """(nq, 2 n_free) with d Psi_p / d X_J at column 2 p + J, from the (nq, n_free) gradient
    matrices of the free functions."""
    n_free = grad_x.shape[1]
    joined = sp.hstack([grad_x, grad_y], format="csr")
    interleaved = np.concatenate([2 * np.arange(n_free), 2 * np.arange(n_free) + 1])
    joined.indices = interleaved.astype(joined.indices.dtype)[joined.indices]
    joined.has_sorted_indices = False
    joined.sort_indices()
    return joined


def gradient_operator(grad_x: sp.spmatrix, grad_y: sp.spmatrix) -> sp.csr_matrix:
    """Rows (q, 2 i + J) -> d u_i / d X_J, columns interleaved free dofs (2 p + i), from the
    (nq, n_free) gradient matrices of the free functions."""
    n_points, n_free = grad_x.shape
    grad_x, grad_y = sp.csr_matrix(grad_x), sp.csr_matrix(grad_y)
    # row (q, i, J) holds row q of grad_J with its columns p moved to 2 p + i: gathered from
    # the two matrices' arrays in place, no sort (the COO route sorts all 4 nnz entries)
    data = np.concatenate([grad_x.data, grad_y.data])
    indices = np.concatenate([grad_x.indices, grad_y.indices]).astype(np.int64)
    starts = np.stack([grad_x.indptr[:-1], grad_x.nnz + grad_y.indptr[:-1]], axis=1)  # (q, J)
    counts = np.stack([np.diff(grad_x.indptr), np.diff(grad_y.indptr)], axis=1)
    starts, counts = np.tile(starts, 2).ravel(), np.tile(counts, 2).ravel()  # (q, i, J)
    gather = concatenated_ranges(starts, counts)
    component = np.repeat(np.tile(np.repeat([0, 1], 2), n_points), counts)  # i of each entry
    return sp.csr_matrix((data[gather], 2 * indices[gather] + component, np.concatenate([[0], np.cumsum(counts)])),
                         shape=(4 * n_points, 2 * n_free))
