"""Numeric CSV tables with a header row: the files a user gives besides the scenario (a
centre path to replay, calibration markers and force recordings).

Every problem is an InputError with one line naming the file and, for a bad value, the line
and the column (`file: line 5, center_x_mm: got ...`): the line number in the file, the row a
spreadsheet shows, so with the header on the first line the first values are on line 2.
Blank lines, lines starting with '#' (a file may carry a comment header) and rows of empty
cells (',,,' as spreadsheets save blank rows) are skipped. The first row is the header.
"""

from __future__ import annotations

import csv
import hashlib
import re
from array import array
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from .config.yaml_files import read_input_bytes
from .decimals import last_digit, parse_number, spells_a_number
from .errors import InputError


def read_numeric_table(path: str | Path, columns: Sequence[str], expected: str, *, exact: bool = False,
                       label: str = "", max_rows: int | None = None,
                       rows_note: str = "") -> tuple[dict[str, np.ndarray], np.ndarray, str]:
    """Every column of the table as a float array, the line number of each data row (n,) and
    the SHA-256 of the bytes read (the ones the table holds, whatever becomes of the file).

    The header must name each of `columns` once (with `exact`, those and no others, in any
    order); every row has as many cells as the header, each a plain finite decimal
    (decimals.parse_number); at least one row. `expected` tells the user what file was
    wanted; `label` (e.g. the YAML field that named the file) goes before the path. More than
    `max_rows` rows are refused, counted but not kept past it (`rows_note`: why, after "expected
    at most `max_rows`").
    """
    content = read_table_bytes(path, expected, label=label)
    text, digest = decode_table(content, path, expected, label=label)
    del content  # the text alone from here: a million-row file's bytes are ~40 MB
    return parse_numeric_table(text, digest, path, columns, expected, exact=exact, label=label,
                               max_rows=max_rows, rows_note=rows_note)


def read_table_bytes(path: str | Path, expected: str, *, label: str = "") -> bytes:
    """The bytes of a table file, read once: a pipe gives them once, so the text parsed, its
    SHA-256 and the text a run records all come from them."""
    where = f"{label}: {path}" if label else f"{path}"
    try:
        return read_input_bytes(Path(path), where, f"a CSV table ({expected})")
    except OSError as error:
        raise InputError(f"{where}: cannot be read ({error.strerror or error})") from None


def decode_table(content: bytes, path: str | Path, expected: str, *, label: str = "") -> tuple[str, str]:
    """The text of a table's bytes (a byte-order mark left out) and their SHA-256."""
    try:
        text = content.decode("utf-8-sig")  # -sig: a BOM
    except UnicodeDecodeError:
        where = f"{label}: {path}" if label else f"{path}"
        raise InputError(f"{where}: not a text file; expected a CSV table ({expected})") from None
    return text, hashlib.sha256(content).hexdigest()


def parse_numeric_table(text: str, digest: str, path: str | Path, columns: Sequence[str], expected: str, *,
                        exact: bool = False, label: str = "", max_rows: int | None = None,
                        rows_note: str = "") -> tuple[dict[str, np.ndarray], np.ndarray, str]:
    """read_numeric_table of a table's `text` read from `path` (decode_table: with `digest`)."""
    where = f"{label}: {path}" if label else f"{path}"
    rows = _rows(text, where)
    wanted = f"exactly the columns {','.join(columns)} (in any order)" if exact else f"at least {', '.join(columns)}"
    first = next(rows, None)
    if first is None:
        raise InputError(f"{where}: got an empty file (no header, no rows); expected a header with {wanted} "
                         f"({expected})")
    header = [name.strip() for name in first[1]]
    missing = [name for name in columns if name not in header]
    _check_header(where, first[0], header, missing)  # a column given twice first: it may be the one missing
    if exact and sorted(header) != sorted(columns):
        raise InputError(f"{where}: columns: got {','.join(header)!r}, expected the columns "
                         f"{','.join(columns)!r} (in any order, no others)")
    if missing:
        raise InputError(f"{where}: columns {header} lack {missing}; expected {wanted} ({expected})")
    values, row_numbers = array("d"), array("q")  # flat: a list of lists of floats took ~0.2 kB a row
    for number, row in rows:
        if max_rows is not None and len(row_numbers) >= max_rows:
            count = len(row_numbers) + 1 + sum(1 for _ in rows)
            raise InputError(f"{where}: got {count} rows, expected at most {max_rows}{rows_note}")
        values.extend(_row_values(where, number, row, header))
        row_numbers.append(number)
    if not row_numbers:
        raise InputError(f"{where}: no rows below the header; expected {expected}")
    table = np.frombuffer(values, dtype=float).reshape(-1, len(header))  # (rows, columns)
    return ({name: table[:, k].copy() for k, name in enumerate(header)}, np.array(row_numbers, dtype=int),
            digest)


