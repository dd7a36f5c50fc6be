"""Independent finite-element reference for configs/slab_edge_load.yaml with scikit-fem,
and a side-by-side timing/accuracy comparison with `stitchplan deform`.

The scikit-fem model solves the same problem as stitchplan:
  * plane strain, St. Venant-Kirchhoff, Total Lagrangian:  P = F S,  S = lambda tr(E) I + 2 mu E;
  * dead traction h0 = F_total / (segment length x thickness) on the loaded reference segment
    (the mesh has element boundaries at its end points), clamped edges u = 0;
  * quadratic elements: 6-node triangles (ElementTriP2, default 6-point rule, exact for the
    SVK integrands on straight triangles) or 9-node quadrilaterals (ElementQuad2, 3x3 Gauss);
  * full Newton with the consistent tangent A_iJkL = dP_iJ/dF_kL, the same load steps, the
    same linear-extrapolation predictor and the same convergence test as stitchplan's solver
    (scenario.solver tolerances), sparse direct solves (skfem.condense + skfem.solve, SuperLU
    with the MMD_AT_PLUS_A ordering that stitchplan also uses);
  * probe displacements by interpolation (Basis.probes).
Everything is per unit thickness (thickness cancels between f_int and the traction).
`solve_skfem` also takes prescribed-displacement segments (Dirichlet values on every dof of
the segment's facets, scaled with the load fraction), grades the mesh toward the segment
ends inside an edge (`grading` levels) and returns the segments' reactions; the load-segment
comparison in benchmarks/deform_segments.py uses that.

One run of this script:
  1. verification: a fine skfem solve (Q2, h = 1.25 mm) against a fine stitchplan solve
     (spacing 1 mm); the converged reference is whichever of the two changed less when its
     mesh size / particle spacing was last halved (stated in the output);
  2. timing, interleaved over repetitions (medians): skfem meshes from coarse to fine (wall time
     of mesh + basis + assembly + solves + probes, imports excluded), and stitchplan's
     `run_deform` wall_seconds at its default discretization (and a few other spacings, and
     with integration: vci);
  3. the cheapest skfem mesh with max probe error <= 1 % of the largest probe displacement,
     and the ratio skfem time / stitchplan default time.

Writes benchmarks/results/skfem_comparison.{csv,md,png} and prints the tables.
Run from the repository root:  python benchmarks/skfem_reference.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it (and for both codes compared):
# the numerics are sparse and small-dense, and BLAS threads only compete on 2 cores
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import time
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from skfem import (  # noqa: E402
    Basis,
    BilinearForm,
    ElementQuad2,
    ElementTriP2,
    ElementVector,
    FacetBasis,
    LinearForm,
    MeshQuad,
    MeshTri,
    asm,
    condense,
    solve,
    solver_direct_scipy,
)
from skfem.helpers import ddot, dot, grad, identity, trace, transpose  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.config.scenario import Scenario, with_discretization  # noqa: E402
from stitchplan.tissue.deform import run_deform  # noqa: E402

ELEMENTS = {
    # name: (mesh class, scalar element, quadrature order passed to Basis)
    "P2-tri": (MeshTri, ElementTriP2, 4),
    "Q2-quad": (MeshQuad, ElementQuad2, 4),
}
SKFEM_SWEEP = {  # cells per side (the mesh lines at the load-segment ends are always kept)
    "P2-tri": (4, 5, 6, 8, 10, 12, 15, 20, 30),
    "Q2-quad": (3, 4, 5, 6, 8, 10, 15, 20, 30),
}
SKFEM_REFERENCE = ("Q2-quad", 80)
STITCHPLAN_REFERENCE = (2.0, 1.0)  # spacings (mm): the fine run and the one before it (h halved)
STITCHPLAN_EXTRA_SPACINGS = (10.0, 4.0, 2.5)  # timed besides the default, for error vs time
STITCHPLAN_VCI_SPACINGS = (10.0, 5.0, 2.5)  # integration: vci, for its cost against Gauss
LINEAR_SOLVER = solver_direct_scipy(permc_spec="MMD_AT_PLUS_A")


# --- weak forms (vectorised over elements and quadrature points) ---------------------------


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Matrix product of point-wise 2 x 2 tensors shaped (2, 2, elements, points)."""
    return np.einsum("ik...,kj...->ij...", a, b)


