"""Readers of the files a user gives besides the scenario: CSV tables with named columns.

Every problem is an InputError with one line naming the file and, for a bad value, the row
and the column. Rows are counted as a spreadsheet shows them: the header is row 1, the first
values are row 2.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..needle.geometry import NeedleGeometry

CENTER_PATH_COLUMNS = ("step", "center_x_mm", "center_y_mm")


def read_columns(path: str | Path, columns: Sequence[str], expected: str) -> dict[str, np.ndarray]:
    """The named numeric columns of a CSV file with a header row, as float arrays (other
    columns are ignored); `expected` tells the user what file was wanted."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:  # -sig: spreadsheets' BOM
            reader = csv.reader(handle)
            header = [name.strip() for name in next(reader, [])]
            missing = [name for name in columns if name not in header]
            if missing:
                raise InputError(f"{path}: columns {header} lack {missing}; expected at least "
                                 f"{', '.join(columns)} ({expected})")
            where = [header.index(name) for name in columns]
            values = [[_number(path, reader.line_num, row, name, k) for name, k in zip(columns, where)]
                      for row in reader if any(cell.strip() for cell in row)]
    except OSError as error:
        raise InputError(f"{path}: cannot be read ({error.strerror or error})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file; expected a CSV table ({expected})") from None
    if not values:
        raise InputError(f"{path}: no rows below the header; expected {expected}")
    table = np.asarray(values, dtype=float)  # (rows, columns)
    return {name: table[:, k] for k, name in enumerate(columns)}


def _number(path: Path, row_number: int, row: list[str], name: str, column: int) -> float:
    if column >= len(row) or not row[column].strip():
        raise InputError(f"{path}: row {row_number}, {name}: missing; expected a number")
    text = row[column].strip()
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{path}: row {row_number}, {name}: got {text!r}, expected a number") from None
    if not math.isfinite(value):
        raise InputError(f"{path}: row {row_number}, {name}: got {text!r}, expected a finite number")
    return value


def read_center_path(path: str | Path, geometry: NeedleGeometry | None = None) -> np.ndarray:
    """Needle centres (n, 2) in mm from a trajectory CSV (columns step, center_x_mm,
    center_y_mm, as `stitchplan plan` exports them); row n holds step n, from 0. With the
    needle's `geometry`, the path must also fit that needle (check_center_path)."""
    table = read_columns(path, CENTER_PATH_COLUMNS, "a trajectory written by `stitchplan plan`")
    steps = table["step"]
    if not np.array_equal(steps, np.arange(len(steps))):
        shown = ", ".join(f"{s:g}" for s in steps[:5]) + (", ..." if len(steps) > 5 else "")
        raise InputError(f"{path}: step: got [{shown}], expected 0, 1, 2, ... one row per step")
    centers = np.column_stack([table["center_x_mm"], table["center_y_mm"]])
    if geometry is not None:
        check_center_path(path, centers, geometry)
    return centers


# a replayed path may end this many steps (relative to the needle's expected steps, at least
# MIN_STEP_SLACK) before or after the undeformed circle's exit: see check_center_path
STEP_SLACK = 0.25
MIN_STEP_SLACK = 2
ENTRY_TOLERANCE = 0.01  # needle radii: row 0 is the needle centre at entry
MAX_CENTER_MOVE = 3.0  # needle radii: how far any centre may lie from the entry centre


def expected_rows(geometry: NeedleGeometry) -> tuple[int, int, int]:
    """(rows, fewest, most) of a centre path for this needle: an exported trajectory has
    one row per step 0 .. N+1 (row N+1 the exit step), N + 2 = expected_steps + 1 rows
    when the tip leaves where the undeformed circle does."""
    rows = geometry.expected_steps + 1
    slack = max(MIN_STEP_SLACK, math.ceil(STEP_SLACK * geometry.expected_steps))
    return rows, max(rows - slack, 2), rows + slack


def check_center_path(path: str | Path, centers: np.ndarray, geometry: NeedleGeometry) -> None:
    """A centre path that fits the scenario's needle, or an InputError naming the file:

    - its row count matches the steps the needle takes (`expected_rows`): the deformed
      tissue lets the tip leave some steps before or after the undeformed circle does (the
      shipped SH 1/2 scenes: the unplanned run exits 2 steps early, the planned runs where the
      circle does), so a quarter of the steps (at least 2) either way is allowed; a path
      written for another needle, step or scene is refused instead of being cut short or
      running out of rows mid-insertion;
    - row 0 is the needle centre at entry (within ENTRY_TOLERANCE radii): the tip starts at
      the entry point;
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
    start = float(np.linalg.norm(centers[0] - entry))
    if start > ENTRY_TOLERANCE * geometry.radius:
        raise InputError(
            f"{path}: row 2, center_x_mm, center_y_mm: got [{centers[0, 0]:.6g}, {centers[0, 1]:.6g}], "
            f"expected the needle centre at entry [{entry[0]:.6g}, {entry[1]:.6g}] (step 0)")
    distance = np.linalg.norm(centers - entry, axis=1)
    far = int(np.argmax(distance))
    if distance[far] > MAX_CENTER_MOVE * geometry.radius:
        raise InputError(
            f"{path}: row {far + 2}, center_x_mm, center_y_mm: got [{centers[far, 0]:.6g}, "
            f"{centers[far, 1]:.6g}], {distance[far]:.4g} mm from the entry centre "
            f"[{entry[0]:.6g}, {entry[1]:.6g}]; expected at most {MAX_CENTER_MOVE:g} needle radii "
            f"({MAX_CENTER_MOVE * geometry.radius:.4g} mm) from it")
