"""Tip tracking: the material point the needle tip reaches in one rotation step
(thesis eq. 3.66-3.70), by the inverse deformation gradient or by Levenberg-Marquardt.

The two kernels work on any displacement field; `track_step` and `locate_exit` apply them
to an insertion: the tip point of a needle step (with the 'auto' fallback from the inverse
gradient to Levenberg-Marquardt), and the boundary point where the tip leaves the tissue.
`locate_reentry` finds where the tip crossing a wound's gap enters the deformed tissue again,
by carrying the boundary with the displacement (no material point maps to a tip in the gap).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InsertionFailure, TipTrackingJump
from ..events import Event, EventKind
from ..geometry.boundary import boundary_edges
from .geometry import IDENTITY, length

if TYPE_CHECKING:
    import scipy.sparse as sp

    from .equilibrium import NeedleInsertion

log = logging.getLogger(__name__)

INVERSE_GRADIENT, LEVENBERG_MARQUARDT = "inverse-gradient", "levenberg-marquardt"


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
    """Minimise C(X) = (|X + u(X) - O| - R)^2 + (|X - X_prev| - IS)^2 (eq. 3.68-3.69) from the
    start point of eq. 3.70. Returns (X, evaluations of u).

    C's minimum is a zero of both terms wherever the needle circle meets the circle of radius IS
    about X_prev, so Newton's method on the two terms finds it first (quadratic convergence,
    3-5 evaluations where Levenberg-Marquardt takes ~9); Levenberg-Marquardt minimises C when
    Newton does not converge within NEWTON_TIP_ITERATIONS (no zero near the start)."""
    point, evaluations = _newton_tip(previous_tip, center, radius, insertion_step, start,
                                     displacement_and_gradient)
    if point is not None:
        return point, evaluations
    last: dict = {}

    def evaluate(x):
        # least_squares asks for the residuals and then the Jacobian at the same point
        if last.get("x") is None or not np.array_equal(last["x"], x):
            last["x"], last["value"] = np.array(x), displacement_and_gradient(x)
        return last["value"]

    def residuals(x):
        return _tip_conditions(x, *evaluate(x), previous_tip, center, radius, insertion_step)[0]

    def jacobian(x):
        return _tip_conditions(x, *evaluate(x), previous_tip, center, radius, insertion_step)[1]

    from scipy.optimize import least_squares  # here: Newton mostly succeeds, and scipy.optimize costs start-up

    result = least_squares(residuals, start, jac=jacobian, method="lm", xtol=1e-13, ftol=1e-13, gtol=1e-13,
                           max_nfev=200)
    return result.x, evaluations + int(result.nfev)


NEWTON_TIP_ITERATIONS = 12
NEWTON_TIP_STOP = 1e-6  # a step below this times R ends Newton's method on the tip conditions


def _tip_conditions(x, u, grad_u, previous_tip, center, radius, insertion_step):
    """The two terms of C (eq. 3.68) and their Jacobian (2, 2)."""
    spatial = x + u - center
    distance = math.hypot(spatial[0], spatial[1])
    chord = x - previous_tip
    chord_length = max(math.hypot(chord[0], chord[1]), 1e-300)
    values = np.array([distance - radius, chord_length - insertion_step])
    jacobian = np.array([(spatial / max(distance, 1e-300)) @ (IDENTITY + grad_u), chord / chord_length])
    return values, jacobian


def _newton_tip(previous_tip, center, radius, insertion_step, start, displacement_and_gradient):
    """Newton's method on C's two terms from `start`: (X, evaluations), X None when it does
    not converge within NEWTON_TIP_ITERATIONS. It stops after a step below NEWTON_TIP_STOP R:
    converging quadratically, the error left is then ~1e-12 R (2e-11 mm at R = 20 mm), far
    below what the equilibrium's residual tolerance leaves in the points (~1e-7 mm), one
    evaluation of u sooner than at 1e-8 R on most tip points of the 20 mm needle scenes."""
    x = np.array(start, dtype=float)
    for evaluations in range(1, NEWTON_TIP_ITERATIONS + 1):
        values, jacobian = _tip_conditions(x, *displacement_and_gradient(x), previous_tip, center, radius,
                                           insertion_step)
        try:
            step = np.linalg.solve(jacobian, values)
        except np.linalg.LinAlgError:
            return None, evaluations
        size = length(step)
        if not math.isfinite(size) or size > insertion_step:
            return None, evaluations  # leaving the step's neighbourhood: no zero near the start
        x = x - step
        if size <= NEWTON_TIP_STOP * max(radius, 1.0):  # quadratic: the error left is ~|step|^2 / R
            return x, evaluations
    return None, NEWTON_TIP_ITERATIONS


# --- tracking the tip of an insertion ---------------------------------------------------------


def track_tip(insertion: NeedleInsertion, rotation_step: float, method: str) -> np.ndarray:
    """Reference position X_{n+1} of the next tip point, `rotation_step` along the needle from
    the current tip X_n (thesis figure 3.1 and eq. 3.66-3.70), by `method` (inverse-gradient
    or levenberg-marquardt). Raises TipTrackingJump when the inverse gradient jumps."""
    geometry, center = insertion.geometry, insertion.center
    previous = insertion.points[-1]
    expected_length = 2.0 * geometry.radius * math.sin(0.5 * rotation_step)  # chord
    rest_angle = math.atan2(*(previous - geometry.center)[::-1])
    expected_direction = geometry.tangent(rest_angle + 0.5 * geometry.sense * rotation_step)
    if method == INVERSE_GRADIENT:
        u, grad = insertion.displacement(previous, gradient=True)
        spatial_previous = previous + u[0]
        relative = spatial_previous - center
        angle = math.atan2(relative[1], relative[0]) + geometry.sense * rotation_step
        target = center + geometry.radius * np.array([math.cos(angle), math.sin(angle)])
        return inverse_gradient_step(previous, spatial_previous, np.eye(2) + grad[0], target, expected_length,
                                     expected_direction, lambda x: insertion.displacement(x)[0])
    start = previous + expected_length * expected_direction  # eq. 3.70

    def field(x):
        u, grad = insertion.displacement(x, gradient=True)
        return u[0], grad[0]

    return levenberg_marquardt_tip(previous, center, geometry.radius, expected_length, start, field)[0]


def track_step(insertion: NeedleInsertion, step: int, rotation: float,
               rotation_step: float | None = None) -> tuple[np.ndarray, str]:
    """The tip point of needle step `step` (rotation `rotation` since entry) by the
    insertion's tip tracking, and the method that found it: 'auto' falls back from a jumping
    inverse gradient to Levenberg-Marquardt and records the event; 'inverse-gradient' alone
    raises InsertionFailure naming the step and angle."""
    t0 = time.perf_counter()
    rotation_step = insertion.geometry.step if rotation_step is None else rotation_step
    try:
        if insertion.tip_tracking == LEVENBERG_MARQUARDT:
            return track_tip(insertion, rotation_step, LEVENBERG_MARQUARDT), LEVENBERG_MARQUARDT
        try:
            return track_tip(insertion, rotation_step, INVERSE_GRADIENT), INVERSE_GRADIENT
        except TipTrackingJump as jump:
            jumped = f"inverse-gradient tip tracking jumped at step {step} (needle rotation {rotation:.3f} rad): {jump}"
            if insertion.tip_tracking == INVERSE_GRADIENT:
                raise InsertionFailure(jumped) from None
            message = f"{jumped}; fell back to Levenberg-Marquardt"
            insertion.events.append(Event(EventKind.TIP_TRACKING_FALLBACK, message, step, rotation))
            log.info(message)  # the user sees it once, as a `note:` from the event
            return track_tip(insertion, rotation_step, LEVENBERG_MARQUARDT), LEVENBERG_MARQUARDT
    finally:
        insertion.timings["tip_tracking"] += time.perf_counter() - t0


def locate_exit(insertion: NeedleInsertion, rotation: float, method: str,
                span: float | None = None) -> tuple[np.ndarray, float]:
    """Where the tip leaves the tissue during the step after `rotation` (or the `span` rad
    after it: the rest of a step the tip re-entered a wound's wall in): the boundary point
    and the needle rotation there. `method` is the tracking that found the step's tip outside;
    if the inverse gradient jumps on the way, Levenberg-Marquardt locates the exit."""
    t0 = time.perf_counter()
    try:
        try:
            return _boundary_crossing(insertion, rotation, method, span)
        except TipTrackingJump as jump:
            log.info("locating the exit: %s; Levenberg-Marquardt used instead", jump)
            return _boundary_crossing(insertion, rotation, LEVENBERG_MARQUARDT, span)
    finally:
        insertion.timings["tip_tracking"] += time.perf_counter() - t0


def brent_root(f, a: float, b: float, xtol: float = 1e-13, rtol: float = 1e-15, max_evaluations: int = 100) -> float:
    """A zero of the continuous f on [a, b], where f(a) and f(b) differ in sign, to within
    xtol + rtol |x|: Brent's method (inverse quadratic interpolation or the secant where they
    step well inside the bracket, bisection where they do not), as scipy.optimize.brentq,
    whose import would cost every run ~0.08 s of start-up. The zero returned is one of the
    points f was evaluated at, so a caller that records f's evaluations has it recorded."""
    fa, fb = f(a), f(b)
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    if (fa > 0.0) == (fb > 0.0):
        raise ValueError(f"f({a}) = {fa} and f({b}) = {fb} do not bracket a zero")
    c, fc = a, fa  # c: the bracket's other end, f(c) of the sign opposite to f(b)
    step = previous = b - a
    for _ in range(max_evaluations):
        if (fb > 0.0) == (fc > 0.0):
            c, fc = a, fa
            step = previous = b - a
        if abs(fc) < abs(fb):  # b: the best estimate
            a, b, c = b, c, b
            fa, fb, fc = fb, fc, fb
        tolerance = 0.5 * (xtol + rtol * abs(b))
        half = 0.5 * (c - b)
        if abs(half) <= tolerance or fb == 0.0:
            return b
        if abs(previous) >= tolerance and abs(fa) > abs(fb):
            s = fb / fa
            if a == c:  # secant
                p, q = 2.0 * half * s, 1.0 - s
            else:  # inverse quadratic interpolation through a, b, c
                q, r = fa / fc, fb / fc
                p = s * (2.0 * half * q * (q - r) - (b - a) * (r - 1.0))
                q = (q - 1.0) * (r - 1.0) * (s - 1.0)
            if p > 0.0:
                q = -q
            p = abs(p)
            if 2.0 * p < min(3.0 * half * q - abs(tolerance * q), abs(previous * q)):
                previous, step = step, p / q
            else:
                step = previous = half
        else:
            step = previous = half
        a, fa = b, fb
        b += step if abs(step) > tolerance else math.copysign(tolerance, half)
        fb = f(b)
    raise InsertionFailure(f"Brent's method found no zero within {max_evaluations} evaluations "
                           f"(bracket [{min(b, c):.17g}, {max(b, c):.17g}])")


