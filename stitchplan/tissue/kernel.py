"""Cubic-spline kernel of the reproducing kernel particle method (thesis eq. 3.22-3.23)."""

from __future__ import annotations

import numpy as np


def cubic_spline(z: np.ndarray, derivative: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Cubic spline phi(z) of eq. 3.23 and its derivative d phi / dz (support |z| < 1; None
    without `derivative`): 2/3 - 4 r^2 + 4 r^3 for r = |z| <= 1/2, 4/3 (1 - r)^3 for 1/2 < r < 1."""
    r = np.abs(z)
    inner = r <= 0.5
    rest = np.maximum(1.0 - r, 0.0)
    r2, rest2 = r * r, rest * rest  # products: numpy's power is several times slower
    phi = np.where(inner, 2.0 / 3.0 - 4.0 * r2 + 4.0 * r2 * r, 4.0 / 3.0 * rest2 * rest)
    if not derivative:
        return phi, None
    dphi = np.where(inner, -8.0 * r + 12.0 * r2, -4.0 * rest2)
    return phi, dphi * np.sign(z)


def tensor_kernel(offset: np.ndarray, support: np.ndarray,
                  gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Tensor-product kernel phi_a(X - X_I) of eq. 3.22 and its gradient with respect to X.

    offset: (n, 2) values X - X_I; support: (n,) kernel half-width a of each pair.
    Returns phi (n,) and grad (n, 2) (None without `gradient`).
    """
    a = support[:, None]  # (n, 1)
    phi_1d, dphi_1d = cubic_spline(offset / a, gradient)  # (n, 2) each
    phi = phi_1d[:, 0] * phi_1d[:, 1] / support**2
    if not gradient:
        return phi, None
    scale = 1.0 / support**3
    grad = np.empty_like(offset)
    grad[:, 0] = dphi_1d[:, 0] * phi_1d[:, 1] * scale
    grad[:, 1] = phi_1d[:, 0] * dphi_1d[:, 1] * scale
    return phi, grad
