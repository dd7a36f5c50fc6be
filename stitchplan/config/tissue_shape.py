"""A tissue's shape as the model can use it: the outer loop (the rectangle of `size` or the
`outline`, walked counter-clockwise), the holes inside it or cut out of it, and the checks
that the outline, holes, regions and clamped pieces make one simple piece of tissue, each
problem naming its field (README, "Tissue shapes").

The functions read a tissue block (stitchplan.config.blocks.Tissue) by its fields and import
no block: blocks builds on them (Tissue.loops, Tissue.domain, the validation of a
Tissue and of its clamped segments).
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

import numpy as np

from ..geometry.polygon_domain import PolygonDomain
from ..geometry.polygons import cut_outline, polygon_problem, signed_area
from ..geometry.rectangle import Rectangle
from ..geometry.segments import segments_touch
from .boundary_points import segment_on_boundary
from .fields import problem
from .messages import Shown

# a blocks.Tissue and a blocks.Hole, read by their fields (blocks imports this module)
TissueBlock = Any
HoleBlock = Any


def counter_clockwise(vertices: np.ndarray) -> np.ndarray:
    """The polygon walked counter-clockwise (a clockwise one reversed)."""
    return vertices if signed_area(vertices) > 0 else vertices[::-1].copy()


def shape_loops(tissue: TissueBlock) -> tuple[np.ndarray | None, list[tuple[int, np.ndarray]], bool, list]:
    """The tissue's outer boundary (counter-clockwise), the holes inside it as (index in
    `holes`, vertices), whether holes were cut out of the outline, and the problems that
    stop the shape (naming their fields). A hole that reaches or crosses the outline is cut
    out of it (the first hole of README's shape example: the tissue is the outline minus the hole), as long
    as one simple piece of tissue is left."""
    if (tissue.size is None) == (tissue.outline is None):
        given = "both" if tissue.size is not None else "neither"
        return None, [], False, [problem("exactly one of 'size' [W, H] or 'outline' (a polygon)", field="size",
                                         value=Shown(given), absent=("size", "outline") if given == "neither" else ())]
    outer, tol, outline_problems = _outer_loop(tissue)
    # the holes' own polygons are checked all the same, so that every problem is said at once
    problems = outline_problems + _hole_polygon_problems(tissue, tol)
    if problems:
        return None, [], False, problems
    inside, reaching = _inside_or_reaching(tissue, outer, tol)
    if reaching:
        outer, problems = _cut_out(tissue, outer, reaching, tol)
        if problems:
            return None, [], False, problems
        problems = _holes_reached_by_cut(tissue, outer, inside, reaching, tol)
    return outer, inside, bool(reaching), problems + _overlapping_holes(tissue, inside, tol)


def _outer_loop(tissue: TissueBlock) -> tuple[np.ndarray | None, float, list]:
    """The outline (counter-clockwise) or the rectangle of `size`, the tolerance of the shape's
    checks (1e-9 of its larger side), and the problem of an outline that is not a simple
    polygon (None as the loop)."""
    if tissue.outline is None:
        w, h = tissue.size
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]), 1e-9 * max(w, h), []
    outline = np.asarray(tissue.outline, dtype=float)
    tol = 1e-9 * float(np.ptp(outline, axis=0).max())
    why = polygon_problem(outline, tol)
    if why:
        return None, tol, [problem(why, field="outline", value=tissue.outline)]
    return counter_clockwise(outline), tol, []


def _inside_or_reaching(tissue: TissueBlock, outer: np.ndarray, tol: float) -> tuple[list, list]:
    """The holes as (index in `holes`, vertices): those inside the outer loop and apart from
    it, and those that reach or cross it."""
    inside, reaching = [], []
    outer_domain = PolygonDomain(outer)
    for i, hole in enumerate(tissue.holes):
        vertices = hole.vertices()
        if _inside_and_apart(vertices, outer_domain, tol):
            inside.append((i, vertices))
        else:
            reaching.append((i, vertices))
    return inside, reaching


def _inside_and_apart(vertices: np.ndarray, domain: PolygonDomain, tol: float) -> bool:
    """Whether a hole lies inside a domain without holes, more than `tol` from its outline."""
    return (bool(np.all(domain._inside_strict(vertices) & (domain.distance(vertices) > tol)))
            and not _loops_touch(vertices, domain.outline, tol))


def _cut_out(tissue: TissueBlock, outer: np.ndarray, reaching: list, tol: float) -> tuple[np.ndarray | None, list]:
    """The outer loop with the `reaching` holes cut out of it (geometry.polygons.cut_outline), and the
    problems of the cut: a hole that holds no tissue, or what is left not one simple piece."""
    cut, why, idle = cut_outline(outer, [vertices for _, vertices in reaching], tol)
    expected = "a hole inside the tissue outline, not touching it, or one cutting into it that leaves " \
               "one simple piece of tissue"
    problems = []
    for k in idle:
        i = reaching[k][0]
        problems.append(problem(f"{expected} (this one holds no tissue)", field=f"holes[{i}]",
                                value=_shown(tissue.holes[i])))
    if not problems and cut is None:
        i = reaching[0][0]
        others = ", ".join(f"holes[{j}]" for j, _ in reaching[1:])
        problems.append(problem(f"{expected} (cut out of the outline{' with ' + others if others else ''}, "
                                f"it leaves {why})", field=f"holes[{i}]", value=_shown(tissue.holes[i])))
    return cut, problems


def _holes_reached_by_cut(tissue: TissueBlock, cut: np.ndarray, inside: list, reaching: list, tol: float) -> list:
    """The problems of the holes inside the outline that the cut outline no longer holds apart."""
    cut_domain = PolygonDomain(cut)
    return [problem("a hole inside the tissue, apart from the holes cut into its outline ("
                    + ", ".join(f"holes[{j}]" for j, _ in reaching) + ")",
                    field=f"holes[{i}]", value=_shown(tissue.holes[i]))
            for i, vertices in inside if not _inside_and_apart(vertices, cut_domain, tol)]


def _overlapping_holes(tissue: TissueBlock, inside: list, tol: float) -> list:
    """The problems of the holes inside that overlap or touch one before them (the first such)."""
    loops, problems = [], []
    lows, highs = np.empty((0, 2)), np.empty((0, 2))  # the loops' bounding boxes
    for i, vertices in inside:
        low, high = vertices.min(axis=0) - tol, vertices.max(axis=0) + tol
        # only loops whose boxes come within tol of this one's may touch or hold it (every
        # edge of every pair checked made a file of 100 circular holes take 45 s to read)
        near = np.flatnonzero(~(np.any(lows > high, axis=1) | np.any(highs < low, axis=1)))
        for j, other in (loops[k] for k in near):
            if _loops_touch(vertices, other, tol) or PolygonDomain(other)._inside_strict(vertices[:1])[0] \
                    or PolygonDomain(vertices)._inside_strict(other[:1])[0]:
                problems.append(problem(f"a hole apart from holes[{j}] (they overlap or touch)",
                                        field=f"holes[{i}]", value=_shown(tissue.holes[i])))
                break
        else:
            loops.append((i, vertices))
            lows, highs = np.vstack([lows, vertices.min(axis=0)]), np.vstack([highs, vertices.max(axis=0)])
    return problems


def _hole_polygon_problems(tissue: TissueBlock, tol: float) -> list:
    """The holes given as polygons that are not simple ones."""
    return [problem(why, field=f"holes[{i}]", value=_shown(hole)) for i, hole in enumerate(tissue.holes)
            if hole.polygon is not None and (why := polygon_problem(hole.vertices(), tol))]


def _region_polygon_problems(tissue: TissueBlock, tol: float | None) -> dict[int, Any]:
    """The problems of the regions whose polygons are not simple ones, by region (`tol`: the
    tissue's, None to take the region's own size when the tissue has no valid shape)."""
    problems = {}
    for i, region in enumerate(tissue.regions):
        if region.polygon is None:  # a circle's polygon is a simple one
            continue
        vertices = region.vertices()
        own = 1e-9 * float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
        why = polygon_problem(vertices, own if tol is None else tol)
        if why:
            problems[i] = problem(why, field=f"regions[{i}].polygon", value=region.polygon)
    return problems


def _shown(hole: HoleBlock):
    return hole.polygon if hole.polygon is not None else asdict(hole.circle)


def shape_problems(tissue: TissueBlock) -> list:
    """Why a tissue's shape is not one the model can hold, as problems naming its fields:
    size and outline both or neither, a self-intersecting outline, holes outside the tissue,
    touching the outline at a point, cutting it apart or overlapping each other, regions
    outside the tissue, clamped pieces off the boundary or named edges on a polygon."""
    problems = list(tissue.loops[3])
    if problems:  # the regions' own polygons do not depend on the shape
        return problems + list(_region_polygon_problems(tissue, None).values())
    domain = tissue.domain
    not_simple = _region_polygon_problems(tissue, domain.tolerance)
    problems = list(not_simple.values())
    for i, region in enumerate(tissue.regions):
        if i in not_simple:
            continue
        if not _overlaps(PolygonDomain(counter_clockwise(region.vertices())), domain):
            name, shown = region.shown()
            problems.append(problem("a region overlapping the tissue (this one holds no tissue)",
                                    field=f"regions[{i}].{name}", value=shown))
    for i, item in enumerate(tissue.clamped):
        if isinstance(item, str):
            if isinstance(domain, PolygonDomain) and not domain.edge_names and item not in domain.aliases:
                problems.append(problem("{segment: [[x0, y0], [x1, y1]]}, or the name of a side of the "
                                        "outline's bounding box that holds one straight piece of the outline "
                                        f"({_side_found(domain, item)})", field=f"clamped[{i}]", value=item))
    return problems + clamps_on_boundary(tissue.clamped, domain)[1]


def _side_found(domain: PolygonDomain, side: str) -> str:
    """What a side of an outline's bounding box holds, when it is not one straight piece."""
    pieces = domain.side_pieces[side]
    if not pieces:
        return f"no outline edge lies along its {side} side"
    shown = [" + ".join(domain.segment_names[k] for k in piece) for piece in pieces]
    return f"its {side} side holds {len(pieces)} separate pieces: " + ", ".join(shown)


def clamps_on_boundary(clamped: tuple, domain: Rectangle | PolygonDomain) -> tuple[tuple, list]:
    """The clamped items with each segment's ends moved onto the boundary (boundary_points),
    and the problems of the segments that are not a straight piece of one edge."""
    items, problems = [], []
    for i, item in enumerate(clamped):
        if not isinstance(item, str):  # a ClampedSegment (a str names an edge)
            segment, why = segment_on_boundary(domain, item.segment)
            if segment is None:
                problems.append(problem(why, field=f"clamped[{i}].segment", value=[list(p) for p in item.segment]))
            elif segment != tuple(item.segment):
                item = replace(item, segment=segment)
        items.append(item)
    return tuple(items), problems


def _loops_touch(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether an edge of loop a comes within tol of an edge of loop b."""
    a0, a1 = a[:, None, :], np.roll(a, -1, axis=0)[:, None, :]
    b0, b1 = b[None], np.roll(b, -1, axis=0)[None]
    return bool(np.any(segments_touch(a0, a1, b0, b1, tol)))


def _box_lattice(low: np.ndarray, high: np.ndarray, count: int = 200) -> np.ndarray:
    """count x count points (count^2, 2) at the centres of a grid over the box [low, high]."""
    t = (np.arange(count) + 0.5) / count
    return np.stack(np.meshgrid(low[0] + t * (high[0] - low[0]), low[1] + t * (high[1] - low[1])),
                    axis=-1).reshape(-1, 2)


def tissue_outside_regions(tissue: TissueBlock) -> bool:
    """Whether some of the tissue lies outside every region (where its own material holds):
    a lattice of 200 x 200 points over its bounding box with a point in the tissue and in no
    region."""
    domain = tissue.domain
    low = np.asarray(domain.origin, dtype=float)
    points = _box_lattice(low, low + np.array(domain.size))
    points = points[domain.contains(points)]
    for region in tissue.regions:
        points = points[~PolygonDomain(counter_clockwise(region.vertices()))._inside_strict(points)]
    return len(points) > 0


def regions_covered_before(tissue: TissueBlock) -> dict[int, list[int]]:
    """The regions that overlap the tissue yet hold none of it, as {index: the regions listed
    before it that cover its part of the tissue}: a point belongs to the first region listed
    that holds it, so a region within earlier ones gets no quadrature point (a lattice of
    200 x 200 points over its bounding box, as _overlaps). Regions outside the tissue are
    shape_problems' to refuse."""
    domain = tissue.domain
    shapes = [PolygonDomain(counter_clockwise(region.vertices())) for region in tissue.regions]
    covered = {}
    for i, region in enumerate(shapes):
        if i == 0:
            continue
        points = _box_lattice(region.origin, region.origin + np.array(region.size))
        points = points[region._inside_strict(points) & domain.contains(points)]
        if not len(points):
            continue
        left, covering = points, []
        for j, earlier in enumerate(shapes[:i]):
            inside = earlier._inside_strict(left)
            if np.any(inside):
                covering.append(j)
                left = left[~inside]
        if not len(left):
            covered[i] = covering
    return covered


def _overlaps(region: PolygonDomain, domain) -> bool:
    """Whether the region holds tissue: a lattice of 200 x 200 points over the region's
    bounding box with some point inside both (regions thinner than 1/200 of their box count
    as empty)."""
    points = _box_lattice(region.origin, region.origin + np.array(region.size))
    points = points[region._inside_strict(points)]
    return bool(np.any(domain.contains(points))) if len(points) else False
