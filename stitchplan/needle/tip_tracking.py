"""Tip tracking: the material point the needle tip reaches in one rotation step
(thesis eq. 3.66-3.70), by the inverse deformation gradient or by Levenberg-Marquardt."""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize

from ..errors import TipTrackingJump


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
