"""The centre path a user gives `simulate --center-path`: a trajectory as `stitchplan plan`
exports it, read by csv_tables (its errors name the file, the line and the column) and checked
against the needle it is to move (its steps, angles and entry).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..csv_tables import decode_table, last_digits, parse_numeric_table, read_table_bytes
from ..errors import InputError
from ..needle.geometry import ENTRY_TOLERANCE, LEAN_TOLERANCE, NeedleGeometry, length, on_entry_circle

CENTER_PATH_COLUMNS = ("step", "center_x_mm", "center_y_mm")
ANGLE_COLUMN = "angle_rad"
TIP_COLUMNS = ("tip_x_mm", "tip_y_mm")
TIME_COLUMN = "time_s"
BASE_CENTER_COLUMNS = ("base_center_x_mm", "base_center_y_mm")
BASE_TIP_COLUMNS = ("base_tip_x_mm", "base_tip_y_mm")
# a tip as trajectory.csv writes it (rounded to 1e-9 mm, from centres rounded alike) lies within
# a few 1e-9 mm of its centre's needle. Written with 9 significant digits each coordinate is
# within half a unit of its 9th digit (5e-9 mm below 10 mm, 5e-8 mm below 100, 5e-7 mm from 100, 5e-6 mm from
# 1000 mm), a centre and its tip together within 1.42 times that: TIP_TOLERANCE_MM, or
# TIP_RELATIVE_TOLERANCE of the row's largest coordinate where that is more (2e-6 mm at 100 mm)
TIP_TOLERANCE_MM = 1e-6
TIP_RELATIVE_TOLERANCE = 2e-8


def point_tolerance(*points: np.ndarray) -> np.ndarray:
    """How far (mm) the points of each row may lie from where the needle puts them: the
    rounding of their printed digits (TIP_TOLERANCE_MM, TIP_RELATIVE_TOLERANCE), (n,)."""
    scale = np.max(np.abs(np.concatenate(points, axis=1)), axis=1)
    return np.maximum(TIP_TOLERANCE_MM, TIP_RELATIVE_TOLERANCE * scale)


@dataclass(frozen=True)
class CenterPathFile:
    """A centre path as read, once: its centres and what a run records of the file."""

    centers: np.ndarray  # (n, 2) mm
    text: str  # the file's text, a byte-order mark kept: the bytes `sha256` is of
    sha256: str


def read_center_path_file(path: str | Path, geometry: NeedleGeometry | None = None,
                          leaning: Callable[[np.ndarray], NeedleGeometry] | None = None) -> CenterPathFile:
    """read_center_path's centres, with the text and SHA-256 of the bytes they were read from
    (a pipe gives them once)."""
    expected = "a trajectory written by `stitchplan plan`"
    content = read_table_bytes(path, expected)
    text, digest = decode_table(content, path, expected)
    table, row_numbers, _ = parse_numeric_table(text, digest, path, CENTER_PATH_COLUMNS, expected)
    digits = last_digits(text, path, (*CENTER_PATH_COLUMNS[1:], *TIP_COLUMNS)) if all(
        name in table for name in TIP_COLUMNS) else None
    return CenterPathFile(_checked_centers(path, table, row_numbers, geometry, leaning, digits),
                          content.decode("utf-8"), digest)


def read_center_path(path: str | Path, geometry: NeedleGeometry | None = None,
                     leaning: Callable[[np.ndarray], NeedleGeometry] | None = None) -> np.ndarray:
    """Needle centres (n, 2) in mm from a trajectory CSV as `stitchplan plan` exports it:
    row n holds step n, from 0, in the columns step, center_x_mm, center_y_mm; the other
    columns (tips, times, base frame) must hold numbers too, time_s, when the file has
    it, increase (check_times), and the base-frame columns, when it has them, be one rigid
    motion of the tissue frame's centres and tips (check_base_frame). With the needle's `geometry`, the path must also fit that
    needle: its angle_rad, when the file has one, the needle's rotation schedule
    (check_angles), its centres the needle's steps and entry (check_center_path), and its
    tips, when it has them, the needle's tip about each centre (check_tips). `leaning(row 0)`: the needle a path starting there replays
    (needle.geometry.entry_lean: a plan may lean the needle at entry); a row 0 off the centre
    at entry but within LEAN_TOLERANCE of the circle about the entry is put onto it."""
    return read_center_path_file(path, geometry, leaning).centers


def _checked_centers(path: str | Path, table: dict[str, np.ndarray], row_numbers: np.ndarray,
                     geometry: NeedleGeometry | None,
                     leaning: Callable[[np.ndarray], NeedleGeometry] | None,
                     digits: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The centres of a centre path's table, checked as read_center_path says (`digits`: the
    unit of the last digit of each centre and tip cell, csv_tables.last_digits)."""
    _check_steps(path, table["step"], row_numbers)
    centers = np.column_stack([table["center_x_mm"], table["center_y_mm"]])
    if geometry is not None and leaning is not None:
        placed = on_entry_circle(geometry, centers[0], LEAN_TOLERANCE)
        if placed is not None and length(centers[0] - geometry.center) > ENTRY_TOLERANCE * geometry.radius:
            centers[0] = placed
        geometry = leaning(centers[0])
    tips = _points(table, TIP_COLUMNS)
    if geometry is not None:
        if ANGLE_COLUMN in table:
            check_angles(path, table[ANGLE_COLUMN], geometry, row_numbers)
        check_center_path(path, centers, geometry, row_numbers)
        if tips is not None:
            check_tips(path, tips, centers, geometry, row_numbers, digits)
    base_centers, base_tips = _points(table, BASE_CENTER_COLUMNS), _points(table, BASE_TIP_COLUMNS)
    if base_centers is not None and base_tips is not None and (tips is not None or geometry is not None):
        tips = geometry.tips_along(centers) if tips is None else tips
        check_base_frame(path, centers, tips, base_centers, base_tips, row_numbers)
    if TIME_COLUMN in table:
        check_times(path, table[TIME_COLUMN], row_numbers)
    return centers


