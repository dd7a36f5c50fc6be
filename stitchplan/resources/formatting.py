"""How estimates and refusals write counts, amounts, bytes and durations."""

from __future__ import annotations

import math

from .model_size import COUNT_CAP


def count_text(value: int, about: str = "") -> str:
    return f"over {COUNT_CAP:.0e}" if value >= COUNT_CAP else f"{about}{value}"


def amount_text(value: float) -> str:
    return f"~{value:.3g}" if math.isfinite(value) else "more than 1e+308"


def bytes_text(value: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6)):
        if value >= size:
            return f"{value / size:.3g} {unit}"
    return f"{value / 1e3:.3g} kB"


def duration_text(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.2g} s"
    if seconds < 7200:
        return f"{seconds / 60:.3g} min"
    if seconds < 172800:
        return f"{seconds / 3600:.3g} h"
    return f"{seconds / 86400:.3g} days"