def svk_response(grad_u: np.ndarray, lame_lambda: float, lame_mu: float) -> tuple[np.ndarray, np.ndarray]:
    """First Piola-Kirchhoff stress P and tangent A_iJkL = dP_iJ / dF_kL of plane-strain SVK.

    With F = I + grad u, E = (F^T F - I)/2, S = lambda tr(E) I + 2 mu E, B = F F^T:
        A_iJkL = delta_ik S_JL + lambda F_iJ F_kL + mu (F_iL F_kJ + delta_JL B_ik).
    """
    eye = identity(grad_u)
    f = eye + grad_u
    strain = 0.5 * (matmul(transpose(f), f) - eye)
    stress = lame_lambda * trace(strain) * eye + 2.0 * lame_mu * strain
    left_cauchy_green = matmul(f, transpose(f))
    delta = np.eye(2)
    tangent = (np.einsum("ik,JL...->iJkL...", delta, stress)
               + lame_lambda * np.einsum("iJ...,kL...->iJkL...", f, f)
               + lame_mu * (np.einsum("iL...,kJ...->iJkL...", f, f)
                            + np.einsum("JL,ik...->iJkL...", delta, left_cauchy_green)))
    return matmul(f, stress), tangent


@LinearForm
def internal_force(v, w):
    """f_int: int P : grad v dX, with P evaluated beforehand at the quadrature points."""
    return ddot(w["P"], grad(v))


@BilinearForm
def tangent_stiffness(du, v, w):
    """K: int grad v : A : grad du dX, with A evaluated beforehand at the quadrature points."""
    return ddot(np.einsum("iJkL...,kL...->iJ...", w["A"], grad(du)), grad(v))


@LinearForm
def dead_traction(v, w):
    return dot(w["h0"], v)


# --- the model ------------------------------------------------------------------------------


def mesh_lines(length: float, cells: int, breaks: list[float], graded: list[float] = (),
               levels: int = 0) -> np.ndarray:
    """Roughly `cells` uniform intervals on [0, length] that keep every break point as a node;
    with `levels`, lines at distances h/2, h/4, ..., h/2^levels on both sides of each `graded`
    point (geometric grading toward the singular points, h = length / cells)."""
    knots = np.unique(np.clip([0.0, length, *breaks], 0.0, length))
    pieces = []
    for a, b in zip(knots[:-1], knots[1:]):
        n = max(1, int(round(cells * (b - a) / length)))
        pieces.append(np.linspace(a, b, n + 1)[:-1])
    lines = np.append(np.concatenate(pieces), length)
    h = length / cells
    extra = [p + s * h / 2**k for p in graded for k in range(1, levels + 1) for s in (-1.0, 1.0)]
    extra = [x for x in extra if 0.0 < x < length]
    lines = np.unique(np.concatenate([lines, extra]))
    return lines[np.concatenate([[True], np.diff(lines) > 1e-9 * length])]


@dataclass
class SkfemRun:
    element: str
    cells: int
    dofs: int
    elements: int
    probe_displacements: np.ndarray
    newton_iterations: int
    seconds: float
    reactions: np.ndarray | None = None  # (n_loads, 2) N, as stitchplan's reactions.csv


def load_stepped_newton(basis, external: np.ndarray, free: np.ndarray, prescribed: np.ndarray,
                        final: np.ndarray, settings, load_steps: int, lame_lambda, lame_mu,
                        h_mesh: float) -> tuple[np.ndarray, int]:
    """Load-stepped full Newton on the SVK problem, with the same predictor and stopping test
    as stitchplan.tissue.solver.newton: load step k applies k / load_steps of `external` and
    of the `prescribed` dofs' `final` values. Returns (u, Newton iterations)."""
    u = np.zeros(basis.N)
    previous_increment = np.zeros(basis.N)
    external_norm = float(np.linalg.norm(external[free]))
    iterations = 0
    for step in range(1, load_steps + 1):
        fraction = step / load_steps
        step_start = u.copy()
        u = u + previous_increment
        u[prescribed] = fraction * final[prescribed]
        increment_norm = np.inf
        for iteration in range(settings.max_iterations + 1):
            first_piola, tangent = svk_response(basis.interpolate(u).grad, lame_lambda, lame_mu)
            residual = asm(internal_force, basis, P=first_piola) - fraction * external
            residual_norm = float(np.linalg.norm(residual[free]))
            if iteration == 0:
                tolerance = settings.residual_tolerance * max(fraction * external_norm, residual_norm)
            small_step = increment_norm <= settings.increment_tolerance * (np.abs(u).max() + h_mesh)
            if residual_norm <= tolerance and (small_step or residual_norm <= 1e-3 * tolerance):
                break
            if iteration == settings.max_iterations:
                raise RuntimeError(f"skfem Newton: no convergence at load step {step}")
            stiffness = asm(tangent_stiffness, basis, A=tangent)
            delta = solve(*condense(stiffness, -residual, I=free, expand=False), solver=LINEAR_SOLVER)
            u[free] += delta
            increment_norm = float(np.abs(delta).max())
            iterations += 1
        previous_increment = u - step_start
    return u, iterations