def _boundary_crossing(insertion: NeedleInsertion, rotation: float, method: str,
                       span: float | None = None) -> tuple[np.ndarray, float]:
    """Root-find, over the fraction of the step, where the tip's material point meets the
    boundary: the signed distance to the boundary is continuous in the fraction, so Brent's
    method needs ~10 tip trackings where bisection needs ~45."""
    step = insertion.geometry.step if span is None else span
    tracked = {0.0: insertion.points[-1]}  # fraction -> tip point, each tracked once

    def signed_distance(fraction: float) -> float:
        if fraction not in tracked:
            tracked[fraction] = track_tip(insertion, fraction * step, method)
        return insertion.domain.outside_distance(tracked[fraction])

    if signed_distance(1.0) <= 0.0:  # the full step stays inside for this tracking method
        fraction = 1.0
    elif signed_distance(0.0) >= 0.0:
        fraction = 0.0
    else:
        fraction = brent_root(signed_distance, 0.0, 1.0)
    return insertion.domain.clip(tracked[fraction]), rotation + fraction * step


# --- across a wound ---------------------------------------------------------------------------
#
# The tip crossing a wound's gap is outside the tissue: no material point maps to it. Where it
# enters the tissue again is found forward, by carrying the boundary with u, never by inverting
# x = X + u(X) in the gap. (A fixed-point iteration X <- x - u(X), u continued from the nearest
# tissue point, did that: near a round hole's middle the nearest wall point sweeps the wall as X
# moves by tenths of a mm, the iteration hops between walls, and it failed on holes the needle
# crosses near their middle, missing the tip by 0.16 mm on a 2 mm hole at the default spacing.)