def _check_steps(path: str | Path, steps: np.ndarray, row_numbers: np.ndarray) -> None:
    """Row k of the data holds step k: the first row where it does not is named."""
    wrong = np.flatnonzero(steps != np.arange(len(steps)))
    if wrong.size:
        k = wrong[0]
        raise InputError(f"{path}: line {row_numbers[k]}, step: got {steps[k]:g}, expected {k} (one row per needle "
                         f"step, numbered 0, 1, 2, ... in order)")


# trajectory.csv writes angles rounded to 1e-12 rad; a file written with 9 significant digits
# (by hand, or by an earlier stitchplan) lies within 5e-9 of k * step, relative to the larger
# of 1 rad and the angle; a path for another step misses by far more
ANGLE_TOLERANCE = 1e-8


def check_angles(path: str | Path, angles: np.ndarray, geometry: NeedleGeometry, row_numbers: np.ndarray) -> None:
    """Each row's angle_rad is the needle's rotation schedule, k * step for step k (the
    exit row too: the trajectory gives it the full step although the tip leaves during it);
    the robot turns the needle to these angles, so a path written for another step is
    refused at its first row that does not match."""
    expected = np.arange(len(angles)) * geometry.step  # as the trajectory writes them
    off = np.flatnonzero(np.abs(angles - expected) > ANGLE_TOLERANCE * np.maximum(1.0, np.abs(expected)))
    if off.size:
        k = off[0]
        raise InputError(f"{path}: line {row_numbers[k]}, angle_rad: got {angles[k]:.9g}, expected {expected[k]:.9g} "
                         f"(step {k} of the needle's {geometry.step:g} rad steps)")


def _points(table: dict[str, np.ndarray], columns: tuple[str, str]) -> np.ndarray | None:
    """The (n, 2) points of a pair of columns, None where the file lacks either."""
    return np.column_stack([table[name] for name in columns]) if all(name in table for name in columns) else None


