"""Background-cell Gauss quadrature over the rectangle and 1D Gauss rules on boundary segments."""

from __future__ import annotations

import numpy as np


def gauss_legendre(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and weights on [0, 1]."""
    points, weights = np.polynomial.legendre.leggauss(order)
    return 0.5 * (points + 1.0), 0.5 * weights


def cell_quadrature(
    size: tuple[float, float], cells: tuple[int, int], order: int
) -> tuple[np.ndarray, np.ndarray]:
    """Tensor Gauss rule of `order` points per direction in each of nx x ny equal cells.

    Returns points (n, 2) and weights (n,) (areas, mm^2) ordered cell by cell.
    """
    (width, height), (nx, ny) = size, cells
    dx, dy = width / nx, height / ny
    s, w = gauss_legendre(order)
    local = np.stack(np.meshgrid(s, s, indexing="ij"), axis=-1).reshape(-1, 2)  # (g, 2)
    local_w = np.outer(w, w).ravel()
    corners = np.stack(np.meshgrid(np.arange(nx) * dx, np.arange(ny) * dy, indexing="ij"), axis=-1)
    corners = corners.reshape(-1, 1, 2)  # (cells, 1, 2)
    points = corners + local[None] * np.array([dx, dy])
    weights = np.broadcast_to(local_w * dx * dy, points.shape[:2])
    return points.reshape(-1, 2), weights.ravel().copy()


def segment_quadrature(
    start: np.ndarray, end: np.ndarray, pieces: int, order: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule on the straight segment start-end split in `pieces`; weights are lengths (mm)."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    s, w = gauss_legendre(order)
    t = ((np.arange(pieces)[:, None] + s[None, :]) / pieces).ravel()
    length = float(np.linalg.norm(end - start))
    points = start + t[:, None] * (end - start)
    weights = np.tile(w, pieces) * length / pieces
    return points, weights
