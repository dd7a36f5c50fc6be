"""The needle's hold on the tissue along its track Gamma_N (thesis eq. 3.58-3.65).

Gamma_N is the sequence of material points the tip has reached, in the reference
configuration. It carries

- friction `friction` N per mm of needle inside the tissue, along the needle (eq. 3.58):
  a line load on Gamma_N, each segment between consecutive needle points carrying the
  needle length R * step it stands for, integrated with two Gauss points (eq. 3.64);
- the cutting force, spread over the tip segment ("the first segment of the needle");
- one constraint per needle point keeping its spatial position on the needle circle,
  written as the residual g_k = |x_k - C| - R that Newton drives to zero (eq. 3.59-3.65),
  so the points do not drift off the needle over many steps.

Arrays: `free` (n_free, 2) free coefficients; generalised forces and G's rows are
interleaved over (particle, direction), length 2 n_free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..config import Needle
from ..tissue.model import TissueModel
from .geometry import NeedleGeometry

GAUSS_POINTS = 0.5 + np.array([-0.5, 0.5]) / math.sqrt(3.0)  # two-point rule on [0, 1]


@dataclass(frozen=True)
class ConstraintValues:
    """The needle constraints at one state (eq. 3.59-3.61)."""

    violation: np.ndarray  # g_k = |x_k - C| - R, (k,)
    normal: np.ndarray  # n_k = (x_k - C) / |x_k - C|, (k, 2)
    rho: np.ndarray  # |x_k - C|, (k,)


class NeedleCoupling:
    """Gamma_N with its shape-function rows, the needle loads and the constraints on it."""

    def __init__(self, model: TissueModel, geometry: NeedleGeometry, needle: Needle):
        self.model = model
        self.geometry = geometry
        self.needle = needle
        n_free = model.n_free
        self.points = np.zeros((0, 2))  # Gamma_N, reference, (k, 2)
        self.point_rows = sp.csr_matrix((0, n_free))  # N(X_k) T, (k, n_free)
        self._point_rows_coo = self.point_rows.tocoo()
        self.expanded_rows = self._expand(self.point_rows)  # N(X_k) T on interleaved dofs, (2k, 2 n_free)
        self.segment_points = np.zeros((0, 2))  # Gauss points of the segments, reference, 2 per segment
        self.segment_rows = sp.csr_matrix((0, n_free))  # N(X_s) T at those points

    def _rows_at(self, points: np.ndarray) -> sp.csr_matrix:
        return self.model.shape_functions_at(points).values @ self.model.boundary.free_map

    def _expand(self, rows: sp.csr_matrix) -> sp.csr_matrix:
        """N T acting on interleaved dofs: rows (k, i), columns (p, i)."""
        coo = rows.tocoo()
        return sp.csr_matrix(
            (np.concatenate([coo.data, coo.data]),
             (np.concatenate([2 * coo.row, 2 * coo.row + 1]), np.concatenate([2 * coo.col, 2 * coo.col + 1]))),
            shape=(2 * rows.shape[0], 2 * self.model.n_free))

    def add(self, reference_point: np.ndarray) -> None:
        """Append a needle point, and the Gauss points of the segment it closes."""
        if len(self.points):
            new = self.points[-1] + GAUSS_POINTS[:, None] * (reference_point - self.points[-1])
            self.segment_points = np.vstack([self.segment_points, new])
            self.segment_rows = sp.vstack([self.segment_rows, self._rows_at(new)], format="csr")
        row = self._rows_at(reference_point[None])
        self.points = np.vstack([self.points, reference_point])
        self.point_rows = sp.vstack([self.point_rows, sp.csr_matrix(row)], format="csr")
        self._point_rows_coo = self.point_rows.tocoo()
        self.expanded_rows = self._expand(self.point_rows)

    # --- loads ------------------------------------------------------------------------------

    def load_magnitudes(self) -> np.ndarray:
        """Force (N) carried by each Gauss point of Gamma_N: friction on every segment,
        plus the cutting force on the tip segment (eq. 3.58, 3.64)."""
        segments = len(self.segment_points) // 2
        per_segment = np.full(segments, self.needle.friction * self.geometry.insertion_step)
        if segments:
            per_segment[-1] += self.needle.cutting_force
        return np.repeat(0.5 * per_segment, 2)

    def needle_force(self, free: np.ndarray, center: np.ndarray) -> np.ndarray:
        """f_needle (2 n_free,): the line loads along the direction of needle motion a_0 at
        the spatial Gauss points (eq. 3.64)."""
        load_points = self.segment_points + self.segment_rows @ free  # spatial, (2 segments, 2)
        angles = np.arctan2(load_points[:, 1] - center[1], load_points[:, 0] - center[0])
        tangent = self.geometry.tangent(angles)  # a_0, (2 segments, 2)
        magnitude = self.load_magnitudes()
        return (self.segment_rows.T @ (magnitude[:, None] * tangent)).ravel()

    # --- constraints ------------------------------------------------------------------------

    def constraint_values(self, free: np.ndarray, center: np.ndarray) -> ConstraintValues:
        spatial = self.points + self.point_rows @ free  # (k, 2)
        relative = spatial - center
        rho = np.linalg.norm(relative, axis=1)
        return ConstraintValues(rho - self.geometry.radius, relative / rho[:, None], rho)

    def constraint_force(self, multipliers: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """G lambda = N^T (lambda_k n_k), interleaved (2 n_free,)."""
        return self.expanded_rows.T @ (multipliers[:, None] * normal).ravel()

    def constraint_matrix(self, normal: np.ndarray) -> sp.csr_matrix:
        """G of eq. 3.65 for the residual form g_k = |x_k - C| - R: column k = N_k^T n_k."""
        rows = self._point_rows_coo
        return sp.csr_matrix(
            (np.concatenate([rows.data * normal[rows.row, 0], rows.data * normal[rows.row, 1]]),
             (np.concatenate([2 * rows.col, 2 * rows.col + 1]), np.concatenate([rows.row, rows.row]))),
            shape=(2 * self.model.n_free, len(self.points)))

    @staticmethod
    def _projections(multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """lambda_k (I - n_k n_k^T) / rho_k, (k, 2, 2)."""
        return multipliers[:, None, None] * (np.eye(2) - normal[:, :, None] * normal[:, None, :]) / rho[:, None, None]

    def curvature(self, multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> sp.csr_matrix:
        """H = sum_k lambda_k d^2 g_k = N^T blockdiag(lambda_k (I - n_k n_k^T) / rho_k) N."""
        k = len(self.points)
        if k == 0:
            return sp.csr_matrix((2 * self.model.n_free, 2 * self.model.n_free))
        blocks = self._projections(multipliers, normal, rho)
        block_matrix = sp.bsr_matrix((blocks, np.arange(k), np.arange(k + 1)), shape=(2 * k, 2 * k)).tocsr()
        return (self.expanded_rows.T @ block_matrix @ self.expanded_rows).tocsr()

    def center_derivative(self, multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """d r_u / dC = -sum_k lambda_k N_k^T (I - n_k n_k^T) / rho_k, (2 n_free, 2)."""
        blocks = self._projections(-multipliers, normal, rho)  # (k, i, j)
        return np.column_stack([self.expanded_rows.T @ blocks[:, :, j].ravel() for j in range(2)])