def solve_skfem(scenario: Scenario, element: str, cells: int, grading: int = 0) -> SkfemRun:
    """Build the mesh and bases, run the load-stepped Newton solve, interpolate the probes.

    Force segments are dead tractions, displacement segments Dirichlet conditions on every
    dof of the segment's facets (nodes and edge midpoints), scaled with the load fraction;
    `grading` adds that many geometric levels of mesh lines around the segment ends that lie
    inside an edge (the singular points)."""
    start = time.perf_counter()
    tissue, material = scenario.tissue, scenario.tissue.material
    if material.model != "saint-venant-kirchhoff":
        raise ValueError("this reference implements St. Venant-Kirchhoff only")
    width, height = tissue.size
    tol = 1e-9 * max(width, height)

    x_breaks = [p[0] for load in scenario.loads for p in load.segment]
    y_breaks = [p[1] for load in scenario.loads for p in load.segment]
    domain = tissue.domain
    singular = [p for load in scenario.loads for p in load.segment if len(domain.edges_at(p)) == 1]
    mesh_class, scalar_element, intorder = ELEMENTS[element]
    mesh = mesh_class.init_tensor(
        mesh_lines(width, cells, x_breaks, [p[0] for p in singular], grading),
        mesh_lines(height, cells, y_breaks, [p[1] for p in singular], grading))
    vector_element = ElementVector(scalar_element())
    basis = Basis(mesh, vector_element, intorder=intorder)

    # dead traction per unit thickness on each loaded segment, assembled once; the dofs of
    # each displacement segment with their final values
    external = np.zeros(basis.N)
    final = np.zeros(basis.N)
    held = []  # per load: (x dofs, y dofs) of a displacement segment, else None
    for load in scenario.loads:
        (x0, y0), (x1, y1) = load.segment
        lo, hi = np.minimum([x0, y0], [x1, y1]), np.maximum([x0, y0], [x1, y1])
        length = float(np.hypot(x1 - x0, y1 - y0))

        def on_segment(x, lo=lo, hi=hi, x0=x0, y0=y0, x1=x1, y1=y1, length=length):
            across = np.abs((x[0] - x0) * (y1 - y0) - (x[1] - y0) * (x1 - x0)) / length
            return ((across <= tol) & (x[0] >= lo[0] - tol) & (x[0] <= hi[0] + tol)
                    & (x[1] >= lo[1] - tol) & (x[1] <= hi[1] + tol))

        facets = mesh.facets_satisfying(on_segment)
        if load.displacement is not None:
            dofs = basis.get_dofs(facets=facets)
            x_dofs, y_dofs = dofs.all(["u^1"]), dofs.all(["u^2"])
            final[x_dofs], final[y_dofs] = load.displacement
            held.append((x_dofs, y_dofs))
            continue
        held.append(None)
        facet_basis = FacetBasis(mesh, vector_element, facets=facets)
        h0 = np.asarray(load.force) / (length * tissue.thickness)
        external += asm(dead_traction, facet_basis, h0=h0[:, None, None])

    edge_test = {"left": lambda x: np.abs(x[0]) <= tol, "right": lambda x: np.abs(x[0] - width) <= tol,
                 "bottom": lambda x: np.abs(x[1]) <= tol, "top": lambda x: np.abs(x[1] - height) <= tol}
    clamped = (np.unique(np.concatenate([basis.get_dofs(edge_test[e]).all() for e in tissue.clamped]))
               if tissue.clamped else np.zeros(0, dtype=np.int64))
    prescribed = np.unique(np.concatenate([clamped, *[np.concatenate(h) for h in held if h is not None]]))
    final[clamped] = 0.0  # the clamp holds a corner it shares with a displacement segment
    free = basis.complement_dofs(prescribed)

    u, iterations = load_stepped_newton(basis, external, free, prescribed, final, scenario.solver,
                                        scenario.load_steps, material.lame_lambda, material.lame_mu,
                                        max(width, height) / cells)

    probes = np.asarray(scenario.probes, dtype=float).reshape(-1, 2)
    values = (basis.probes(probes.T) @ u).reshape(2, -1).T
    # reactions: minus the internal force (x thickness) at a segment's dofs; a force
    # segment's is minus its load, as in stitchplan
    first_piola, _ = svk_response(basis.interpolate(u).grad, material.lame_lambda, material.lame_mu)
    internal = asm(internal_force, basis, P=first_piola) * tissue.thickness
    reactions = np.array([-np.asarray(load.force, float) if dofs is None else
                          [-internal[dofs[0]].sum(), -internal[dofs[1]].sum()]
                          for load, dofs in zip(scenario.loads, held)])
    seconds = time.perf_counter() - start
    return SkfemRun(element, cells, basis.N, mesh.nelements, values, iterations, seconds, reactions)