WALL_SAMPLES = 4  # boundary chords per local particle spacing
MATERIAL_POINT_TOLERANCE = 0.1  # local particle spacings: what the field resolves
MATERIAL_POINT_ITERATIONS = 30
MATERIAL_POINT_STOP = 1e-13  # a Newton step below this times R ends the search for a material point
WALL_REFINEMENT = 32  # pieces a chord is cut into when Brent's method stopped at a jump of u
ROTATION_ROUNDOFF = 1e-12  # rad


@dataclass(frozen=True)
class BoundarySamples:
    """The tissue's boundary sampled at rest: each directed boundary edge (tissue on its left)
    cut into WALL_SAMPLES chords per local particle spacing (a 2 mm hole's 96-gon edge, 0.13 mm,
    is one chord at any spacing the model resolves), and the shape functions there. Chord k
    joins samples k and k + 1 of one edge; an edge's last sample is the next edge's first, so
    the chords close every boundary loop. Made once per model (boundary_samples)."""

    reference: np.ndarray  # (n, 2) samples at rest
    chords: np.ndarray  # (m,) the first sample of each chord
    rows: sp.csr_matrix  # (n, n_free) N(X) T at the samples: u = rows @ free

    @classmethod
    def of(cls, insertion: NeedleInsertion) -> BoundarySamples:
        starts, ends = boundary_edges(insertion.domain)
        lengths = np.linalg.norm(ends - starts, axis=1)
        # first at the spacing at the edges' ends and middles, then at the finest spacing those
        # samples meet (a long outline edge is graded toward the needle in between)
        pieces = _chords_per_edge(insertion, np.vstack([starts, 0.5 * (starts + ends), ends]),
                                  np.tile(np.arange(len(starts)), 3), lengths)
        samples, edge, _ = _edge_samples(starts, ends, pieces)
        samples, _, last = _edge_samples(starts, ends, _chords_per_edge(insertion, samples, edge, lengths))
        samples = insertion.domain.clip(samples)  # as NeedleInsertion.displacement evaluates u
        return cls(samples, np.flatnonzero(~last), insertion.model.free_rows_at(samples))


