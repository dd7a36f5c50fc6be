"""Numeric CSV tables with a fixed header: the marker files and force recordings."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..decimals import parse_number, spells_a_number
from ..errors import InputError


def cell_problem(text: str) -> str:
    """What was wrong with a cell parse_number refused, for the error message."""
    text = text.strip()
    if not text:
        return "missing; expected a finite number"
    if spells_a_number(text):
        return f"got {text!r}, expected a finite number"
    return f"got {text!r}, expected a finite number in plain decimals (digits 0-9, like -1.5e-3)"


def read_columns(path: str | Path, columns: tuple[str, ...],
                 label: str = "") -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a numeric CSV whose header holds exactly `columns`, in any order.

    Lines starting with '#' and blank lines are skipped (data files may carry a comment
    header). Returns ({column: values (n,)}, file line number of each row (n,)).
    Every cell must be a plain decimal number (parse_number). Every problem is an InputError
    naming the file (and `label`, e.g. the YAML field).
    """
    where = f"{label}: {path}" if label else f"{path}"
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            lines = [(number, line) for number, line in enumerate(handle, start=1)
                     if line.strip() and not line.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as error:
        reason = getattr(error, "strerror", None) or type(error).__name__
        raise InputError(f"{where}: cannot be read ({reason})") from None
    if not lines:
        raise InputError(f"{where}: empty, expected a header {','.join(columns)} and data rows")
    rows = list(csv.reader(line for _, line in lines))
    header = [name.strip() for name in rows[0]]
    again = [k for k, name in enumerate(header) if name in header[:k]]
    if again:  # perhaps the column missing, misnamed
        k, lacking = again[0], [name for name in columns if name not in header]
        lacks = f" (the header lacks {', '.join(lacking)})" if lacking else ""
        raise InputError(f"{where}: line {lines[0][0]}, column {k + 1}: got {header[k]!r} again, expected each "
                         f"column once{lacks}")
    if sorted(header) != sorted(columns):
        raise InputError(f"{where}: columns: got {','.join(header)!r}, expected the columns "
                         f"{','.join(columns)!r} (in any order, no others)")
    values = np.empty((len(rows) - 1, len(header)))
    for r, (row, (number, _)) in enumerate(zip(rows[1:], lines[1:])):
        if len(row) != len(header):
            raise InputError(f"{where}: line {number}: got {len(row)} values, expected "
                             f"{len(header)} ({','.join(header)})")
        for c, text in enumerate(row):
            value = parse_number(text)
            if value is None:
                raise InputError(f"{where}: line {number}, {header[c]}: {cell_problem(text)}")
            values[r, c] = value
    line_numbers = np.array([number for number, _ in lines[1:]], dtype=int)
    return {name: values[:, c] for c, name in enumerate(header)}, line_numbers
