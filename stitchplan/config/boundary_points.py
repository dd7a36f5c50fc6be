"""Points a file places on the tissue's boundary (a needle entry, the ends of load and clamped
segments) or inside it (probes), as a person types or measures them.

A point within the domain's input tolerance of the boundary (a micrometre; see
geometry.bounding_box.INPUT_TOLERANCE_MM) is moved onto it (geometry.boundary.snap_to_boundary)
and the run uses the moved point; the checks that follow (a corner, a clamped edge, one edge
holding a segment) judge the moved point. A point further off is refused with the nearest
boundary point, written to the nanometre so that it is accepted when pasted back. `log_moves`
says which points moved: at INFO when a move is within the rounding of the digits typed, at
WARNING when it is more.
"""

from __future__ import annotations

import logging
import math
from decimal import Decimal, InvalidOperation
from typing import Any

import numpy as np

from .messages import field_path, value_at
from ..geometry.boundary import nearest_boundary_point, smooth_vertex, snap_to_boundary
from ..geometry.polygon_domain import PolygonDomain
from ..geometry.polygons import CIRCLE_SEGMENTS
from ..geometry.rectangle import Rectangle

log = logging.getLogger(__name__)

SHOWN_DECIMALS = 6  # a nanometre: a point shown so lies within 0.71 nm of its value, far inside the tolerance


def placed(value, context: dict | None, place):
    """A validator's `value` placed by `place(domain, value)` (segment_on_boundary,
    probe_in_tissue: the moved value, or None and what was expected) on the domain of the
    validation `context`; unchanged without one (a block made in Python). Raises the
    expectation as the field's problem."""
    from .fields import problem

    domain = (context or {}).get("domain")
    if domain is None:
        return value
    moved, expected = place(domain, value)
    if moved is None:
        raise problem(expected)
    return moved


def shown_number(value: float) -> str:
    """A coordinate to the nanometre, without trailing zeros (13.333333, 40, -0.5)."""
    text = f"{round(float(value), SHOWN_DECIMALS) + 0.0:.{SHOWN_DECIMALS}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def shown_point(point) -> str:
    return "[" + ", ".join(shown_number(value) for value in point) + "]"


def shown_as_given(points) -> str:
    """Points (a segment) as a file gives them ([[40.0, 5.0], ...]), a coordinate moved onto
    the boundary to the nanometre (33.333294 rather than 33.33329411764706)."""
    return "[" + ", ".join(shown_point_as_given(point) for point in points) + "]"


def shown_point_as_given(point) -> str:
    """One point as shown_as_given shows a segment's ([0.0, 15.0], [13.333294, 26.666706])."""
    def number(value: float) -> str:
        short = shown_number(value)
        return repr(float(value)) if float(short) == float(value) else short

    return "[" + ", ".join(number(v) for v in point) + "]"


def nearest_note(domain: Rectangle | PolygonDomain, point) -> str:
    """'the nearest is [x, y], d mm away' (with the circle note on a domain with holes)."""
    nearest, distance = nearest_boundary_point(domain, point)
    # a circle's hole is its inscribed polygon of CIRCLE_SEGMENTS vertices (tissue_shape)
    circles = (f" (a circular hole is held as its inscribed {CIRCLE_SEGMENTS}-gon)"
               if any(len(hole) == CIRCLE_SEGMENTS for hole in getattr(domain, "holes", ())) else "")
    return f"the nearest is {shown_point(nearest)}, {distance:.3g} mm away{circles}"


def on_boundary(domain: Rectangle | PolygonDomain) -> str:
    return f"a point on the boundary of the {domain.describe()} or within {domain.input_tolerance:g} mm of it"


def segment_expectation(domain: Rectangle | PolygonDomain) -> str:
    # one edge, or consecutive edges on one straight line (PolygonDomain.straight_run)
    return f"a non-empty straight piece of one edge of the {domain.describe()}"


def as_pair(point) -> tuple[float, float]:
    return (float(point[0]), float(point[1]))


def entry_on_boundary(domain: Rectangle | PolygonDomain, entry) -> tuple[tuple[float, float] | None, str, str]:
    """A needle entry moved onto the boundary, or (None, what was received, what is expected):
    off the boundary (with the nearest point), or at a corner (a vertex where the boundary
    turns by more than geometry.polygons.CORNER_TURN, or within the input tolerance of one)."""
    snapped = snap_to_boundary(domain, entry)
    if snapped is None:
        return None, "", f"{on_boundary(domain)}; {nearest_note(domain, entry)}"
    if len(domain.edges_at(snapped)) > 1 and not smooth_vertex(domain, snapped):
        gap = float(np.linalg.norm(snapped - np.asarray(entry, dtype=float)))
        where = ("a corner" if gap <= domain.tolerance
                 else f"{gap:.3g} mm from the corner {shown_point(snapped)}")
        return None, where, ("a point inside one edge (the entry normal is undefined at a corner; a point "
                             f"within {domain.input_tolerance:g} mm of a vertex is the vertex)")
    return as_pair(snapped), "", ""