def check_tips(path: str | Path, tips: np.ndarray, centers: np.ndarray, geometry: NeedleGeometry,
               row_numbers: np.ndarray, digits: dict[str, np.ndarray] | None = None) -> None:
    """Each row's tip where its centre puts the needle's tip at its step's rotation (k x step,
    the exit row's too): a file whose centres were edited and its tips not (or the other way
    round) says two things, and a robot may follow either; the first row that disagrees is
    refused. With `digits` (the unit of the last digit of each centre and tip cell) a file
    rounded to fewer digits may be off by what rounding moves a centre and a tip, half a unit
    of its finest cell in each coordinate of each: a trajectory rounded to the micrometre
    replays. The finest cell, not each cell's own: a writer that drops trailing zeros ('30'
    for 30.000000000, as plan's does) says nothing of its precision in those cells."""
    expected = geometry.tips_along(centers)
    off = np.hypot(*(tips - expected).T)  # a norm's squares overflow at 1e300 mm, warning on stderr
    tolerance = point_tolerance(tips, centers)
    if digits is not None:
        finest = min(float(units.min()) for units in digits.values())
        tolerance = np.maximum(tolerance, (1.0 + 1e-9) * math.sqrt(2.0) * finest)
    bad = np.flatnonzero(off > tolerance)
    if bad.size:
        k = bad[0]
        raise InputError(
            f"{path}: line {row_numbers[k]}, tip_x_mm, tip_y_mm: got [{tips[k, 0]:.9g}, {tips[k, 1]:.9g}], "
            f"expected [{expected[k, 0]:.9g}, {expected[k, 1]:.9g}], the tip of the needle about the row's centre "
            f"[{centers[k, 0]:.9g}, {centers[k, 1]:.9g}] at step {k} ({off[k]:.3g} mm off: the row's centre and "
            "tip disagree; export the trajectory again, or drop the tip columns)")


def check_base_frame(path: str | Path, centers: np.ndarray, tips: np.ndarray, base_centers: np.ndarray,
                     base_tips: np.ndarray, row_numbers: np.ndarray) -> None:
    """The base-frame columns one rigid motion (p_base = R p + t, as plan writes them) of the
    tissue frame's centres and tips: the robot follows those columns, the replay the tissue
    frame's, so a row where they disagree says two things and the first such row is refused.
    The transform is not the scenario's (the options may have replaced it) but the one the rows
    agree on: each row's centre and tip give a rotation and an offset, the medians of which
    hold however few rows were edited."""
    turned = np.arctan2(*(base_tips - base_centers)[:, ::-1].T) - np.arctan2(*(tips - centers)[:, ::-1].T)
    turned = turned[0] + np.angle(np.exp(1j * (turned - turned[0])))  # unwrapped about row 0's
    angle = float(np.median(turned))
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    offset = np.median(np.concatenate([base_centers - centers @ rotation.T, base_tips - tips @ rotation.T]), axis=0)
    tolerance = point_tolerance(centers, tips, base_centers, base_tips)
    for names, points, base in ((BASE_CENTER_COLUMNS, centers, base_centers), (BASE_TIP_COLUMNS, tips, base_tips)):
        expected = points @ rotation.T + offset
        off = np.hypot(*(base - expected).T)
        bad = np.flatnonzero(off > tolerance)
        if bad.size:
            k = bad[0]
            raise InputError(
                f"{path}: line {row_numbers[k]}, {names[0]}, {names[1]}: got [{base[k, 0]:.9g}, {base[k, 1]:.9g}], "
                f"expected [{expected[k, 0]:.9g}, {expected[k, 1]:.9g}], the row's tissue-frame point "
                f"[{points[k, 0]:.9g}, {points[k, 1]:.9g}] in the base frame the other rows give (rotation "
                f"{math.degrees(angle):.6g} deg, translation [{offset[0]:.6g}, {offset[1]:.6g}] mm; {off[k]:.3g} mm "
                "off: the row's base-frame and tissue-frame points disagree; export the trajectory again, or drop "
                "the base-frame columns)")


