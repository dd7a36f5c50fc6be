"""The needle's hold on the tissue along its track Gamma_N (thesis eq. 3.58-3.65).

Gamma_N is the sequence of material points the tip has reached, in the reference
configuration, joined by straight segments. It carries

- friction `friction` N per mm of needle inside the tissue, along the needle (eq. 3.58):
  a line load on Gamma_N, each segment carrying the needle length R * step it stands for,
  integrated with two Gauss points (eq. 3.64) on each of the segment's pieces (mortar: as
  many pieces as keep the points at most a particle spacing apart, track_layout's
  segment_subintervals; one on the shipped scenes at their spacing and at half of it);
- the cutting force at the tip;
- the constraint that keeps the track on the needle circle, g = |x(X) - C| - R = 0,
  written as a residual that Newton drives to zero (eq. 3.59-3.65), so the track does not
  drift off the needle over many steps. Eq. 3.59 holds the incremental form, u^T a_1 = 0
  (no displacement towards the centre); g is its total form, whose linearisation about the
  current state is that (a_1 = (x - C) / |x - C|), and whose value does not accumulate the
  increments' round-off and linearisation error over the steps.

Two couplings (`needle.coupling`):

- `points`, the thesis's: one multiplier per needle point, g_k = |x(X_k) - C| - R = 0, and
  the cutting force on the tip segment. The multipliers are point forces R * step apart
  and the cutting force acts on one step's length, so refining the particles below that
  length resolves the log-singular displacement of a point force in 2D instead of
  converging (benchmarks/results/needle_coupling.md).
- `mortar`: a multiplier field mu(s) on Gamma_N, discretised independently of the needle
  points: continuous and piecewise linear (MULTIPLIER_ORDER 1; 0 gives one constant per
  element) on elements of whole segments at least MULTIPLIER_SPACINGS local particle
  spacings (and `needle.multiplier_length` mm, if given) long, counted from the tip (where
  the loads act) so a shorter remainder sits at the entry. No more multipliers than the
  particles can resolve keeps the discrete inf-sup condition (Babuska 1973, Brezzi 1974;
  mortar methods: Wohlmuth 2000; tests/test_needle_coupling.py checks the normalised Schur
  complement). The constraint is enforced weakly, g_j = int phi_j g(X(s)) ds / int phi_j ds
  = 0 per multiplier (the segments' Gauss points), so lambda_j is a force. A Gauss point of a segment is asked to lie
  on the chord between the needle points (see `target_radius`), not on the arc. The
  cutting force is spread uniformly over `cutting_length` mm of needle behind the tip (a
  physical length: the needle point's cutting edge and taper), not over one step; with
  CUTTING_PROFILE "smooth" as the density (2 / l) sin^2(pi s / l) over it instead (see
  load_quadrature's CUTTING_PROFILE and TrackLoads, `needle.cutting_ramp`;
  benchmarks/results/needle_coupling.md).

  `needle.multiplier_ends: arc` cuts the elements at exact arc lengths instead: the track
  measured in local spacings, cut every MULTIPLIER_SPACINGS from the tip, so the element
  length is c h and follows the spacing smoothly (whole segments jump: 3 then 2 segments of
  0.71 mm on the SH 1/2 scenes); its constraint has its own Gauss points per segment (at
  least two, more where an element is shorter than a segment). It does not converge better
  (benchmarks/results/needle_coupling.md): most of the change under refinement comes from
  the tissue's response to the cutting force, not from the multiplier space.

Both are written on one constraint quadrature: points X_q with shape-function rows N_q and
a sparse weight matrix W (Q, m) whose columns sum to one, so that g_j = sum_q W_qj g_q and
G_j = sum_q W_qj N_q^T n_q (the point coupling: the needle points with W = I).
`weights_matrix` B (2Q, m), B[2q + d, j] = W_qj n_q,d, gives G = E^T B, E the interleaved
rows of the quadrature points: the saddle-point solvers cache K^-1 E^T once per quadrature
point and form K^-1 G = (K^-1 E^T) B.

Loads follow Algorithm 1's ramp: within a step the load is (1 - beta) x the previous
step's load + beta x this step's (the new segment's friction and the cutting force moved to
the new tip), beta = `load_factor` raised to one by needle/equilibrium.py.

Arrays: `free` (n_free, 2) free coefficients; generalised forces and G's rows are
interleaved over (particle, direction), length 2 n_free.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..config import Needle
from ..tissue.model import TissueModel
from ..tissue.quadrature import gauss_legendre
from .constraint_rows import GrowingRows, empty_row_block, joined_rows, row_block, row_block_matrix
from .geometry import NeedleGeometry
from .load_quadrature import LoadQuadrature, TrackLoads, segment_gauss_points
from .track_layout import (ARC_ENDS, MORTAR, MULTIPLIER_SPACINGS, POINTS, QUADRATURE_PER_ELEMENT, SEGMENT_ENDS,
                           segment_subintervals)

MULTIPLIER_ORDER = 1  # mortar multipliers: 0 piecewise constant, 1 continuous piecewise linear
PARTITION_FROM_TIP = True  # mortar elements counted from the tip (the shorter remainder at the entry)


def _element_starts(lengths: np.ndarray, needed: np.ndarray, from_tip: bool) -> list[int]:
    """First segment of each mortar element: whole segments grouped until each group is at
    least `needed` (the largest of its segments') long, counted from the tip or from the
    entry; a shorter remainder joins its neighbour (one element while the track is shorter)."""
    order = range(len(lengths) - 1, -1, -1) if from_tip else range(len(lengths))
    groups, current, length, longest = [], [], 0.0, 0.0
    for j in order:  # the track's segments: tens
        current.append(j)
        length, longest = length + lengths[j], max(longest, needed[j])
        if length >= longest and length > 0.0:  # a gap's zero-length segment joins a neighbour
            groups.append(current)
            current, length, longest = [], 0.0, 0.0
    if current:
        if groups:
            groups[-1].extend(current)
        else:
            groups.append(current)
    return sorted(min(group) for group in groups)


def _own_rows(attributes: dict) -> dict:
    """A coupling's attributes with copies of its growing rows, which append in place (the
    segment and quadrature rows may be one object, and stay one), without the caches a state
    need not keep (rebuilt when first asked for): a state is kept per needle step, and caches
    that grow with the track would make a long insertion's states grow with its square."""
    attributes = dict(attributes)
    rows = (attributes["_segment_rows"], attributes["_quadrature_rows"])
    copies = {id(part): copy.copy(part) for part in rows}
    attributes["_segment_rows"], attributes["_quadrature_rows"] = (copies[id(part)] for part in rows)
    attributes["_track_rows"] = None
    return attributes