def segment_on_boundary(domain: Rectangle | PolygonDomain, segment) -> tuple[tuple | None, str]:
    """A load or clamped segment with both ends moved onto the boundary, or (None, what is
    expected): a straight piece of one edge, naming the nearest boundary point of an end off it."""
    snapped = [snap_to_boundary(domain, end) for end in segment]
    off = [f"its end {shown_point(end)} is off the boundary, {nearest_note(domain, end)}"
           for end, moved in zip(segment, snapped) if moved is None]
    if off:
        return None, f"{segment_expectation(domain)}; " + "; ".join(off)
    apart = float(np.linalg.norm(np.subtract(snapped[1], snapped[0])))
    if 0.0 < apart <= domain.input_tolerance:  # a point, typed as two (4e-15 mm apart: no load reached the tissue)
        return None, (f"{segment_expectation(domain)} (its ends are one point: {apart:.2g} mm apart, within the "
                      f"{domain.input_tolerance:g} mm to which points are placed)")
    if domain.segment_edge(*snapped) is None:
        why = ("its ends are one point" if np.array_equal(snapped[0], snapped[1])
               else "its ends are on the boundary, not on one edge or one straight run of edges")
        return None, f"{segment_expectation(domain)} ({why})"
    return tuple(as_pair(end) for end in snapped), ""


def inside_expectation(domain: Rectangle | PolygonDomain) -> str:
    if isinstance(domain, Rectangle):
        return f"a point inside [0, {domain.width:g}] x [0, {domain.height:g}] mm"
    return f"a point inside the {domain.describe()}"


def probe_in_tissue(domain: Rectangle | PolygonDomain, point) -> tuple[tuple[float, float] | None, str]:
    """A probe inside the tissue as given, one just outside moved onto the boundary, or (None,
    what is expected, naming the nearest boundary point)."""
    if domain.contains(np.asarray(point, dtype=float)):
        return tuple(point), ""
    snapped = snap_to_boundary(domain, point)
    if snapped is None:
        return None, f"{inside_expectation(domain)}; {nearest_note(domain, point)}"
    if not domain.contains(snapped):  # kept as given, on the boundary to round-off, yet outside: onto it
        snapped = nearest_boundary_point(domain, snapped)[0]
    return as_pair(snapped), ""


# --- which points moved ------------------------------------------------------------------------


def _rounding(value: Any) -> float:
    """Half a unit of the last decimal written (13.3333: 5e-5; 18.0: 0.05; 40: 0.5)."""
    try:
        exponent = Decimal(repr(value)).as_tuple().exponent
    except (InvalidOperation, TypeError):
        return 0.0
    return 0.5 * 10.0 ** exponent if isinstance(exponent, int) else 0.0



def segment_ends(raw: Any, path: tuple, items) -> list[tuple[str, Any, Any]]:
    """(field, as the file gives it, as the run uses it) of each end of the segments of
    `items` (the validated list at `path` in the file's data `raw`; items without a segment,
    a clamped edge named whole, have none): log_moves's points."""
    return [(field_path("", (*path, i, "segment", k)), value_at(raw, (*path, i, "segment", k)), end)
            for i, item in enumerate(items) for k, end in enumerate(getattr(item, "segment", ()))]


def log_moves(domain: Rectangle | PolygonDomain, moves: list[tuple[str, Any, Any]], source: str = "") -> None:
    """One log line per point (field, as given, as used) moved by more than round-off, naming
    the file `source` when given, as the file's errors do."""
    for field, given, used in moves:
        try:
            given_xy = np.asarray([float(value) for value in given])
        except (TypeError, ValueError):
            continue
        used_xy = np.asarray(used, dtype=float)
        if given_xy.shape != (2,) or used_xy.shape != (2,):
            continue
        moved = np.abs(used_xy - given_xy)
        distance = float(np.hypot(*moved))
        if not math.isfinite(distance) or distance <= domain.tolerance:
            continue
        rounding = all(m <= _rounding(value) * (1 + 1e-9) for m, value in zip(moved, given))
        log.log(logging.INFO if rounding else logging.WARNING,
                "%s%s: %s lies %.3g mm off the boundary of the %s; the run uses %s on it%s",
                f"{source}: " if source else "", field,
                "[" + ", ".join(map(repr, given)) + "]", distance, domain.describe(), shown_point(used_xy),
                "" if rounding else " (more than the rounding of the digits given)")