def check_times(path: str | Path, times: np.ndarray, row_numbers: np.ndarray) -> None:
    """time_s increases from row to row: the needle turns forward in time."""
    back = np.flatnonzero(np.diff(times) <= 0.0)
    if back.size:
        k = back[0] + 1
        raise InputError(f"{path}: line {row_numbers[k]}, time_s: got {times[k]:.9g}, expected more than the row "
                         f"before's {times[k - 1]:.9g} (the needle turns forward in time, one step per row)")


# a replayed path may end this many steps (relative to the needle's expected steps, at least
# MIN_STEP_SLACK) before or after the undeformed circle's exit: see check_center_path
STEP_SLACK = 0.25
MIN_STEP_SLACK = 2
MAX_CENTER_MOVE = 3.0  # needle radii: how far any centre may lie from the entry centre


def expected_rows(geometry: NeedleGeometry) -> tuple[int, int, int]:
    """(rows, fewest, most) of a centre path for this needle: an exported trajectory has
    one row per step 0 .. N+1 (row N+1 the exit step), N + 2 = expected_steps + 1 rows
    when the tip leaves where the undeformed circle does."""
    rows = geometry.expected_steps + 1
    slack = max(MIN_STEP_SLACK, math.ceil(STEP_SLACK * geometry.expected_steps))
    return rows, max(rows - slack, 2), rows + slack


def check_center_path(path: str | Path, centers: np.ndarray, geometry: NeedleGeometry, row_numbers: np.ndarray) -> None:
    """A centre path that fits the scenario's needle, or an InputError naming the file (and
    the row: `row_numbers` holds each centre's row in it):

    - its row count matches the steps the needle takes (`expected_rows`): the deformed
      tissue lets the tip leave some steps before or after the undeformed circle does (the
      shipped SH 1/2 scenes: the unplanned run exits 2 steps early, the planned runs where the
      circle does), so a quarter of the steps (at least 2) either way is allowed; a path
      written for another needle, step or scene is refused instead of being cut short or
      running out of rows mid-insertion;
    - row 0 is the needle centre at entry (within ENTRY_TOLERANCE radii): the tip starts at
      the entry point (`geometry` leaning there when the path leans it: entry_lean);
    - every centre lies within MAX_CENTER_MOVE needle radii of the entry centre: the planner
      moves the centre to follow the tissue's displacement, at most 1.04 radii on the shipped
      plans (9.24 mm on sh12_100x30); a centre further away is not a compensation but a
      path for another scene or frame (e.g. robot base coordinates).
    """
    rows, fewest, most = expected_rows(geometry)
    if not fewest <= len(centers) <= most:
        raise InputError(
            f"{path}: rows: got {len(centers)}, expected {fewest} to {most} for this needle "
            f"({geometry.expected_steps} steps of {geometry.step:g} rad until the tip exits: "
            f"{rows} rows as `stitchplan plan` exports them, give or take the steps deformation adds)")
    entry = geometry.center
    start = math.hypot(*(centers[0] - entry))
    if start > ENTRY_TOLERANCE * geometry.radius:
        raise InputError(
            f"{path}: line {row_numbers[0]}, center_x_mm, center_y_mm: got [{centers[0, 0]:.6g}, {centers[0, 1]:.6g}], "
            f"expected the needle centre at entry [{entry[0]:.6g}, {entry[1]:.6g}] (step 0), or one "
            f"{geometry.radius:g} mm from the entry point [{geometry.entry[0]:.6g}, {geometry.entry[1]:.6g}] "
            "(the needle leaning at entry)")
    distance = np.hypot(*(centers - entry).T)
    far = int(np.argmax(distance))
    if distance[far] > MAX_CENTER_MOVE * geometry.radius:
        raise InputError(
            f"{path}: line {row_numbers[far]}, center_x_mm, center_y_mm: got [{centers[far, 0]:.6g}, "
            f"{centers[far, 1]:.6g}], {distance[far]:.4g} mm from the entry centre "
            f"[{entry[0]:.6g}, {entry[1]:.6g}]; expected at most {MAX_CENTER_MOVE:g} needle radii "
            f"({MAX_CENTER_MOVE * geometry.radius:.4g} mm) from it")
