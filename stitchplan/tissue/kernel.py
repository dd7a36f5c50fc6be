"""Cubic-spline kernel of the reproducing kernel particle method (thesis eq. 3.22-3.23)."""

from __future__ import annotations

import numpy as np


def cubic_spline(z: np.ndarray, derivative: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Cubic spline phi(z) of eq. 3.23 and its derivative d phi / dz (support |z| < 1; None
    without `derivative`): 2/3 - 4 r^2 + 4 r^3 for r = |z| <= 1/2, 4/3 (1 - r)^3 for 1/2 < r < 1.

    Evaluated as the B-spline's truncated powers, 4/3 (1 - r)+^3 - 16/3 (1/2 - r)+^3, the same
    polynomials without computing both branches everywhere."""
    r = np.abs(z)
    outer = np.maximum(1.0 - r, 0.0)
    inner = np.maximum(0.5 - r, 0.0)
    outer2, inner2 = outer * outer, inner * inner  # products: numpy's power is several times slower
    phi = (4.0 / 3.0) * (outer2 * outer) - (16.0 / 3.0) * (inner2 * inner)
    if not derivative:
        return phi, None
    # d phi / dr = 16 (1/2 - r)+^2 - 4 (1 - r)+^2 <= 0, times sign(z)
    return phi, np.copysign(4.0 * outer2 - 16.0 * inner2, -z)


def tensor_kernel(offset: np.ndarray, support: np.ndarray,
                  gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Tensor-product kernel phi_a(X - X_I) of eq. 3.22 and its gradient with respect to X.

    offset: (n, 2) values X - X_I; support: (n,) kernel half-width a of each pair.
    Returns phi (n,) and grad (n, 2) (None without `gradient`).
    """
    inverse = 1.0 / support  # products below: numpy's power is several times slower
    phi_1d, dphi_1d = cubic_spline(offset * inverse[:, None], gradient)  # (n, 2) each
    inverse2 = inverse * inverse
    phi_x, phi_y = phi_1d[:, 0], phi_1d[:, 1]
    phi = phi_x * phi_y * inverse2
    if not gradient:
        return phi, None
    scale = inverse2 * inverse
    grad = np.empty_like(offset)
    np.multiply(dphi_1d[:, 0] * phi_y, scale, out=grad[:, 0])
    np.multiply(phi_x * dphi_1d[:, 1], scale, out=grad[:, 1])
    return phi, grad