def solve_skfem_shape(scenario: Scenario, h: float, grading: int = 3) -> SkfemRun:
    """`solve_skfem` for a tissue with an outline, holes and material regions whose edges
    all run along x or y (an L-shape, a plate with a rectangular hole, a layered slab):
    a Q2 tensor mesh of side ~h over the bounding box with lines through every vertex and
    segment end, `grading` geometric levels of lines around every vertex (the corners are
    singular), elements outside the tissue removed, each element's Lame moduli those of the
    region holding its centre (solve_on_shape_mesh)."""
    start = time.perf_counter()
    tissue = scenario.tissue
    domain = tissue.domain
    origin = np.asarray(domain.origin, float)
    width, height = domain.size
    vertices = [np.asarray(domain.outline if hasattr(domain, "outline") else
                           [[0, 0], [width, 0], [width, height], [0, height]], float)]
    vertices += [np.asarray(h_, float) for h_ in domain.holes]
    vertices += [r.vertices() for r in tissue.regions]
    corners = np.concatenate(vertices) - origin
    ends = np.asarray([p for load in scenario.loads for p in load.segment], float).reshape(-1, 2) - origin
    points = np.concatenate([corners, ends])
    x_lines = mesh_lines(width, max(int(round(width / h)), 1), list(points[:, 0]), list(corners[:, 0]), grading)
    y_lines = mesh_lines(height, max(int(round(height / h)), 1), list(points[:, 1]), list(corners[:, 1]), grading)
    mesh = MeshQuad.init_tensor(x_lines + origin[0], y_lines + origin[1])
    return solve_on_shape_mesh(scenario, mesh, ElementQuad2(), "Q2-quad", h, start)


