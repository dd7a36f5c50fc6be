"""The tissue domain in the reference configuration: outline, edges, normals, inside tests,
distances and boundary segments.

Every layer asks the domain these questions instead of comparing coordinates with 0, W
and H itself, so another shape (a polygon, holes) is another domain class with the same
methods, not a change to the numerics. Points are (..., 2) arrays in mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EDGE_NAMES = ("left", "right", "bottom", "top")


def on_segment(points: np.ndarray, start, end, tol: float) -> np.ndarray:
    """Mask of points within `tol` of the straight segment start-end; points (n, 2)."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    direction = end - start
    length = float(np.linalg.norm(direction))
    relative = np.asarray(points, dtype=float) - start
    along = relative @ direction / length
    across = np.abs(relative[:, 0] * direction[1] - relative[:, 1] * direction[0]) / length
    return (across <= tol) & (along >= -tol) & (along <= length + tol)


@dataclass(frozen=True)
class Rectangle:
    """The slab [0, W] x [0, H]."""

    width: float
    height: float

    @classmethod
    def of_size(cls, size) -> Rectangle:
        return cls(float(size[0]), float(size[1]))

    @property
    def size(self) -> tuple[float, float]:
        return (self.width, self.height)

    @property
    def tolerance(self) -> float:
        """Distance below which a point counts as on the boundary (round-off of the input)."""
        return 1e-9 * max(self.width, self.height)

    def describe(self) -> str:
        return f"{self.width:g} x {self.height:g} mm tissue"

    # --- edges ----------------------------------------------------------------------------

    def edge(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """End points of a named edge."""
        w, h = self.width, self.height
        ends = {"left": ((0.0, 0.0), (0.0, h)), "right": ((w, 0.0), (w, h)),
                "bottom": ((0.0, 0.0), (w, 0.0)), "top": ((0.0, h), (w, h))}[name]
        return np.asarray(ends[0]), np.asarray(ends[1])

    @staticmethod
    def inward_normal(name: str) -> np.ndarray:
        return np.asarray({"left": (1.0, 0.0), "right": (-1.0, 0.0), "bottom": (0.0, 1.0),
                           "top": (0.0, -1.0)}[name])

    def edge_mask(self, points: np.ndarray, name: str, tol: float | None = None) -> np.ndarray:
        """Mask of points (n, 2) on the named edge's line."""
        tol = self.tolerance if tol is None else tol
        coordinate, value = {"left": (0, 0.0), "right": (0, self.width), "bottom": (1, 0.0),
                             "top": (1, self.height)}[name]
        return np.abs(np.asarray(points)[:, coordinate] - value) <= tol

    def edges_at(self, point, tol: float | None = None) -> list[str]:
        """Names of the edges a point lies on (two at a corner, none inside or outside)."""
        tol = self.tolerance if tol is None else tol
        x, y = float(point[0]), float(point[1])
        if not self.contains(np.array([x, y]), tol):
            return []
        hits = (("left", abs(x) <= tol), ("right", abs(x - self.width) <= tol),
                ("bottom", abs(y) <= tol), ("top", abs(y - self.height) <= tol))
        return [name for name, hit in hits if hit]

    def segment_edge(self, start, end, tol: float | None = None) -> str | None:
        """The edge that holds the whole non-empty segment start-end, or None."""
        if np.allclose(start, end, rtol=0.0, atol=0.0):
            return None
        common = set(self.edges_at(start, tol)) & set(self.edges_at(end, tol))
        return sorted(common)[0] if common else None

    # --- inside, outside ------------------------------------------------------------------

    def contains(self, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Mask (...,) of points inside the closed domain, grown by tol."""
        points = np.asarray(points)
        return ((points[..., 0] >= -tol) & (points[..., 0] <= self.width + tol)
                & (points[..., 1] >= -tol) & (points[..., 1] <= self.height + tol))

    def outside_distance(self, point) -> float:
        """Positive outside the domain, negative inside (the largest coordinate excess); its
        zero is the boundary, and it is continuous, so a root finder can locate crossings."""
        x, y = float(point[0]), float(point[1])
        return float(max(-x, x - self.width, -y, y - self.height))

    def clip(self, points: np.ndarray) -> np.ndarray:
        """The nearest domain point of each point (...,2)."""
        return np.clip(points, [0.0, 0.0], [self.width, self.height])

    # --- circles --------------------------------------------------------------------------

    def first_exit_rotation(self, center: np.ndarray, radius: float, start_angle: float,
                            sense: float) -> float | None:
        """Smallest rotation > 0 at which the circle point center + R (cos phi, sin phi),
        phi = start_angle + sense * rotation, crosses the boundary outward; None if never."""
        candidates = []
        for axis, value in ((0, 0.0), (0, self.width), (1, 0.0), (1, self.height)):
            offset = (value - center[axis]) / radius
            if abs(offset) > 1.0:
                continue
            base = math.acos(offset) if axis == 0 else math.asin(offset)
            for phi in ((base, -base) if axis == 0 else (base, math.pi - base)):
                rotation = ((phi - start_angle) * sense) % (2 * math.pi)
                if rotation >= 1e-9:
                    candidates.append(rotation)
        for rotation in sorted(candidates):
            angle = start_angle + sense * (rotation + 1e-7)
            ahead = center + radius * np.array([math.cos(angle), math.sin(angle)])
            if not self.contains(ahead):
                return rotation
        return None


def circle_center_at_entry(domain: Rectangle, entry, radius: float, turn: str) -> tuple[np.ndarray, str]:
    """Centre of a needle of `radius` entering orthogonally at `entry` (tip tangent to the
    inward normal), on the side `turn` (cw/ccw) selects; and the entry edge's name.
    The caller has checked that `entry` lies inside exactly one edge."""
    edge = domain.edges_at(entry)[0]
    inward = domain.inward_normal(edge)
    # centre to the right of the motion for a clockwise turn, to the left for ccw
    side = np.array([inward[1], -inward[0]]) if turn == "cw" else np.array([-inward[1], inward[0]])
    return np.asarray(entry, dtype=float) + radius * side, edge
