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


def natural_boundary_quadrature(
    size: tuple[float, float], essential: list[tuple[np.ndarray, np.ndarray]], interval: float, order: int,
    boundary: list | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss rule on the rectangle's boundary minus the `essential` pieces (segments along its
    edges: clamped edges, prescribed-displacement segments).

    Each edge is cut at its ends, every `interval` mm and at the ends of the essential pieces
    on it; intervals whose midpoint lies on an essential piece are dropped. Returns points
    (n, 2), outward unit normals (n, 2) and weights (n,) (lengths, mm). `boundary` replaces
    the rectangle's edges by any (start, end, outward normal) edges (a polygon, holes).
    """
    width, height = size
    tol = 1e-9 * max(size)
    edges = (  # start, end, outward normal
        ((0.0, 0.0), (width, 0.0), (0.0, -1.0)),
        ((width, 0.0), (width, height), (1.0, 0.0)),
        ((width, height), (0.0, height), (0.0, 1.0)),
        ((0.0, height), (0.0, 0.0), (-1.0, 0.0)),
    )
    if boundary is not None:
        edges = boundary
    s, w = gauss_legendre(order)
    points, normals, weights = [], [], []
    for start, end, normal in edges:
        start, end = np.asarray(start), np.asarray(end)
        length = float(np.linalg.norm(end - start))
        direction = (end - start) / length
        cuts = [np.linspace(0.0, length, max(int(np.ceil(length / interval - 1e-9)), 1) + 1)]
        pieces = []
        for a, b in essential:
            ta, tb = (float((np.asarray(p, float) - start) @ direction) for p in (a, b))
            off = max(abs(float(direction[0] * (p[1] - start[1]) - direction[1] * (p[0] - start[0])))
                      for p in (a, b))
            if off <= tol:  # the piece lies on this edge
                low, high = sorted((ta, tb))
                pieces.append((low, high))
                cuts.append(np.clip([low, high], 0.0, length))
        breaks = np.unique(np.round(np.concatenate(cuts) / tol) * tol)
        left, right = breaks[:-1], breaks[1:]
        middle = 0.5 * (left + right)
        keep = right - left > tol
        for low, high in pieces:
            keep &= ~((middle >= low - tol) & (middle <= high + tol))
        left, right = left[keep], right[keep]
        t = (left[:, None] + s[None, :] * (right - left)[:, None]).ravel()
        points.append(start + t[:, None] * direction)
        normals.append(np.broadcast_to(np.asarray(normal, float), (len(t), 2)))
        weights.append((w[None, :] * (right - left)[:, None]).ravel())
    return np.concatenate(points), np.concatenate(normals), np.concatenate(weights)