def _chords_per_edge(insertion: NeedleInsertion, points: np.ndarray, edge: np.ndarray,
                     lengths: np.ndarray) -> np.ndarray:
    """Chords of each edge (k,): WALL_SAMPLES per the least local spacing at its `points`
    (`edge`: the edge of each point)."""
    spacing = np.full(len(lengths), np.inf)
    np.minimum.at(spacing, edge, insertion.coupling.local_spacing(points))
    return np.maximum(np.ceil(WALL_SAMPLES * lengths / spacing), 1).astype(int)


def _edge_samples(starts: np.ndarray, ends: np.ndarray, pieces: np.ndarray):
    """The ends of `pieces` equal chords of every edge starts-ends (k, 2), both edge ends
    included: the samples (n, 2), the edge of each (n,) and whether it ends its edge (n,)."""
    edge = np.repeat(np.arange(len(starts)), pieces + 1)
    first = np.cumsum(pieces + 1) - (pieces + 1)  # (k,) each edge's first sample
    along = (np.arange(len(edge)) - first[edge]) / pieces[edge]  # (n,) fraction along its edge
    samples = starts[edge] + along[:, None] * (ends - starts)[edge]
    last = np.zeros(len(edge), dtype=bool)
    last[first + pieces] = True
    return samples, edge, last