def solve_skfem_curved(scenario: Scenario, h: float, grading: int = 0) -> SkfemRun:
    """`solve_skfem` for a tissue whose edges need not run along x and y: a rectangle or a
    polygon outline, holes and material regions of any shape (circles: the model's 96-gons),
    on P2 triangles that follow every edge of the outline (a polygon's), the holes and the
    regions: the Delaunay triangulation of a grid of side h over the bounding box, without its
    points outside the tissue or within h/2 of those edges, and of the edges' points, each
    edge cut into pieces of at most h/2 with the load and clamp segments' ends among them
    (each piece's diametral circle then holds no other point, so the piece is an edge of the
    triangulation: no triangle straddles an edge, checked), triangles outside the tissue
    removed; then `grading` times the triangles within 2h / 2^k of a re-entrant corner split
    (skfem's conforming refinement; the corners are singular); each triangle's Lame moduli
    those of the region holding its centre (solve_on_shape_mesh). The holes and regions must
    keep h from a rectangle's sides, and a region's edges must not cross the boundary."""
    from scipy.spatial import Delaunay

    from stitchplan.geometry.segments import on_segment, point_segment_distance
    from stitchplan.tissue.shapes import corner_zones, region_index

    start = time.perf_counter()
    tissue = scenario.tissue
    domain = tissue.domain
    origin = np.asarray(domain.origin, float)
    width, height = domain.size
    tol = 1e-9 * max(width, height)
    polygon = hasattr(domain, "outline") and not domain.edge_names  # an outline's edges, not a rectangle's
    loops = ([np.asarray(domain.outline, float)] if polygon else []) + [np.asarray(hole, float) for hole in domain.holes]
    loops += [region.vertices() for region in tissue.regions]
    starts = np.concatenate(loops)
    ends = np.concatenate([np.roll(loop, -1, axis=0) for loop in loops])
    breaks = np.asarray([p for load in scenario.loads for p in load.segment]
                        + [p for piece in tissue.clamped_pieces() for p in piece], float).reshape(-1, 2)
    along = []
    for a, b in zip(starts, ends):
        on = breaks[on_segment(breaks, a, b, tol)] if len(breaks) else breaks
        knots = np.unique(np.concatenate([[0.0, 1.0], (on - a) @ (b - a) / float((b - a) @ (b - a))]))
        for t0, t1 in zip(knots[:-1], knots[1:]):
            n = max(int(np.ceil(np.linalg.norm(b - a) * (t1 - t0) / (0.5 * h))), 1)
            along.append(a + (b - a) * (t0 + (t1 - t0) * np.arange(n) / n)[:, None])
    edge_points = np.concatenate(along)
    x = origin[0] + np.linspace(0.0, width, max(int(round(width / h)), 1) + 1)
    y = origin[1] + np.linspace(0.0, height, max(int(round(height / h)), 1) + 1)
    grid = np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
    grid = grid[domain.contains(grid)]  # no nodes inside a hole
    near = np.zeros(len(grid), dtype=bool)
    for a, b in zip(starts, ends):
        near |= point_segment_distance(grid, a, b) < 0.5 * h
    points = np.concatenate([grid[~near], edge_points[domain.contains(edge_points, tol)]])
    _, first = np.unique(np.round(points / tol), axis=0, return_index=True)
    points = points[np.sort(first)]  # each point once (edges meet at their ends), in order
    triangles = Delaunay(points).simplices
    centres = points[triangles].mean(axis=1)
    inside = domain.contains(centres)
    # a flat triangle of collinear boundary points has its centre on the edge, inside by the
    # test, and no area: the solve gave NaN
    sides = points[triangles[:, 1:]] - points[triangles[:, :1]]
    inside &= 0.5 * np.abs(np.cross(sides[:, 0], sides[:, 1])) > 1e-9 * h * h
    triangles, centres = triangles[inside], centres[inside]
    # a straddling triangle has a corner off the edges, or a point inside, in another region
    # or outside the tissue: its corners and four inner points (barycentric) are looked at
    on_edge = np.zeros(len(points), dtype=bool)
    for a, b in zip(starts, ends):
        on_edge |= point_segment_distance(points, a, b) <= tol
    inner = np.array([[2, 1, 1], [1, 2, 1], [1, 1, 2], [1, 1, 1]]) / np.array([[4], [4], [4], [3]])
    looked_at = np.concatenate([points[triangles], np.einsum("sk,tkd->tsd", inner, points[triangles])], axis=1)
    off_edge = np.concatenate([~on_edge[triangles], np.ones((len(triangles), len(inner)), dtype=bool)], axis=1)
    which = region_index(tissue, looked_at.reshape(-1, 2)).reshape(len(triangles), -1)
    outside = ~domain.contains(looked_at.reshape(-1, 2), tol).reshape(len(triangles), -1)
    own = region_index(tissue, centres)
    straddles = np.any(off_edge & ((which != own[:, None]) | outside), axis=1)
    if np.any(straddles):
        raise RuntimeError(f"{int(straddles.sum())} triangles straddle an edge of the tissue or of a region")
    mesh = MeshTri(points.T.copy(), triangles.T.copy())
    # the re-entrant corners the model grades its particles toward
    corners = np.array([zone.center for zone in corner_zones(tissue, scenario.discretization)]).reshape(-1, 2)
    for k in range(grading if len(corners) else 0):
        vertices = mesh.p.T[mesh.t.T]  # (elements, 3, 2)
        distance = np.linalg.norm(vertices[:, :, None, :] - corners[None, None], axis=-1).min(axis=(1, 2))
        mesh = mesh.refined(np.flatnonzero(distance < 2.0 * h / 2**k))
    return solve_on_shape_mesh(scenario, mesh, ElementTriP2(), "P2-tri", h, start)


