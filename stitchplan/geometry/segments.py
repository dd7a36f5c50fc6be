"""Straight segments: a point's distance to one, points on one, two crossing or touching."""

from __future__ import annotations

import numpy as np


def on_segment(points: np.ndarray, start, end, tol: float) -> np.ndarray:
    """Mask of points within `tol` of the straight segment start-end; points (n, 2)."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    direction = end - start
    length = float(np.linalg.norm(direction))
    relative = np.asarray(points, dtype=float) - start
    along = relative @ direction / length
    across = np.abs(relative[:, 0] * direction[1] - relative[:, 1] * direction[0]) / length
    return (across <= tol) & (along >= -tol) & (along <= length + tol)


def cross_2d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def segments_cross(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    """Mask of segment pairs p-q and a-b (broadcasting (..., 2) arrays) that cross properly:
    each segment's ends lie strictly (beyond `tol` mm) on opposite sides of the other's line.
    Touching at an end, running along each other or meeting at a vertex is not a crossing."""
    d, e = q - p, b - a
    length_d = np.maximum(np.linalg.norm(d, axis=-1), 1e-300)
    length_e = np.maximum(np.linalg.norm(e, axis=-1), 1e-300)
    o1, o2 = cross_2d(d, a - p) / length_d, cross_2d(d, b - p) / length_d  # a, b seen from p-q
    o3, o4 = cross_2d(e, p - a) / length_e, cross_2d(e, q - a) / length_e  # p, q seen from a-b
    return (((o1 > tol) & (o2 < -tol)) | ((o1 < -tol) & (o2 > tol))) & \
        (((o3 > tol) & (o4 < -tol)) | ((o3 < -tol) & (o4 > tol)))


def segments_touch(p, q, a, b, tol: float) -> np.ndarray:
    """Mask of segment pairs that come within `tol` of each other (crossing, touching,
    overlapping)."""
    p, q, a, b = (np.asarray(v, dtype=float) for v in (p, q, a, b))
    close = np.minimum.reduce([point_segment_distance(p, a, b), point_segment_distance(q, a, b),
                               point_segment_distance(a, p, q), point_segment_distance(b, p, q)])
    return (close <= tol) | segments_cross(p, q, a, b, 0.0)


def point_segment_foot(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The point (..., 2) of each segment a-b nearest x."""
    e = b - a
    t = np.clip(np.sum((x - a) * e, axis=-1) / np.maximum(np.sum(e * e, axis=-1), 1e-300), 0.0, 1.0)
    return a + t[..., None] * e


def point_segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x - point_segment_foot(x, a, b), axis=-1)