def boundary_samples(insertion: NeedleInsertion) -> BoundarySamples:
    """The BoundarySamples of the insertion's model, made on its first re-entry and kept with
    the model's PreparedTissue (a plan's passes and replays share it)."""
    tissue = insertion.tissue
    if tissue.boundary_samples is None:
        tissue.boundary_samples = BoundarySamples.of(insertion)
    return tissue.boundary_samples


class DeformedBoundary:
    """The boundary samples carried by the displacement: the chords' spatial ends X + u(X)
    (`spatial`, (n, 2)), closed polygons that bound the deformed tissue to within the chords'
    sag (what the tip in a wound's gap is tested against and crosses)."""

    def __init__(self, insertion: NeedleInsertion):
        samples = boundary_samples(insertion)
        self.reference, self.chords = samples.reference, samples.chords
        self.spatial = samples.reference + samples.rows @ insertion.free  # (n, 2)

    def contains(self, point: np.ndarray) -> bool:
        """Whether the spatial point lies inside the deformed tissue: the even-odd rule, an odd
        count of chords crossing the ray to its right."""
        a, b = self.spatial[self.chords], self.spatial[self.chords + 1]  # (m, 2) each
        x, y = float(point[0]), float(point[1])
        straddle = (a[:, 1] > y) != (b[:, 1] > y)
        a, b = a[straddle], b[straddle]
        crossing_x = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        return bool(np.count_nonzero(x < crossing_x) % 2)

    def circle_crossings(self, center: np.ndarray, radius: float, rotation_of) -> tuple[np.ndarray, np.ndarray]:
        """The chords that cross the circle of `radius` about `center` (c,), in the order of
        the needle rotations where they cross it (`rotation_of` a spatial point's), (c,). A
        chord from inside the circle to outside crosses it once."""
        outside = np.linalg.norm(self.spatial - center, axis=1) > radius  # (n,)
        chords = self.chords[outside[self.chords] != outside[self.chords + 1]]
        a, b = self.spatial[chords], self.spatial[chords + 1]  # (c, 2) each
        # |a + s (b - a) - center| = radius, 0 <= s <= 1: the far root from inside, else the near one
        e, f = b - a, a - center
        qa, qb, qc = np.sum(e * e, axis=1), np.sum(f * e, axis=1), np.sum(f * f, axis=1) - radius**2
        root = np.sqrt(np.maximum(qb * qb - qa * qc, 0.0))
        s = np.where(qc <= 0.0, -qb + root, -qb - root) / qa
        rotations = rotation_of(a + s[:, None] * e)
        order = np.argsort(rotations)
        return chords[order], rotations[order]


