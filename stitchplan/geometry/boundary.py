"""Boundary questions for any domain: its edges, the nearest boundary point, snapping typed points, smooth vertices."""

from __future__ import annotations

import math

import numpy as np

from .polygons import CORNER_TURN
from .segments import cross_2d


def smooth_vertex(domain, point) -> bool:
    """Whether `point` is a boundary vertex where the boundary turns by at most CORNER_TURN
    (a traced contour's vertex, which the model treats as a point inside an edge)."""
    names = domain.edges_at(point)
    if len(names) != 2:
        return False
    (a0, a1), (b0, b1) = (domain.edge(name) for name in names)
    d, e = a1 - a0, b1 - b0
    return abs(math.atan2(float(cross_2d(d, e)), float(np.dot(d, e)))) <= CORNER_TURN


def boundary_edges(domain) -> tuple[np.ndarray, np.ndarray]:
    """Starts and ends (k, 2) of every directed boundary edge of a domain."""
    segments = domain.boundary_segments()
    return (np.array([start for start, _ in segments], dtype=float),
            np.array([end for _, end in segments], dtype=float))


def ray_meets_edges(starts: np.ndarray, ends: np.ndarray, origin, direction) -> bool:
    """Whether the ray from `origin` along `direction` (2,) meets any of the segments
    starts -> ends (k, 2)."""
    o, d = np.asarray(origin, dtype=float), np.asarray(direction, dtype=float)
    e, w = ends - starts, starts - o  # (k, 2)
    cross = d[0] * e[:, 1] - d[1] * e[:, 0]  # d x e
    parallel = np.abs(cross) <= 1e-15 * np.linalg.norm(e, axis=1) * np.linalg.norm(d)
    safe = np.where(parallel, 1.0, cross)
    along_ray = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / safe  # w x e / d x e
    along_edge = (w[:, 0] * d[1] - w[:, 1] * d[0]) / safe  # w x d / d x e
    return bool(np.any(~parallel & (along_ray > 0.0) & (along_edge >= 0.0) & (along_edge <= 1.0)))


def nearest_on_edges(starts: np.ndarray, ends: np.ndarray, point) -> tuple[int, float, np.ndarray, float]:
    """The point of the segments starts -> ends (k, 2) nearest `point` (2,): its segment,
    the fraction along it, the point, and how far it is (mm)."""
    x = np.asarray(point, dtype=float)
    e = ends - starts  # (k, 2)
    along = np.clip(np.sum((x - starts) * e, axis=1) / np.sum(e * e, axis=1), 0.0, 1.0)
    candidates = starts + along[:, None] * e
    distances = np.linalg.norm(candidates - x, axis=1)
    k = int(np.argmin(distances))
    return k, float(along[k]), candidates[k], float(distances[k])


def nearest_boundary_point(domain, point) -> tuple[np.ndarray, float]:
    """The boundary point nearest `point` (2,), and how far it is (mm)."""
    _, _, nearest, distance = nearest_on_edges(*boundary_edges(domain), point)
    return nearest, distance


def snap_to_boundary(domain, point) -> np.ndarray | None:
    """The boundary point that a typed or measured `point` (2,) means, or None when it lies
    more than domain.input_tolerance off the boundary. A boundary vertex within that tolerance
    is the point (a point typed next to a corner is the corner, refused as one wherever a
    corner is); else the point itself when it lies on the boundary to round-off
    (domain.tolerance: a file's exact points are kept to the bit); else the nearest boundary
    point."""
    x = np.asarray(point, dtype=float)
    starts, _ = boundary_edges(domain)
    gaps = np.linalg.norm(starts - x, axis=1)
    k = int(np.argmin(gaps))
    if gaps[k] <= domain.input_tolerance:
        return x.copy() if gaps[k] <= domain.tolerance else starts[k].copy()
    nearest, distance = nearest_boundary_point(domain, x)
    if distance <= domain.tolerance:
        return x.copy()
    return nearest if distance <= domain.input_tolerance else None
