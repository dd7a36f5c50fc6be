"""Numbers in the CSV files a user gives (trajectories, marker positions, force recordings):
plain decimals only. Python's float() also takes '1_0' (as 10), 'infinity' and non-ASCII
digits (Arabic-Indic ones as their values), none of which such a file should contain."""

from __future__ import annotations

import math
import re

DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def parse_number(text: str) -> float | None:
    """The finite number a plain decimal `text` spells (surrounding blanks allowed), else None."""
    text = text.strip()
    if not DECIMAL.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None  # '1e999' overflows to inf


PARTS = re.compile(r"[+-]?[0-9]*(?:\.([0-9]*))?(?:[eE]([+-]?[0-9]+))?")


def last_digit(text: str) -> float:
    """The value of one unit in the last digit a plain decimal `text` writes: 1e-3 for
    '12.345', 1 for '12', 1e-4 for '1.5e-3' (what rounding to its digits may have moved it by,
    twice over)."""
    match = PARTS.fullmatch(text.strip())
    fraction, exponent = (match.group(1) or "", match.group(2) or "0") if match else ("", "0")
    # parse_number takes a zero's '0e400' (and an exponent of thousands of digits): such a unit
    # is inf or 0, not an OverflowError of 10.0 ** 400 nor int()'s digit limit
    if len(exponent.lstrip("+-0")) > 6:
        exponent = "-1000000" if exponent.startswith("-") else "1000000"
    return float(f"1e{int(exponent) - len(fraction)}")


def spells_a_number(text: str) -> bool:
    """Whether `text` spells a number parse_number refuses only for not being finite."""
    text = text.strip()
    return bool(DECIMAL.fullmatch(text) or NON_FINITE.fullmatch(text))