def material_point(insertion: NeedleInsertion, spatial: np.ndarray,
                   iterations: int = MATERIAL_POINT_ITERATIONS) -> np.ndarray:
    """The reference point X with X + u(X) = `spatial`, a point inside the deformed tissue:
    Newton's method with F = I + grad u from X = x - u(x). Where u jumps (across a hole's
    corner, where the visibility criterion cuts the particles' supports) no point maps
    exactly: the last iterate is kept while X + u(X) misses `spatial` by at most
    MATERIAL_POINT_TOLERANCE local particle spacings (what the field resolves), and a
    TipTrackingJump says so beyond."""
    point = spatial - insertion.displacement(spatial)[0]
    stop = MATERIAL_POINT_STOP * max(insertion.geometry.radius, 1.0)
    for _ in range(iterations):
        u, grad = insertion.displacement(point, gradient=True)
        try:
            step = np.linalg.solve(IDENTITY + grad[0], point + u[0] - spatial)
        except np.linalg.LinAlgError:
            break
        point = point - step
        if length(step) <= stop:
            break
    miss = float(np.linalg.norm(point + insertion.displacement(point)[0] - spatial))
    if miss > MATERIAL_POINT_TOLERANCE * float(insertion.coupling.local_spacing(point)[0]):
        raise TipTrackingJump(
            f"no material point maps to the tip at ({spatial[0]:.4g}, {spatial[1]:.4g}) mm: Newton's method on "
            f"X + u(X) = x misses it by {miss:.3g} mm after {iterations} iterations (the displacement jumps near "
            "the tissue's edge there): refine the spacing")
    return point


def _wall_point(insertion: NeedleInsertion, start: np.ndarray, end: np.ndarray, rotation_of,
                earliest: float) -> tuple[np.ndarray, float]:
    """The point X of the boundary chord start-end (at rest) whose position X + u(X) lies on
    the needle's circle, and the needle rotation there: Brent's method along the chord on
    |X + u(X) - O| - R, which differs in sign at its ends. Where u jumps along the wall (the
    visibility criterion at a hole's vertices) the zero found may be the jump: the chord
    is then cut into WALL_REFINEMENT pieces, and of the zeros that X + u(X) meets within
    MATERIAL_POINT_TOLERANCE local particle spacings the first in needle order from `earliest`
    is taken; a TipTrackingJump when there is none (the deformed wall jumps across the circle)."""
    center, radius = insertion.center, insertion.geometry.radius

    def points(fractions):
        return start + np.multiply.outer(fractions, end - start)  # (..., 2)

    def off_circle(fraction):
        x = points(fraction)
        return np.linalg.norm(x + insertion.displacement(x).reshape(x.shape) - center, axis=-1) - radius

    def bracketed(a: float, b: float) -> float:
        fa, fb = float(off_circle(a)), float(off_circle(b))
        if (fa > 0.0) == (fb > 0.0):  # the samples' u and this one differ by round-off at a zero
            return a if abs(fa) <= abs(fb) else b
        return brent_root(lambda fraction: float(off_circle(fraction)), a, b)

    fraction = bracketed(0.0, 1.0)
    miss = abs(float(off_circle(fraction)))
    tolerance = MATERIAL_POINT_TOLERANCE * float(insertion.coupling.local_spacing(points(fraction))[0])
    if miss > tolerance:
        cuts = np.linspace(0.0, 1.0, WALL_REFINEMENT + 1)
        values = off_circle(cuts)
        zeros = [bracketed(cuts[k], cuts[k + 1]) for k in np.flatnonzero((values[:-1] > 0.0) != (values[1:] > 0.0))]
        zeros = [zero for zero in zeros if abs(float(off_circle(zero))) <= tolerance]
        spatial = {zero: points(zero) + insertion.displacement(points(zero))[0] for zero in zeros}
        zeros = [zero for zero in zeros if rotation_of(spatial[zero]) >= earliest]
        if not zeros:
            point = points(fraction)
            raise TipTrackingJump(
                f"the deformed wall jumps across the needle by {miss:.3g} mm at the wall point ({point[0]:.4g}, "
                f"{point[1]:.4g}) mm where the tip enters it (the displacement jumps along the tissue's edge there, "
                f"by more than {MATERIAL_POINT_TOLERANCE:g} local particle spacings): refine the spacing")
        fraction = min(zeros, key=lambda zero: rotation_of(spatial[zero]))
    point = points(fraction)
    return point, float(rotation_of(point + insertion.displacement(point)[0]))


