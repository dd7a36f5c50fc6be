"""The move limits of a planned centre path (thesis Algorithm 2's centres as a path a robot
follows): each step's centre within a disc about the previous one (the move per step) and a
disc about its linear extrapolation (the second difference), braking so that the centre can
stop at the exit step; the path's largest moves, and the limits a path breaks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Planner

REFERENCE_STEP = 0.08  # rad per needle step at which the move limits (config Planner) are stated
# the exported centres are rounded to 1e-9 mm (trajectory.DECIMALS_MM), which moves a centre's
# move or second difference by up to 2e-9 mm: the planner keeps its path this far inside each
# limit, so that the limits hold on the numbers a robot reads (the summary's largest moves are
# the exported path's)
EXPORT_MARGIN_MM = 5e-9


@dataclass(frozen=True)
class MoveLimits:
    """Bounds on the centre path O(t_n) (mm per needle step of `step` rad): |O_n - O_(n-1)|
    <= step_mm and |O_n - 2 O_(n-1) + O_(n-2)| <= second_difference_mm. The bounds are stated
    at REFERENCE_STEP and scale linearly with the needle step. The centre also brakes so
    that it can stop at the exit step, which keeps the centre of the step before
    (trajectory.py): |O_n - O_(n-1)| <= second_difference_mm x (steps left before the exit)."""

    step_mm: float
    second_difference_mm: float
    last_step: int  # the step the centre brakes toward: the last before the tip is expected to leave

    @classmethod
    def for_needle(cls, geometry, settings: Planner, exit_steps: int | None = None) -> MoveLimits:
        """The scenario's limits (planner.center_step_limit and
        center_second_difference_limit, stated per REFERENCE_STEP) at the needle's step,
        braking toward the last step before the undeformed circle's exit, or toward the
        last of `exit_steps` (a pass's steps in the tissue) when the tip left earlier."""
        scale = geometry.step / REFERENCE_STEP
        last_step = geometry.expected_steps - 1
        if exit_steps is not None:
            last_step = min(last_step, exit_steps)
        return cls(_inside(settings.center_step_limit * scale), _inside(settings.center_second_difference_limit * scale),
                   last_step)

    def speed(self, step: int) -> float:
        """The largest move at `step`, braking one step early (the tip may leave a step
        before it was expected to)."""
        return min(self.step_mm, self.second_difference_mm * max(self.last_step - step, 1))

    def project(self, candidate: np.ndarray, centers: list[np.ndarray], step: int) -> np.ndarray:
        """The point nearest `candidate` within both discs: the move limit about O_(n-1) and
        the second-difference limit about 2 O_(n-1) - O_(n-2)."""
        previous = centers[-1]
        if len(centers) < 2:
            return _into_disc(np.asarray(candidate, dtype=float), previous, self.speed(step))
        return _into_both(np.asarray(candidate, dtype=float), 2.0 * previous - centers[-2],
                          self.second_difference_mm, previous, self.speed(step))


def _inside(limit: float) -> float:
    """A limit less the export's margin (EXPORT_MARGIN_MM; at most half of it)."""
    return max(limit - EXPORT_MARGIN_MM, 0.5 * limit)


def _into_disc(point: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    offset = point - center
    distance = float(np.linalg.norm(offset))
    return point if distance <= radius else center + offset * (radius / distance)


def _into_both(point: np.ndarray, center_a: np.ndarray, radius_a: float, center_b: np.ndarray,
               radius_b: float) -> np.ndarray:
    """The point of the intersection of two discs nearest `point`: a projection onto one
    disc if it lies in the other, else the nearer crossing of the two circles (if the discs
    do not meet, the point of disc a nearest disc b)."""
    for (center, radius), (other, other_radius) in (((center_a, radius_a), (center_b, radius_b)),
                                                    ((center_b, radius_b), (center_a, radius_a))):
        projected = _into_disc(point, center, radius)
        if np.linalg.norm(projected - other) <= other_radius * (1 + 1e-12):
            return projected
    axis = center_b - center_a
    distance = float(np.linalg.norm(axis))
    if distance >= radius_a + radius_b:
        return center_a + axis * (radius_a / distance)
    along = (radius_a ** 2 - radius_b ** 2 + distance ** 2) / (2.0 * distance)
    across = np.sqrt(max(radius_a ** 2 - along ** 2, 0.0))
    middle = center_a + axis * (along / distance)
    normal = np.array([-axis[1], axis[0]]) / distance
    crossings = (middle + across * normal, middle - across * normal)
    return min(crossings, key=lambda crossing: float(np.linalg.norm(crossing - point)))


def center_moves(centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|O_n - O_(n-1)| (n - 1,) and |O_n - 2 O_(n-1) + O_(n-2)| (n - 2,) of a centre path (n, 2), mm."""
    centers = np.asarray(centers, dtype=float).reshape(-1, 2)
    return (np.linalg.norm(np.diff(centers, axis=0), axis=1),
            np.linalg.norm(np.diff(centers, 2, axis=0), axis=1) if len(centers) > 2 else np.zeros(0))


def path_smoothness(centers: np.ndarray) -> tuple[float, float]:
    """Largest centre move and largest second difference (mm) of a centre path (n, 2)."""
    moves, second = center_moves(centers)
    return float(moves.max(initial=0.0)), float(second.max(initial=0.0))


def broken_limits(centers: np.ndarray, limits: MoveLimits) -> list[str]:
    """The move limits a centre path (n, 2) breaks, each as the largest breach and its row."""
    moves, second = center_moves(centers)
    broken = []
    slack = 1e-6  # mm: the limits hold to round-off, and the exported centres are rounded to 1e-9 mm
    if len(moves) and moves.max() > limits.step_mm + slack:
        k = int(np.argmax(moves))
        broken.append(f"a move of {moves[k]:.3g} mm into row {k + 1} (limit {limits.step_mm:.3g} mm)")
    if len(second) and second.max() > limits.second_difference_mm + slack:
        k = int(np.argmax(second))
        broken.append(f"a second difference of {second[k]:.3g} mm at row {k + 2} (limit "
                      f"{limits.second_difference_mm:.3g} mm)")
    return broken