@dataclass(frozen=True)
class ConstraintValues:
    """The needle constraints at one state (eq. 3.59-3.61)."""

    violation: np.ndarray  # g_j = sum_q W_qj (|x_q - C| - R_q), R_q the point's target_radius, (m,)
    normal: np.ndarray  # n_q = (x_q - C) / |x_q - C|, (Q, 2)
    rho: np.ndarray  # |x_q - C|, (Q,)



class NeedleCoupling:
    """Gamma_N with its shape-function rows, the needle loads and the constraints on it."""

    def __init__(self, model: TissueModel, geometry: NeedleGeometry, needle: Needle, dilation: float = 2.0):
        self.model = model
        self.geometry = geometry
        self.needle = needle
        self._read_options(needle, geometry)
        self._spacing = model.support / dilation  # local particle spacing, (NP,)
        pieces = self._segment_pieces()
        self._start_track(pieces)
        self._start_rows()
        self._start_multipliers()
        self._start_loads()
        self._start_target_radius(pieces)

    def _read_options(self, needle: Needle, geometry: NeedleGeometry) -> None:
        """The coupling's options from the needle block (config Needle)."""
        self.kind = getattr(needle, "coupling", POINTS)
        self.cutting_length = float(getattr(needle, "cutting_length", geometry.insertion_step))
        # `needle.cutting_ramp` (mortar): False, the whole cutting force from the first step on
        # (over the needle inside while that is shorter than cutting_length); True,
        # cutting_force / cutting_length per mm of cutting edge inside, so it grows over the
        # first steps (benchmarks/results/needle_coupling.md: the whole force on the first
        # step's 0.7 mm at the free edge has no resolved solution)
        self.cutting_ramp = bool(getattr(needle, "cutting_ramp", False))
        self.track_loads = TrackLoads(geometry.insertion_step, needle.friction, needle.cutting_force,
                                      self.cutting_length, self.cutting_ramp, on_tip_segment=self.kind == POINTS)
        # `needle.multiplier_length` (mortar): the elements' least length in mm besides
        # MULTIPLIER_SPACINGS local spacings (0: none); fixed in mm, the multiplier space stays
        # the same when the particles are refined
        self.multiplier_length = float(getattr(needle, "multiplier_length", None) or 0.0)
        self.arc_ends = self.kind == MORTAR and getattr(needle, "multiplier_ends", SEGMENT_ENDS) == ARC_ENDS

    def _segment_pieces(self) -> int:
        """The pieces of a segment that carry two Gauss points each: `segment_subintervals` at the
        particle spacing at the needle (mortar), one for the point coupling."""
        model = self.model
        at_needle = model.needle_spacing if model.needle_spacing is not None else model.spacing
        return 1 if self.kind == POINTS else segment_subintervals(self.geometry.insertion_step, at_needle)

    def _start_track(self, pieces: int) -> None:
        """Gamma_N without points, and the Gauss points its segments will have."""
        self.points = np.zeros((0, 2))  # Gamma_N, reference, (k, 2)
        # per segment: a gap the needle crosses outside the tissue (a wound: no load, no
        # constraint, zero length along the track), and the share of a needle step it stands
        # for (1, less at a wound's walls where the tip left or re-entered mid-step)
        self.segment_gap = np.zeros(0, dtype=bool)
        self.segment_fraction = np.zeros(0)
        # the segments' Gauss points: the two-point rule on each of `segment_subintervals`
        # pieces of a segment (mortar; one piece for the point coupling), equal weights
        self.gauss = segment_gauss_points(pieces)  # (P,) along a segment, in [0, 1]
        self.gauss_weight = 1.0 / len(self.gauss)
        self.segment_points = np.zeros((0, 2))  # Gauss points of the segments, P per segment
        self.tip_row = np.zeros(self.model.n_free)  # N(X) T at the last needle point, dense

    def _start_rows(self) -> None:
        """N(X_s) T at the segments' Gauss points; the constraint quadrature's rows N_q T with
        their interleaved form (the needle points, the segments' Gauss points, or the arc ends'
        own Gauss points)."""
        n_free = self.model.n_free
        self._segment_rows = GrowingRows(n_free, interleaved=self.kind == MORTAR and not self.arc_ends)
        self._quadrature_rows = (self._segment_rows if self.kind == MORTAR and not self.arc_ends
                                 else GrowingRows(n_free, interleaved=True))

    def _start_multipliers(self) -> None:
        """No multipliers yet, and (multiplier_ends "arc") no constraint quadrature of its own."""
        # dense: W has a few entries per row and columns, m ~ Q / 2
        self.weights = np.zeros((0, 0))  # W (Q, m): g = W^T g_q, G = E^T B(W, n)
        self._spacing_of_segments = np.zeros(0)  # local particle spacing per segment (_segment_spacing)
        self.multiplier_count = 0
        self.multiplier_nodes = np.zeros(0)  # mortar: arc length of each multiplier's node (element start)
        # mortar constraint quadrature (multiplier_ends "arc"): Gauss points of each segment, fixed
        # when the segment is added (so the solvers' cached K^-1 E^T columns stay valid)
        self._constraint_points = np.zeros((0, 2))  # X_q, (Q, 2)
        self._constraint_segment = np.zeros(0, dtype=int)  # segment of each point, (Q,)
        self._constraint_along = np.zeros(0)  # t_q in [0, 1] along its segment, (Q,)
        self._constraint_length = np.zeros(0)  # ds_q: Gauss weight x segment length, mm, (Q,)

    def _start_loads(self) -> None:
        """No needle loads yet, the ramp's load factor at one."""
        self.loads = LoadQuadrature(np.zeros((0, 2)), (sp.csr_matrix((0, self.model.n_free)),), np.zeros(0))
        self.previous_loads = self.loads
        self.load_factor = 1.0  # beta of Algorithm 1's ramp within a step
        self._track_rows: tuple[sp.csr_matrix, sp.csc_matrix, np.ndarray] | None = None  # _track

    def _start_target_radius(self, pieces: int) -> None:
        """|x_q - C| the constraint asks of a quadrature point: the needle points lie on the
        circle; a Gauss point at t of a segment lies on the chord between two needle points one
        step apart, at sqrt(R^2 - t (1 - t) c^2) from C (c = 2 R sin(step / 2); t (1 - t) = 1/6
        at both Gauss points of one piece). Asking R there would push the whole track outward
        by the chord's sag, c^2 / 12R on average (0.017 mm for the 20 mm needle's 2 mm steps).
        One value for all with one piece per segment, else per point (P per segment)."""
        geometry = self.geometry
        self._chord = 2.0 * geometry.radius * math.sin(0.5 * geometry.step)
        self._gauss_targets = np.sqrt(geometry.radius**2 - self.gauss * (1.0 - self.gauss) * self._chord**2)
        # segment ends in pieces: the segments' points ask their own radii, appended per segment
        self._targets_per_point = self.kind == MORTAR and not self.arc_ends and pieces > 1
        self.target_radius = (geometry.radius if self.kind == POINTS
                              else np.zeros(0) if self.arc_ends or self._targets_per_point
                              else math.sqrt(geometry.radius**2 - self._chord**2 / 6.0))

    # --- state -----------------------------------------------------------------------------

    def state(self) -> dict:
        """What `add` (and the ramp's load_factor) changed, for `restore`. Every attribute is
        replaced, never changed in place, so a shallow copy keeps it; W is kept sparse (a
        state per needle step: dense, (Q, m) each, they grew with the cube of the steps)."""
        attributes = _own_rows(self.__dict__)
        attributes["weights"] = sp.csr_matrix(attributes["weights"])
        return attributes

    def restore(self, state: dict) -> None:
        """Back to a `state` of this coupling (kept unchanged for another restore)."""
        attributes = _own_rows(state)
        attributes["weights"] = attributes["weights"].toarray()
        self.__dict__.update(attributes)

    # --- the track ------------------------------------------------------------------------

    @property
    def segment_rows(self) -> sp.csr_matrix:
        """N(X_s) T at the segments' Gauss points, (P segments, n_free)."""
        return self._segment_rows.matrix

    @property
    def quadrature_rows(self) -> sp.csr_matrix:
        """N_q T at the constraint quadrature's points, (Q, n_free)."""
        return self._quadrature_rows.matrix

    @property
    def expanded_rows(self) -> sp.csr_matrix:
        """E: N_q T on interleaved dofs, (2Q, 2 n_free)."""
        return self._quadrature_rows.expanded

    def local_spacing(self, points: np.ndarray) -> np.ndarray:
        """Particle spacing at reference points: that of the nearest particle, (n,)."""
        return self._spacing[self.model.search.nearest(np.atleast_2d(points))]

    def add(self, reference_point: np.ndarray, multipliers: np.ndarray | None = None,
            gap: bool = False, fraction: float = 1.0) -> np.ndarray:
        """Append a needle point (and the segment it closes) to Gamma_N; returns the
        multipliers carried over to the new constraint set (forces conserved, new ones 0).
        `gap`: the segment crosses a wound outside the tissue (it carries nothing);
        `fraction`: the share of a needle step the segment stands for."""
        multipliers = np.zeros(self.multiplier_count) if multipliers is None else multipliers
        forces = self.weights @ multipliers if self.multiplier_count else np.zeros(self.weights.shape[0])  # (Q,)
        new = np.zeros((0, 2))  # the new segment's Gauss points
        if len(self.points):
            new = self.points[-1] + self.gauss[:, None] * (reference_point - self.points[-1])
            self.segment_points = np.vstack([self.segment_points, new])
            if self._targets_per_point:
                self.target_radius = np.append(self.target_radius, self._gauss_targets)
            self.segment_gap = np.append(self.segment_gap, gap)
            self.segment_fraction = np.append(self.segment_fraction, 0.0 if gap else fraction)
        self.points = np.vstack([self.points, reference_point])
        constraint_points = self._new_constraint_points() if self.arc_ends and len(self.points) > 1 else np.zeros((0, 2))
        magnitudes, part_points, lumping = self._load_layout()
        # the shape-function rows of every point the step adds, in one evaluation: the tip,
        # the new segment's Gauss points (no tissue in a gap: zero rows), the arc ends'
        # constraint points and the load points on a partly covered segment
        blocks = (reference_point[None], np.zeros((0, 2)) if gap else new, constraint_points, part_points)
        ends = np.cumsum([0] + [len(block) for block in blocks])
        rows = self.model.free_rows_at(np.vstack(blocks))
        self.tip_row = np.bincount(rows.indices[:rows.indptr[1]], rows.data[:rows.indptr[1]],
                                   minlength=self.model.n_free)  # N(X_tip) T, dense (n_free,)
        if len(new):
            self._segment_rows.append(empty_row_block(len(self.gauss)) if gap else row_block(rows, 1, ends[2]))
        if len(constraint_points):
            self._quadrature_rows.append(row_block(rows, ends[2], ends[3]))
        if self.kind == POINTS:
            self._quadrature_rows.append(row_block(rows, 0, 1))
            self.weights = np.eye(len(self.points))
            self.multiplier_count = len(self.points)
            carried = np.append(multipliers, 0.0)
        else:
            shares = self._partition()
            forces = np.concatenate([forces, np.zeros(shares.shape[0] - len(forces))])
            carried = shares.T @ forces
        self.previous_loads, self._track_rows = self.loads, None
        if len(part_points):
            part_rows = row_block_matrix(row_block(rows, ends[3], ends[4]), rows.shape[1])
            self.loads = LoadQuadrature(np.vstack([self.segment_points, part_points]),
                                        (self.segment_rows, part_rows), magnitudes, lumping)
        else:
            self.loads = LoadQuadrature(self.segment_points, (self.segment_rows,), magnitudes)
        return carried

    def _segment_spacing(self) -> np.ndarray:
        """Local particle spacing at each segment's midpoint, (k - 1,), kept as segments are added."""
        have = len(self._spacing_of_segments)
        if have < len(self.points) - 1:
            middles = 0.5 * (self.points[have:-1] + self.points[have + 1:])
            self._spacing_of_segments = np.concatenate([self._spacing_of_segments, self.local_spacing(middles)])
        return self._spacing_of_segments

    def _least_element(self, spacing: np.ndarray) -> np.ndarray:
        """A mortar element's least length where the local particle spacing is `spacing`:
        MULTIPLIER_SPACINGS of it, and at least `needle.multiplier_length`."""
        return np.maximum(MULTIPLIER_SPACINGS * spacing, self.multiplier_length)

    def _segment_lengths(self) -> np.ndarray:
        """Reference lengths of the segments along the track; a gap counts zero (the track's
        pieces on both sides of a wound join in the multiplier field's arc length)."""
        lengths = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return np.where(self.segment_gap, 0.0, lengths)

    def _new_constraint_points(self) -> np.ndarray:
        """Gauss points of the new segment for the constraint (returned, (count, 2); none
        across a gap), with their segment, position and length recorded: at least two, and at least
        QUADRATURE_PER_ELEMENT per multiplier element length over the segment (a 2 mm segment
        against 1.25 mm elements gets 4), so every element holds Gauss points and the hat
        functions' kinks inside a segment are integrated closely. Each asks |x - C| of a point
        at t on the chord between two needle points: sqrt(R^2 - t (1 - t) c^2)."""
        start, end = self.points[-2], self.points[-1]
        if self.segment_gap[-1]:
            return np.zeros((0, 2))
        length = float(np.linalg.norm(end - start))
        element = float(self._least_element(self.local_spacing(0.5 * (start + end)))[0])
        count = max(2, math.ceil(QUADRATURE_PER_ELEMENT * length / element - 1e-9))
        along, gauss_weights = gauss_legendre(count)  # on [0, 1]
        ds = gauss_weights * length
        new = start + along[:, None] * (end - start)  # (count, 2)
        self._constraint_points = np.vstack([self._constraint_points, new])
        self._constraint_segment = np.append(self._constraint_segment, np.full(count, len(self.points) - 2))
        self._constraint_along = np.append(self._constraint_along, along)
        self._constraint_length = np.append(self._constraint_length, ds)
        radius = self.geometry.radius
        self.target_radius = np.append(self.target_radius, np.sqrt(radius**2 - along * (1 - along) * self._chord**2))
        return new

    def _arc_nodes(self, lengths: np.ndarray, arc: np.ndarray) -> np.ndarray:
        """Element ends at exact arc lengths: the track measured in local spacings,
        tau(s) = int ds / (MULTIPLIER_SPACINGS h(s)) (h per segment, at its midpoint), cut at
        tau_tip - k for k = 0, 1, ..., the remainder (< 1) joining the element at the entry
        (one element while the track is shorter than one). Arc length of the ends, (m_e + 1,)."""
        spacing = self._least_element(self._segment_spacing())
        tau = np.concatenate([[0.0], np.cumsum(lengths / spacing)])  # at the needle points
        count = max(math.floor(tau[-1] + 1e-9), 1)
        cuts = tau[-1] - np.arange(count - 1, 0, -1, dtype=float)  # interior ends, increasing
        return np.concatenate([[0.0], np.interp(cuts, tau, arc), [arc[-1]]])

    def _partition(self) -> np.ndarray:
        """Mortar elements: whole segments from the entry, each closed once it is at least
        MULTIPLIER_SPACINGS local spacings long; a shorter remainder at the tip joins the
        last closed element (one element while the track is shorter). The multipliers are
        the nodal values of a continuous piecewise-linear field on the elements' ends
        (MULTIPLIER_ORDER 1) or one constant per element (0).

        `weights` W (Q, m): P ds_q normalised per multiplier, so that g_j = sum_q W_qj g_q is
        the phi_j-weighted mean violation, with P (Q, m) the share phi_j(s_q) of quadrature
        point q in multiplier j (a partition of unity), returned for `add` to carry the
        multipliers over; not kept (each step's state would hold one more (Q, m) array)."""
        lengths = self._segment_lengths()
        if not len(lengths):
            self.weights = np.zeros((0, 0))
            self.multiplier_count = 0
            return self.weights
        arc = np.concatenate([[0.0], np.cumsum(lengths)])  # arc length at the needle points
        if self.arc_ends:
            nodes = self._arc_nodes(lengths, arc)  # element ends, (m_e + 1,)
            segment = self._constraint_segment
            s_q = arc[segment] + self._constraint_along * lengths[segment]  # (Q,)
            ds = self._constraint_length
            element = np.clip(np.searchsorted(nodes, s_q, side="right") - 1, 0, len(nodes) - 2)
        else:
            needed = np.where(self.segment_gap, 0.0, self._least_element(self._segment_spacing()))
            starts = _element_starts(lengths, needed, from_tip=PARTITION_FROM_TIP)
            marks = np.zeros(len(lengths), dtype=int)
            marks[starts[1:]] = 1
            nodes = np.append(arc[starts], arc[-1])  # element ends, (m_e + 1,)
            s_q = (arc[:-1, None] + self.gauss[None, :] * lengths[:, None]).ravel()  # (Q,)
            ds = np.repeat(self.gauss_weight * lengths, len(self.gauss))
            element = np.repeat(np.cumsum(marks), len(self.gauss))  # (Q,)
        elements = len(nodes) - 1
        q = np.arange(len(s_q))
        if MULTIPLIER_ORDER == 0:
            shares = np.zeros((len(q), elements))
            shares[q, element] = 1.0
        else:
            upper = (s_q - nodes[element]) / (nodes[element + 1] - nodes[element])
            shares = np.zeros((len(q), elements + 1))
            shares[q, element] = 1.0 - upper
            shares[q, element + 1] += upper
        self.multiplier_nodes = nodes if MULTIPLIER_ORDER == 1 else nodes[:-1]  # arc length, mm
        weighted = shares * ds[:, None]
        self.weights = weighted / weighted.sum(axis=0)
        self.multiplier_count = shares.shape[1]
        return shares

    # --- loads ------------------------------------------------------------------------------

    def _load_layout(self) -> tuple[np.ndarray, np.ndarray, tuple | None]:
        """The friction and the cutting force on the track as it stands (TrackLoads.layout)."""
        return self.track_loads.layout(self.points, self.segment_fraction, self.gauss)

    def applied_forces(self) -> tuple[float, float]:
        """(friction, cutting force), N, that the track's loads apply once the step's ramp is
        through: friction on the needle inside the tissue (a wound's gaps carry none), and the
        cutting force as laid out (with `cutting_ramp`, only the share of the cutting edge
        inside), not the needle block's nominal values."""
        friction = self.needle.friction * self.geometry.insertion_step * float(self.segment_fraction.sum())
        return friction, float(self.loads.magnitudes.sum()) - friction

    # --- the coupling's terms of the residual --------------------------------------------------

    def _track(self) -> tuple[sp.csr_matrix, sp.csc_matrix, np.ndarray]:
        """S = [N_q T; N_l T; N_l' T], the rows of the constraint quadrature's points, of this
        step's load points and of the previous step's, (Q + L + L', n_free), with S^T and the
        points' reference positions; built once per needle point. The residual's coupling
        terms then take one product with S and one with S^T: on these few rows scipy's
        per-product overhead, not the arithmetic, is the cost."""
        if self._track_rows is None:
            rows = joined_rows(self.quadrature_rows, *self.loads.row_parts, *self.previous_loads.row_parts)
            points = np.vstack([self.quadrature_points(), self.loads.points, self.previous_loads.points])
            self._track_rows = (rows, rows.T, points)  # S^T as a CSC view: no conversion
        return self._track_rows

    def _load_weights(self) -> np.ndarray:
        """The load magnitudes (N) of Algorithm 1's ramp on S's load rows: beta x this step's
        and (1 - beta) x the previous step's, (L + L',)."""
        beta = self.load_factor
        return np.concatenate([beta * self.loads.magnitudes, (1.0 - beta) * self.previous_loads.magnitudes])

    def residual_terms(self, free: np.ndarray, multipliers: np.ndarray,
                       center: np.ndarray) -> tuple[ConstraintValues, np.ndarray, np.ndarray]:
        """The coupling's terms of eq. 3.62 at (free, multipliers, centre): the constraint
        values g (eq. 3.59-3.61); f_needle (2 n_free,), the line loads along the direction of
        needle motion a_0 at the spatial load points (eq. 3.64), ramped between the previous
        and this step's; and G lambda = sum_q N_q^T (mu_q n_q) (2 n_free,)."""
        rows, rows_t, points = self._track()
        q = self.weights.shape[0]
        spatial = points + rows @ free  # (Q + L + L', 2)
        relative = spatial[:q] - center
        rho = np.sqrt((relative * relative).sum(axis=1))  # np.linalg.norm's sum, without its checks
        normal = relative / rho[:, None]
        # S^T's right-hand sides: mu_q n_q on the quadrature rows (columns 0-1), the load
        # forces on the load rows (columns 2-3)
        terms = np.zeros((len(points), 4))
        terms[:q, :2] = self._carried(multipliers)[:, None] * normal
        magnitudes = self._load_weights()
        if len(magnitudes):
            angles = np.arctan2(spatial[q:, 1] - center[1], spatial[q:, 0] - center[0])
            terms[q:, 2:] = magnitudes[:, None] * self.geometry.tangent(angles)  # a_0
        forces = rows_t @ terms  # (n_free, 4)
        values = ConstraintValues(self.weights.T @ (rho - self.target_radius), normal, rho)
        return values, forces[:, 2:].ravel(), forces[:, :2].ravel()

    def _needle_force_turn(self, free: np.ndarray, center: np.ndarray) -> np.ndarray:
        """d a_l / dC (L + L', i, j), the change of each load point's force with the centre:
        a_0 turns with the polar angle seen from C, d a_0 / dC = sense unit(theta) t^T / rho
        with t = (-sin theta, cos theta)."""
        rows, _, points = self._track()
        q = self.weights.shape[0]
        relative = (points + rows @ free)[q:] - center  # (L + L', 2)
        rho = np.sqrt((relative * relative).sum(axis=1))
        radial = relative / rho[:, None]
        across = np.column_stack([-radial[:, 1], radial[:, 0]])
        scale = self._load_weights() * self.geometry.sense / rho
        return (scale[:, None, None] * radial[:, :, None]) * across[:, None, :]

    def needle_force_center_derivative(self, free: np.ndarray, center: np.ndarray) -> np.ndarray:
        """d f_needle / dC (2 n_free, 2) (_needle_force_turn on the load points' rows)."""
        _, rows_t, points = self._track()
        q = self.weights.shape[0]
        if len(points) == q:
            return np.zeros((2 * self.model.n_free, 2))
        terms = np.zeros((len(points), 2, 2))
        terms[q:] = self._needle_force_turn(free, center)
        columns = rows_t @ terms.reshape(len(points), 4)  # (n_free, (i, j))
        return columns.reshape(-1, 2)  # rows (p, i), columns j

    def center_derivative_on_rows(self, free: np.ndarray, multipliers: np.ndarray, normal: np.ndarray,
                                  rho: np.ndarray, center: np.ndarray) -> np.ndarray | None:
        """d r_u / dC = d (G lambda) / dC - d f_needle / dC as E^T C: the coefficients C (2Q, 2)
        on the interleaved constraint rows E, where the constraint quadrature is the segments'
        Gauss points (the mortar coupling's default); else None. The saddle solver keeps
        K^-1 E^T, so these right-hand sides need no solve with its factor.

        Exact but for the cutting force's points on a partly covered segment: their force
        change is lumped onto two of the segment's Gauss points (LoadQuadrature.lumping), whose
        rows interpolate theirs linearly along the segment. The columns only make the Jacobian
        of the planner's centre move (needle/steering.py; tests/test_needle_coupling.py bounds
        the change by 1e-3 of its norm), so the centre still settles where Algorithm 2's update holds."""
        loads, previous = self.loads, self.previous_loads
        if not (self._segment_rows is self._quadrature_rows and loads.lumping is not None
                and previous.lumping is not None):
            return None
        q = self.weights.shape[0]
        coefficients = np.zeros((q, 2, 2))  # (point, i, j)
        if q and self.multiplier_count:
            coefficients -= self._projections(multipliers, normal, rho)
        turn = self._needle_force_turn(free, center)  # this step's load points, then the previous step's
        for part, (indices, weights) in ((turn[:len(loads.magnitudes)], loads.lumping),
                                         (turn[len(loads.magnitudes):], previous.lumping)):
            on_segments = len(part) - len(indices)
            coefficients[:on_segments] -= part[:on_segments]
            np.subtract.at(coefficients, indices.ravel(),
                           (weights[:, :, None, None] * part[on_segments:, None]).reshape(-1, 2, 2))
        return coefficients.reshape(2 * q, 2)

    # --- constraints ------------------------------------------------------------------------

    def quadrature_points(self) -> np.ndarray:
        """X_q, the reference points of the constraint quadrature, (Q, 2)."""
        if self.kind == POINTS:
            return self.points
        return self._constraint_points if self.arc_ends else self.segment_points

    def normal_weights(self, normal: np.ndarray) -> np.ndarray:
        """B (2Q, m) dense, B[2q + d, j] = W_qj n_q,d (the saddle-point solver's G = E^T B)."""
        weights = self.weights
        return (weights[:, None, :] * normal[:, :, None]).reshape(2 * weights.shape[0], weights.shape[1])

    @property
    def expanded_rows_t(self) -> sp.csr_matrix:
        """E^T (2 n_free, 2Q), kept until the constraint quadrature grows."""
        return self._quadrature_rows.expanded_t

    def weights_matrix(self, normal: np.ndarray) -> sp.csr_matrix:
        """B (2Q, m) of normal_weights as a sparse matrix (MINRES's G = E^T B)."""
        return sp.csr_matrix(self.normal_weights(normal))

    def _carried(self, multipliers: np.ndarray) -> np.ndarray:
        """mu_q = sum_j W_qj lambda_j, the force weight of each quadrature point, (Q,)."""
        if not self.multiplier_count:
            return np.zeros(self.weights.shape[0])
        return self.weights @ multipliers

    def constraint_matrix(self, normal: np.ndarray) -> sp.csr_matrix:
        """G of eq. 3.65 for the residual form: column j = sum_q W_qj N_q^T n_q."""
        return (self.expanded_rows_t @ self.weights_matrix(normal)).tocsr()

    def constraint_center_derivative(self, normal: np.ndarray) -> np.ndarray:
        """d g_j / dC = -sum_q W_qj n_q^T, (m, 2)."""
        return -(self.weights.T @ normal).reshape(self.multiplier_count, 2)

    def _projections(self, multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """mu_q (I - n_q n_q^T) / rho_q, (Q, 2, 2)."""
        weight = self._carried(multipliers) / rho
        return weight[:, None, None] * (np.eye(2) - normal[:, :, None] * normal[:, None, :])

    def curvature(self, multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> sp.csr_matrix:
        """H = sum_e lambda_e d^2 g_e = E^T blockdiag(w_q lambda_e(q) (I - n_q n_q^T) / rho_q) E."""
        q = self.weights.shape[0]
        if q == 0 or self.multiplier_count == 0:
            return sp.csr_matrix((2 * self.model.n_free, 2 * self.model.n_free))
        blocks = self._projections(multipliers, normal, rho)
        block_matrix = sp.bsr_matrix((blocks, np.arange(q), np.arange(q + 1)), shape=(2 * q, 2 * q)).tocsr()
        return (self.expanded_rows_t @ block_matrix @ self.expanded_rows).tocsr()

    def center_derivative(self, multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """d (G lambda) / dC = -sum_q w_q lambda_e(q) N_q^T (I - n_q n_q^T) / rho_q, (2 n_free, 2)."""
        if not self.weights.shape[0] or self.multiplier_count == 0:
            return np.zeros((2 * self.model.n_free, 2))
        blocks = -self._projections(multipliers, normal, rho)  # (Q, i, j)
        _, rows_t, points = self._track()
        terms = np.zeros((len(points), 4))  # (i, j) in columns 2 i + j, on the quadrature rows
        terms[:len(blocks)] = blocks.reshape(-1, 4)
        return (rows_t @ terms).reshape(-1, 2)