def solve_on_shape_mesh(scenario: Scenario, mesh, element, label: str, h: float, start: float) -> SkfemRun:
    """The shape scenes' solve on `mesh` (elements of the scalar `element`): elements whose
    centre lies outside the tissue removed, each element's Lame moduli those of the region
    holding its centre; clamped edges or segments u = 0, force segments dead tractions
    (displacement segments are not implemented here), St. Venant-Kirchhoff only."""
    from stitchplan.geometry.segments import on_segment
    from stitchplan.tissue.shapes import region_index

    tissue = scenario.tissue
    domain = tissue.domain
    width, height = domain.size
    materials = [tissue.material] + [region.material for region in tissue.regions]
    if any(m.model != "saint-venant-kirchhoff" for m in materials):
        raise ValueError("this reference implements St. Venant-Kirchhoff only")
    if any(load.displacement is not None for load in scenario.loads):
        raise ValueError("force loads only")
    centres = mesh.p[:, mesh.t].mean(axis=1).T  # (nel, 2)
    outside = ~domain.contains(centres)
    if np.any(outside):
        mesh = mesh.remove_elements(np.flatnonzero(outside))
        centres = mesh.p[:, mesh.t].mean(axis=1).T
    which = region_index(tissue, centres) + 1
    lame_lambda = np.array([m.lame_lambda for m in materials])[which][:, None]
    lame_mu = np.array([m.lame_mu for m in materials])[which][:, None]
    vector_element = ElementVector(element)
    basis = Basis(mesh, vector_element, intorder=4)

    def facets_on(a, b):
        a, b = np.asarray(a, float), np.asarray(b, float)
        return mesh.facets_satisfying(lambda x: on_segment(np.asarray(x).T, a, b, 1e-7 * max(width, height)),
                                      boundaries_only=True)

    external = np.zeros(basis.N)
    for load in scenario.loads:
        a, b = (np.asarray(p, float) for p in load.segment)
        facet_basis = FacetBasis(mesh, vector_element, facets=facets_on(a, b))
        h0 = np.asarray(load.force) / (float(np.linalg.norm(b - a)) * tissue.thickness)
        external += asm(dead_traction, facet_basis, h0=h0[:, None, None])
    clamped = [basis.get_dofs(facets=facets_on(a, b)).all() for a, b in tissue.clamped_pieces()]
    prescribed = np.unique(np.concatenate(clamped)) if clamped else np.zeros(0, dtype=np.int64)
    free = basis.complement_dofs(prescribed)

    u, iterations = load_stepped_newton(basis, external, free, prescribed, np.zeros(basis.N), scenario.solver,
                                        scenario.load_steps, lame_lambda, lame_mu, h)
    probes = np.asarray(scenario.probes, dtype=float).reshape(-1, 2)
    values = (basis.probes(probes.T) @ u).reshape(2, -1).T
    return SkfemRun(label, int(round(max(width, height) / h)), basis.N, mesh.nelements, values,
                    iterations, time.perf_counter() - start)


# --- the benchmark ------------------------------------------------------------------------


