"""Rigid circular needle: geometry, desired exit and tip tracking (thesis section 3.1.5).

Angles: the needle tip sits at C + R (cos phi, sin phi); the needle rotation alpha >= 0
since entry advances phi = phi0 + sense * alpha, with sense -1 for a clockwise turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ..config import Needle, ScenarioError

EDGE_NORMALS = {"left": (1.0, 0.0), "right": (-1.0, 0.0), "bottom": (0.0, 1.0), "top": (0.0, -1.0)}


def unit(angle: float | np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def inside(points: np.ndarray, size: tuple[float, float], tol: float = 0.0) -> np.ndarray:
    points = np.asarray(points)
    return ((points[..., 0] >= -tol) & (points[..., 0] <= size[0] + tol)
            & (points[..., 1] >= -tol) & (points[..., 1] <= size[1] + tol))


@dataclass(frozen=True)
class NeedleGeometry:
    """The needle at entry: centre, start angle, turning sense and the desired exit."""

    radius: float
    arc: float
    center: np.ndarray  # (2,) reference centre at entry
    start_angle: float  # phi0, angle of the entry point seen from the centre
    sense: float  # +1 ccw, -1 cw
    step: float  # rad per step
    entry: np.ndarray  # (2,)
    entry_edge: str
    exit_rotation: float  # alpha at which the undeformed circle leaves the tissue
    desired_exit: np.ndarray  # (2,)

    def tip(self, rotation: float | np.ndarray, center: np.ndarray | None = None) -> np.ndarray:
        """Tip position of the rigid needle after `rotation` (rad) about `center`."""
        center = self.center if center is None else center
        return center + self.radius * unit(self.start_angle + self.sense * np.asarray(rotation))

    def tangent(self, angle: float | np.ndarray) -> np.ndarray:
        """Direction of needle motion at the point of polar angle `angle` (a_0 of eq. 3.58)."""
        return self.sense * np.stack([-np.sin(angle), np.cos(angle)], axis=-1)

    @property
    def insertion_step(self) -> float:
        """IS = R theta (eq. 3.69)."""
        return self.radius * self.step


def needle_geometry(needle: Needle, size: tuple[float, float]) -> NeedleGeometry:
    """Centre on the boundary tangent at the entry (orthogonal entry), desired exit where the
    undeformed circle first leaves the tissue (SCENARIO.md, "Needle geometry")."""
    width, height = size
    entry = np.asarray(needle.entry, dtype=float)
    tol = 1e-9 * max(size)
    edges = [edge for edge, hit in (("left", abs(entry[0]) <= tol), ("right", abs(entry[0] - width) <= tol),
                                    ("bottom", abs(entry[1]) <= tol), ("top", abs(entry[1] - height) <= tol)) if hit]
    if not inside(entry, size, tol) or not edges:
        raise ScenarioError(f"needle.entry: got {list(needle.entry)}, expected a point on the "
                            f"boundary of the {width:g} x {height:g} mm tissue")
    if len(edges) > 1:
        raise ScenarioError(f"needle.entry: got {list(needle.entry)}, a corner; expected a point "
                            "inside one edge (the entry normal is undefined at a corner)")
    inward = np.asarray(EDGE_NORMALS[edges[0]])
    sense = -1.0 if needle.turn == "cw" else 1.0
    # centre to the right of the motion for a clockwise turn, to the left for ccw
    side = np.array([inward[1], -inward[0]]) if sense < 0 else np.array([-inward[1], inward[0]])
    center = entry + needle.radius * side
    start_angle = math.atan2(*(entry - center)[::-1])
    geometry = NeedleGeometry(needle.radius, needle.arc, center, start_angle, sense, needle.step, entry,
                              edges[0], 0.0, entry)
    rotation = first_exit_rotation(geometry, size)
    if rotation is None or rotation > needle.arc + 1e-9:
        reach = "never leaves the tissue" if rotation is None else f"leaves after {rotation:.4g} rad"
        raise ScenarioError(
            f"needle: the {needle.radius:g} mm needle entering at {list(needle.entry)} turning "
            f"{needle.turn} {reach}; expected an exit within its arc of {needle.arc:.4g} rad"
        )
    if rotation < 2 * needle.step:
        raise ScenarioError(
            f"needle: the needle entering at {list(needle.entry)} turning {needle.turn} exits after "
            f"{rotation:.3g} rad, expected at least two steps of {needle.step:g} rad inside the tissue"
        )
    from dataclasses import replace

    return replace(geometry, exit_rotation=rotation, desired_exit=geometry.tip(rotation))


def first_exit_rotation(geometry: NeedleGeometry, size: tuple[float, float]) -> float | None:
    """Smallest rotation > 0 at which the undeformed circle crosses the boundary outward."""
    width, height = size
    candidates = []
    c, r = geometry.center, geometry.radius
    for axis, value in ((0, 0.0), (0, width), (1, 0.0), (1, height)):
        offset = (value - c[axis]) / r
        if abs(offset) > 1.0:
            continue
        base = math.acos(offset) if axis == 0 else math.asin(offset)
        angles = (base, -base) if axis == 0 else (base, math.pi - base)
        for phi in angles:
            rotation = ((phi - geometry.start_angle) * geometry.sense) % (2 * math.pi)
            if rotation < 1e-9:
                continue
            candidates.append(rotation)
    for rotation in sorted(candidates):
        ahead = geometry.tip(rotation + 1e-7)
        if not inside(ahead, size):
            return rotation
    return None


# --- tip tracking ----------------------------------------------------------------------


class TipTrackingJump(ArithmeticError):
    """The inverse-gradient step departs from the expected one (thesis section 5.1.1)."""


def inverse_gradient_step(reference_tip: np.ndarray, spatial_tip: np.ndarray,
                          deformation_gradient: np.ndarray, target: np.ndarray,
                          expected_length: float, expected_direction: np.ndarray,
                          displacement=None, jump_ratio: float = 2.0,
                          jump_angle: float = math.radians(60.0), mismatch: float = 0.05) -> np.ndarray:
    """X_{n+1} = X_n + F^-1 (x_{n+1} - x_n) (eq. 3.66-3.67).

    Raises TipTrackingJump when the step in the material is longer than jump_ratio x or
    shorter than 1/jump_ratio x the expected one, turns more than jump_angle from it, or
    (with `displacement`, a callable X -> u(X)) when the point it finds is mapped more than
    `mismatch` x the expected step away from the target: F at X_n no longer describes the
    deformation over one step.
    """
    step = np.linalg.solve(deformation_gradient, target - spatial_tip)
    length = float(np.linalg.norm(step))
    cosine = float(step @ expected_direction) / max(length * np.linalg.norm(expected_direction), 1e-300)
    if (length > jump_ratio * expected_length or length < expected_length / jump_ratio
            or cosine < math.cos(jump_angle)):
        raise TipTrackingJump(
            f"inverse-gradient step of {length:.3g} mm at {math.degrees(math.acos(max(-1, min(1, cosine)))):.0f} deg "
            f"from the expected {expected_length:.3g} mm step"
        )
    point = reference_tip + step
    if displacement is not None:
        miss = float(np.linalg.norm(point + displacement(point) - target))
        if miss > mismatch * expected_length:
            raise TipTrackingJump(f"inverse-gradient step lands {miss:.3g} mm from the needle "
                                  f"(more than {mismatch:g} x the {expected_length:.3g} mm step)")
    return point


def levenberg_marquardt_tip(previous_tip: np.ndarray, center: np.ndarray, radius: float,
                            insertion_step: float, start: np.ndarray, displacement_and_gradient
                            ) -> tuple[np.ndarray, int]:
    """Minimise C(X) = (|X + u(X) - O| - R)^2 + (|X - X_prev| - IS)^2 (eq. 3.68-3.69) by
    Levenberg-Marquardt from the start point of eq. 3.70. Returns (X, evaluations)."""

    last: dict = {}

    def evaluate(x):
        # least_squares asks for the residuals and then the Jacobian at the same point
        if last.get("x") is None or not np.array_equal(last["x"], x):
            last["x"], last["value"] = np.array(x), displacement_and_gradient(x)
        return last["value"]

    def residuals(x):
        u, grad_u = evaluate(x)
        spatial = x + u - center
        return np.array([np.linalg.norm(spatial) - radius, np.linalg.norm(x - previous_tip) - insertion_step])

    def jacobian(x):
        u, grad_u = evaluate(x)
        spatial = x + u - center
        normal = spatial / np.linalg.norm(spatial)
        chord = x - previous_tip
        return np.vstack([normal @ (np.eye(2) + grad_u), chord / max(np.linalg.norm(chord), 1e-300)])

    result = scipy.optimize.least_squares(residuals, start, jac=jacobian, method="lm", xtol=1e-13,
                                          ftol=1e-13, gtol=1e-13, max_nfev=200)
    return result.x, int(result.nfev)
