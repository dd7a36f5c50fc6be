"""Rectangle: the slab [0, W] x [0, H] and its named edges; a needle's centre at its entry."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .bounding_box import BoundingBox
from .polygon_domain import circle_crossings
from .boundary import nearest_boundary_point

EDGE_NAMES = ("left", "right", "bottom", "top")


@dataclass(frozen=True)
class Rectangle(BoundingBox):
    """The slab [0, W] x [0, H]."""

    width: float
    height: float

    @classmethod
    def of_size(cls, size) -> Rectangle:
        return cls(float(size[0]), float(size[1]))

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

    # --- general shapes ask the same questions ------------------------------------------------

    origin = np.zeros(2)
    holes: tuple = ()
    convex = True

    def boundary_segments(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The four edges, counter-clockwise (tissue on the left)."""
        w, h = self.width, self.height
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        return list(zip(corners, np.roll(corners, -1, axis=0)))

    def nearest_boundary_point(self, point) -> tuple[np.ndarray, bool]:
        """The boundary point nearest `point`, and True: every edge is the outline's (no holes).
        A needle leaving through the far side of a thin slab and coming back in crosses it
        as it would a wound's wall (needle.wound_crossings asks for the wall)."""
        return nearest_boundary_point(self, point)[0], True

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (...,) of points to the boundary."""
        points = np.asarray(points, dtype=float)
        x, y = points[..., 0], points[..., 1]
        inside = np.minimum.reduce([x, self.width - x, y, self.height - y])
        outside = np.hypot(np.maximum.reduce([-x, x - self.width, 0 * x]),
                           np.maximum.reduce([-y, y - self.height, 0 * y]))
        return np.where(inside >= 0, inside, outside)

    def blocked(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Convex: no segment between tissue points leaves it."""
        return np.zeros(len(starts), dtype=bool)

    def circle_crossings(self, center, radius: float, start_angle: float, sense: float,
                         max_rotation: float = 2 * math.pi) -> list[tuple[float, str]]:
        """Every crossing of the circle with the boundary within max_rotation, in order."""
        ends = self.boundary_segments()
        return circle_crossings(self, np.array([a for a, _ in ends]), np.array([b for _, b in ends]),
                                np.asarray(center, float), radius, start_angle, sense, max_rotation)

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
    The caller has checked that `entry` lies inside exactly one edge, or on a smooth vertex
    (smooth_vertex), whose inward normal is the mean of its two edges'."""
    names = domain.edges_at(entry)
    edge = names[0]
    inward = sum(domain.inward_normal(name) for name in names)
    inward = inward / float(np.hypot(*inward))
    # centre to the right of the motion for a clockwise turn, to the left for ccw
    side = np.array([inward[1], -inward[0]]) if turn == "cw" else np.array([-inward[1], inward[0]])
    return np.asarray(entry, dtype=float) + radius * side, edge