def _rotation_about(insertion: NeedleInsertion, start: float):
    """The needle rotation, within half a turn of `start`, at which the tip about the current
    centre passes the polar angle of spatial points (..., 2), as a function of them."""
    geometry, center = insertion.geometry, insertion.center

    def rotation_of(spatial: np.ndarray) -> np.ndarray:
        angle = np.arctan2(spatial[..., 1] - center[1], spatial[..., 0] - center[0])
        turned = geometry.sense * (angle - geometry.start_angle) - start
        return start + np.mod(turned + math.pi, 2.0 * math.pi) - math.pi
    return rotation_of


# a circle crossing the deformed boundary within this share of a needle step after the tip's
# exit is that exit (the sampled boundary's chords sag a little off the located exit)
ENTRY_AHEAD_MARGIN = 0.25


def entry_ahead(insertion: NeedleInsertion, start: float, end: float) -> tuple[np.ndarray, float] | None:
    """Where the rigid needle's circle about the current centre, past the tip's exit at
    rotation `start`, enters the deformed tissue again before rotation `end` (the needle's
    arc): the spatial point and the rotation, or None when the rest of the arc stays outside.
    A tip leaving for good has air ahead; tissue ahead means the deformation carried the
    boundary across the needle's path."""
    geometry, center = insertion.geometry, insertion.center
    if end <= start:
        return None
    t0 = time.perf_counter()
    try:
        boundary = DeformedBoundary(insertion)
        _, rotations = boundary.circle_crossings(center, geometry.radius, _rotation_about(insertion, start))
        ahead = rotations[(rotations > start + ENTRY_AHEAD_MARGIN * geometry.step) & (rotations < end)]
        for rotation, after in zip(ahead, [*ahead[1:], end]):
            if boundary.contains(geometry.tip(0.5 * (rotation + after), center)):
                return geometry.tip(float(rotation), center), float(rotation)
        return None
    finally:
        insertion.timings["tip_tracking"] += time.perf_counter() - t0


def locate_reentry(insertion: NeedleInsertion, start: float, end: float) -> tuple[np.ndarray, float] | None:
    """Where the rigid needle's tip, crossing a wound from rotation `start` to `end` about the
    current centre, enters the deformed tissue again: the reference boundary point and the
    rotation there, or None while the tip at `end` is still outside the deformed tissue.

    The boundary is carried forward (DeformedBoundary): the first crossing of the needle's arc
    with it after `start` is where the tip enters, and the re-entry, a wall point at rest, is
    found along that wall (_wall_point). A tip already inside at `start` (the wall moved over
    it in the last equilibrium) enters there, at its material point."""
    t0 = time.perf_counter()
    geometry, center = insertion.geometry, insertion.center
    rotation_of = _rotation_about(insertion, start)
    try:
        boundary = DeformedBoundary(insertion)
        if not boundary.contains(geometry.tip(end, center)):
            return None
        tip = geometry.tip(start, center)
        if boundary.contains(tip):
            return insertion.domain.clip(material_point(insertion, tip)), start
        chords, rotations = boundary.circle_crossings(center, geometry.radius, rotation_of)
        ahead = chords[(rotations >= start - ROTATION_ROUNDOFF) & (rotations <= end + ROTATION_ROUNDOFF)]
        if not len(ahead):  # the even-odd rule and the crossings count the same chords
            raise TipTrackingJump(f"the tip lies inside the deformed tissue at {end:.3f} rad but its arc from "
                                  f"{start:.3f} rad crosses no boundary")
        # the first crossing after a start outside enters
        point, rotation = _wall_point(insertion, boundary.reference[ahead[0]], boundary.reference[ahead[0] + 1],
                                      rotation_of, start)
        return point, min(max(rotation, start), end)
    except TipTrackingJump as jump:
        raise InsertionFailure(f"re-entry of the tip between needle rotations {start:.3f} and {end:.3f} rad: "
                               f"{jump}") from None
    finally:
        insertion.timings["tip_tracking"] += time.perf_counter() - t0
