"""How a scenario's loads meet its clamped edges and each other: no load on a clamped edge,
no two loads on one piece of the boundary, and a slab held by a clamp or a displacement
(HELD). The checks span blocks (the tissue's clamps, the file's loads), so the scenario and
calibration files run them once their blocks are valid; no block's own validation does.
"""

from __future__ import annotations

import numpy as np

from ..geometry.polygon_domain import PolygonDomain
from ..geometry.rectangle import Rectangle
from .boundary_points import shown_as_given
from .fields import problem
from .messages import Shown
from .tissue_shape import clamps_on_boundary


def shared_length(a, b, tol: float) -> float:
    """Length (mm) two straight segments a, b (pairs of points) have in common: > 0 only
    when they are collinear and overlap by more than a point."""
    start, end = np.asarray(a[0], float), np.asarray(a[1], float)
    length = float(np.linalg.norm(end - start))
    if length == 0.0:
        return 0.0
    direction = (end - start) / length
    relative = np.asarray(b, float) - start  # (2, 2)
    across = np.abs(relative[:, 0] * direction[1] - relative[:, 1] * direction[0])
    if np.any(across > tol):
        return 0.0
    along = np.sort(relative @ direction)
    return max(0.0, min(length, along[1]) - max(0.0, along[0]))


def load_problems(loads, clamped: tuple, domain: Rectangle | PolygonDomain | None, path: str = "loads") -> list:
    """The loads' conflicts with each other and with the clamped edges, as problems naming
    `path[i].segment`: a load on a clamped edge (the clamp holds every particle there, so
    a force would be dropped and a displacement overruled), and two loads sharing more than
    a point of the boundary (one would silently win)."""
    if domain is None:
        return []
    tol = domain.tolerance
    problems = []
    # clamped segments as the run uses them (ends moved onto the boundary), so that a load on a
    # slanted edge meets the clamp on it as typed
    clamped = clamps_on_boundary(tuple(clamped), domain)[0]
    clamped_edges = [(name, domain.edge(name)) if isinstance(name, str) else
                     (f"clamped[{k}] segment", getattr(name, "segment", name)) for k, name in enumerate(clamped)]
    # each segment's bounding box: two loads share more than a point only where theirs come
    # within tol of each other (every pair compared made a file of 2000 loads take 45 s to read)
    ends = np.array([load.segment for load in loads], dtype=float).reshape(-1, 2, 2)
    low, high = ends.min(axis=1) - tol, ends.max(axis=1) + tol
    for i, load in enumerate(loads):
        segment = Shown(shown_as_given(load.segment))
        on_clamp = [name for name, edge in clamped_edges if shared_length(edge, load.segment, tol) > tol]
        if on_clamp:
            problems.append(problem(
                f"a segment off the clamped edges (the {on_clamp[0]} edge is clamped: it neither "
                f"moves nor takes a load; remove it from tissue.clamped or move the load)",
                field=f"{path}[{i}].segment", value=segment))
            continue
        near = np.flatnonzero(np.all((low[:i] <= high[i]) & (high[:i] >= low[i]), axis=1))
        for j in near:
            common = shared_length(loads[j].segment, load.segment, tol)
            if common > tol:
                other = shown_as_given(loads[j].segment)
                problems.append(problem(
                    f"a segment sharing at most an end point with {path}[{j}].segment {other} "
                    f"(they share {common:.4g} mm; one load would overrule the other there)",
                    field=f"{path}[{i}].segment", value=segment))
    return problems


HELD = ("at least one clamped edge or a displacement load: forces alone leave the slab free "
        "to move and turn rigidly (no unique solution)")
