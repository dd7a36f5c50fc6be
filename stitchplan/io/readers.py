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
        raise InputError(f"{path}: row {row_number}, {name} = {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{path}: row {row_number}, {name} = {text!r} is not a finite number")
    return value


def read_center_path(path: str | Path) -> np.ndarray:
    """Needle centres (n, 2) in mm from a trajectory CSV (columns step, center_x_mm,
    center_y_mm, as `stitchplan plan` exports them); row n holds step n, from 0."""
    table = read_columns(path, CENTER_PATH_COLUMNS, "a trajectory written by `stitchplan plan`")
    steps = table["step"]
    if not np.array_equal(steps, np.arange(len(steps))):
        shown = ", ".join(f"{s:g}" for s in steps[:5]) + (", ..." if len(steps) > 5 else "")
        raise InputError(f"{path}: steps [{shown}]; expected 0, 1, 2, ... one row per step")
    return np.column_stack([table["center_x_mm"], table["center_y_mm"]])