def last_digits(text: str, path: str | Path, columns: Sequence[str]) -> dict[str, np.ndarray]:
    """For each of `columns` a table's text has, the unit of the last digit written in each of
    its rows (decimals.last_digit), in the rows parse_numeric_table reads (the table is read
    already: its cells are numbers)."""
    rows = _rows(text, str(path))
    header = [name.strip() for name in next(rows)[1]]
    wanted = [(name, header.index(name)) for name in columns if name in header]
    units = [[last_digit(row[k]) for name, k in wanted] for _, row in rows]
    table = np.array(units, dtype=float).reshape(-1, len(wanted))
    return {name: table[:, j] for j, (name, _) in enumerate(wanted)}


# a line as io.StringIO(text, newline="") splits them (ended by \n, \r\n or \r), found in the
# text itself: a list of a million-row file's lines took ~0.3 kB a row, a StringIO 4 bytes a character
LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+")


def _rows(text: str, where: str) -> Iterator[tuple[int, list[str]]]:
    """(line number, cells) of each row of the text, one at a time, skipping blank lines, lines
    starting with '#' and rows of empty cells; a row's number is its first line's. A cell past
    csv's field limit is refused naming the line it starts on."""
    start: list[int | None] = [None]

    def kept() -> Iterator[str]:
        for number, match in enumerate(LINE.finditer(text), start=1):
            line = match.group()
            if line.strip() and not line.lstrip().startswith("#"):
                if start[0] is None:  # the reader asks for the lines of one row at a time
                    start[0] = number
                yield line

    reader = csv.reader(kept())
    while True:
        try:
            row = next(reader, None)
        except csv.Error:  # the field limit: a stray quote's cell runs on to the end of the file
            raise InputError(f"{where}: line {start[0]}: got a cell longer than {csv.field_size_limit()} "
                             "characters (a quote left open takes in the lines after it), expected a number in "
                             "each cell") from None
        if row is None:
            return
        number, start[0] = start[0], None
        if any(cell.strip() for cell in row):
            yield number, row


def _check_header(where: str, line: int, header: list[str], missing: list[str]) -> None:
    """Every column named, and named once: a value must not depend on which one is read
    (`missing`: required columns the header lacks, told with a column given twice)."""
    for k, name in enumerate(header):
        if not name:
            raise InputError(f"{where}: line {line}, column {k + 1}: got no name, expected a column name "
                             f"(header {','.join(header)})")
        if name in header[:k]:
            lacks = f" (the header lacks {', '.join(missing)})" if missing else ""
            raise InputError(f"{where}: line {line}, column {k + 1}: got {name!r} again, expected each "
                             f"column once{lacks}")


def _row_values(where: str, line: int, row: list[str], header: list[str]) -> list[float]:
    """A row of as many cells as the header, each a finite number."""
    if len(row) < len(header):
        raise InputError(f"{where}: line {line}, {header[len(row)]}: missing; got {len(row)} cells, expected "
                         f"{len(header)} as in the header ({','.join(header)})")
    if len(row) > len(header):
        raise InputError(f"{where}: line {line}: got {len(row)} cells, expected {len(header)} as in the "
                         f"header ({','.join(header)})")
    return [_number(where, line, name, text) for name, text in zip(header, row)]


def _number(where: str, line: int, name: str, text: str) -> float:
    value = parse_number(text)
    if value is None:
        raise InputError(f"{where}: line {line}, {name}: {_cell_problem(text)}")
    return value


def _cell_problem(text: str) -> str:
    """What was wrong with a cell parse_number refused."""
    text = text.strip()
    if not text:
        return "missing; expected a finite number"
    if spells_a_number(text):
        return f"got {text!r}, expected a finite number"
    return f"got {text!r}, expected a finite number in plain decimals (digits 0-9, like -1.5e-3)"