def stitchplan_run(scenario: Scenario, spacing: float | None, integration: str = "gauss"):
    chosen = with_discretization(scenario, spacing=spacing, integration=integration)
    return run_deform(chosen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed repetitions (medians)")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")

    base = common.load_slab_scenario()  # default discretization: spacing 5 mm
    default_spacing = base.discretization.spacing
    probes = np.asarray(base.probes)

    # 1. verification and reference ------------------------------------------------------
    print("reference runs ...", flush=True)
    sk_element, sk_cells = SKFEM_REFERENCE
    sk_fine = solve_skfem(base, sk_element, sk_cells)
    sk_previous = solve_skfem(base, sk_element, sk_cells // 2)
    sp_previous = stitchplan_run(base, STITCHPLAN_REFERENCE[0])
    sp_fine = stitchplan_run(base, STITCHPLAN_REFERENCE[1])
    sk_change = common.max_probe_error(sk_previous.probe_displacements, sk_fine.probe_displacements)
    sp_change = common.max_probe_error(sp_previous.probe_displacements, sp_fine.probe_displacements)
    agreement = common.max_probe_error(sp_fine.probe_displacements, sk_fine.probe_displacements)
    sk_label = f"{sk_element}, {sk_cells} x {sk_cells} cells, h = {base.tissue.size[0] / sk_cells:g} mm ({sk_fine.dofs} dofs)"
    sp_label = f"spacing {STITCHPLAN_REFERENCE[1]:g} mm ({sp_fine.model.n_particles} particles)"
    if sk_change <= sp_change:
        reference, reference_label = sk_fine.probe_displacements, f"skfem {sk_label}"
    else:
        reference, reference_label = sp_fine.probe_displacements, f"stitchplan {sp_label}"
    verification = [
        ["skfem", sk_label, *(f"{v:.5f}" for v in sk_fine.probe_displacements.ravel()),
         f"{100 * sk_change:.4f} % (from {sk_cells // 2} x {sk_cells // 2})"],
        ["stitchplan", sp_label, *(f"{v:.5f}" for v in sp_fine.probe_displacements.ravel()),
         f"{100 * sp_change:.4f} % (from {STITCHPLAN_REFERENCE[0]:g} mm)"],
    ]
    verification_header = ["code", "discretization",
                           *[f"{c} ({x:g},{y:g})" for x, y in probes for c in ("ux", "uy")],
                           "change in last refinement"]
    print(f"  skfem {sk_label}: {sk_fine.seconds:.1f} s; stitchplan {sp_label}: "
          f"{sp_fine.wall_seconds:.1f} s", flush=True)
    print(f"  skfem fine vs stitchplan fine: max probe difference {100 * agreement:.4f} % "
          f"of the largest probe displacement", flush=True)
    print(f"  reference: {reference_label}", flush=True)

    # 2. timing, interleaved ------------------------------------------------------------
    configs = [("stitchplan", None)] + [("stitchplan", s) for s in STITCHPLAN_EXTRA_SPACINGS]
    configs += [("stitchplan vci", s) for s in STITCHPLAN_VCI_SPACINGS]
    configs += [(element, cells) for element, sizes in SKFEM_SWEEP.items() for cells in sizes]
    solve_skfem(base, "P2-tri", 4)  # warm-up (first-call costs of both libraries), not timed
    stitchplan_run(base, None)
    samples: dict[tuple, list[float]] = {c: [] for c in configs}
    last: dict[tuple, object] = {}
    for repeat in range(args.repeats):
        print(f"timing repetition {repeat + 1}/{args.repeats} ...", flush=True)
        for config in configs:
            code, size = config
            if code.startswith("stitchplan"):
                result = stitchplan_run(base, size, "vci" if code.endswith("vci") else "gauss")
                samples[config].append(result.wall_seconds)
            else:
                result = solve_skfem(base, code, size)
                samples[config].append(result.seconds)
            last[config] = result

    rows = []
    for config in configs:
        code, size = config
        result = last[config]
        seconds = statistics.median(samples[config])
        if code.startswith("stitchplan"):
            spacing = default_spacing if size is None else size
            error = common.max_probe_error(result.probe_displacements, reference)
            vci = code.endswith("vci")
            rows.append({"code": code, "discretization":
                         f"spacing {spacing:g} mm" + (", integration vci" if vci else "")
                         + (" (default)" if size is None and not vci else ""),
                         "size_mm": result.model.spacing, "unknowns": 2 * result.model.n_free,
                         "newton": result.report.iterations, "seconds": seconds,
                         "samples": samples[config], "error": error, "default": size is None and not vci,
                         "probes": result.probe_displacements})
        else:
            error = common.max_probe_error(result.probe_displacements, reference)
            rows.append({"code": f"skfem {code}", "discretization":
                         f"{result.cells} x {result.cells} cells, {result.elements} elements",
                         "size_mm": base.tissue.size[0] / result.cells, "unknowns": result.dofs,
                         "newton": result.newton_iterations, "seconds": seconds,
                         "samples": samples[config], "error": error, "default": False,
                         "probes": result.probe_displacements})

    # 3. summary -------------------------------------------------------------------------
    default_row = next(r for r in rows if r["default"])
    skfem_ok = [r for r in rows if r["code"].startswith("skfem") and r["error"] <= 0.01]
    cheapest = min(skfem_ok, key=lambda r: r["seconds"]) if skfem_ok else None
    stitch_ok = [r for r in rows if r["code"] == "stitchplan" and r["error"] <= 0.01]
    cheapest_stitch = min(stitch_ok, key=lambda r: r["seconds"]) if stitch_ok else None

    header = ["code", "discretization", "h_mm", "unknowns", "newton_iterations",
              "seconds_median", "seconds_samples", "max_probe_error_rel",
              *[f"{c}({x:g},{y:g})" for x, y in probes for c in ("ux", "uy")]]
    common.write_csv(common.results_path("skfem_comparison.csv"), header, [
        [r["code"], r["discretization"], r["size_mm"], r["unknowns"], r["newton"], r["seconds"],
         " ".join(f"{s:.4f}" for s in r["samples"]), r["error"], *r["probes"].ravel()]
        for r in rows])

    md_header = ["code", "discretization", "h (mm)", "unknowns", "Newton its",
                 f"time s (median of {args.repeats})", "max probe error", "<= 1 %"]
    md_rows = [[r["code"], r["discretization"], r["size_mm"], r["unknowns"], r["newton"],
                r["seconds"], f"{100 * r['error']:.3f} %", "yes" if r["error"] <= 0.01 else "no"]
               for r in rows]
    table = common.markdown_table(md_header, md_rows)
    verification_table = common.markdown_table(verification_header, verification)

    lines = [f"Reference: {reference_label} (of the two fine runs, the one that changed less "
             f"when its mesh size / particle spacing was last halved).",
             f"Verification: the fine skfem and fine stitchplan solutions differ by at most "
             f"{100 * agreement:.4f} % of the largest probe displacement."]
    if cheapest is not None:
        ratio = cheapest["seconds"] / default_row["seconds"]
        lines.append(
            f"Cheapest skfem mesh with max probe error <= 1 %: {cheapest['code']}, "
            f"{cheapest['discretization']} ({cheapest['unknowns']} unknowns): "
            f"{cheapest['seconds']:.3f} s, error {100 * cheapest['error']:.3f} %.")
        lines.append(
            f"stitchplan at its default discretization ({default_row['discretization']}): "
            f"{default_row['seconds']:.3f} s, error {100 * default_row['error']:.3f} %.")
        lines.append(f"Ratio skfem time / stitchplan default time = {ratio:.2f} "
                     f"(> 1 means stitchplan is faster; target >= 3). From the fastest of the "
                     f"{args.repeats} samples instead of the medians: "
                     f"{min(cheapest['samples']) / min(default_row['samples']):.2f}.")
        if cheapest_stitch is not None:
            lines.append(
                f"At equal accuracy (cheapest run of each code with error <= 1 %): stitchplan "
                f"{cheapest_stitch['discretization']} {cheapest_stitch['seconds']:.3f} s, ratio "
                f"{cheapest['seconds'] / cheapest_stitch['seconds']:.2f}.")
    else:
        lines.append("No skfem mesh in the sweep reached 1 %.")
    summary = "\n".join(f"- {line}" for line in lines)

    text = "\n".join([
        "# scikit-fem reference and timing comparison on configs/slab_edge_load.yaml",
        "",
        "Same problem in both codes: plane strain St. Venant-Kirchhoff, Total Lagrangian, dead "
        "traction on the left-edge segment (0,40)-(0,60), clamped right edge, 10 load steps, "
        "full Newton with the same predictor and stopping test. skfem: quadratic elements "
        "(P2 triangles with the 6-point rule, Q2 quadrilaterals with 3x3 Gauss), mesh lines at "
        "y = 40 and 60, SuperLU (MMD_AT_PLUS_A) through `skfem.solve`, probes via "
        "`Basis.probes`. skfem time = mesh + bases + all assembly + solves + probes (imports "
        "excluded); stitchplan time = `DeformResult.wall_seconds` (discretization + solve + "
        "probes) from the loaded scenario. All runs interleaved, median of "
        f"{args.repeats} repetitions after one untimed warm-up of each code.",
        "",
        "## Verification (fine runs)",
        "",
        verification_table,
        "",
        "## Timing and accuracy",
        "",
        "Error = max over the 6 probes of |u - u_ref| / max |u_ref|.",
        "",
        table,
        "",
        summary,
        "",
        f"Machine: {common.machine_note()}; shared with other jobs, so single timings are noisy.",
        "",
    ])
    common.results_path("skfem_comparison.md").write_text(text)
    print()
    print(verification_table)
    print()
    print(table)
    print()
    print(summary)

    figure, axis = plt.subplots(figsize=(6, 4.5))
    for code, marker in (("skfem P2-tri", "s-"), ("skfem Q2-quad", "d-"), ("stitchplan", "o-"),
                         ("stitchplan vci", "^--")):
        chosen = sorted((r for r in rows if r["code"] == code), key=lambda r: -r["size_mm"])
        axis.loglog([r["seconds"] for r in chosen], [100 * r["error"] for r in chosen], marker,
                    label=code)
    axis.loglog([default_row["seconds"]], [100 * default_row["error"]], "k*", ms=12,
                label="stitchplan default (5 mm)")
    axis.axhline(1.0, color="grey", lw=0.8, ls=":")
    axis.set_xlabel("wall time (s), median")
    axis.set_ylabel("max probe error (% of largest |u|)")
    axis.set_title("slab_edge_load: accuracy vs time (lines join refinements)")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(common.results_path("skfem_comparison.png"), dpi=120)


if __name__ == "__main__":
    main()
