"""Field types shared by the config blocks: finite numbers with their bounds and units,
integers, fixed choices and points. Each type carries the text of its error message
("expected a positive number (mm)"), so that every problem of a file reads the same way
(see stitchplan.config.messages)."""

from __future__ import annotations

import operator
import unicodedata
from collections.abc import Callable
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    WrapValidator,
)
from pydantic_core import PydanticCustomError

from ..geometry.rectangle import EDGE_NAMES
from .messages import combined

EDGES = EDGE_NAMES
MATERIAL_MODELS = ("saint-venant-kirchhoff", "neo-hookean")
TIP_TRACKING = ("auto", "inverse-gradient", "levenberg-marquardt")
LINEAR_SOLVERS = ("direct", "minres")
INTEGRATIONS = ("gauss", "vci")
TURNS = ("cw", "ccw")

# every block: unknown keys refused, no nan or inf anywhere
BLOCK = ConfigDict(extra="forbid", allow_inf_nan=False)

NOT_GIVEN = object()


def problem(expected: str, field: str | None = None, value: Any = NOT_GIVEN,
            absent: tuple[str, ...] = ()) -> PydanticCustomError:
    """The error of a check: `expected` completes "<field>: got <value>, expected ...".
    `field` names a field below the validated one (a check of a whole block reporting on one
    of its fields); `value` replaces the input as the value shown; `absent`: keys of the
    validated block whose absence the problem is (a misspelling of one is told once,
    messages.merged_typos)."""
    context: dict[str, Any] = {"expected": expected}
    if field is not None:
        context["field"] = field
    if value is not NOT_GIVEN:
        context["value"] = value
    if absent:
        context["absent"] = tuple(absent)
    return PydanticCustomError("expected", "expected {expected}", context)


def expecting(expected: str, *, items: bool = False, length: int | None = None) -> WrapValidator:
    """A wrap validator turning any error of the value into one `expected` error.

    items=True keeps the errors of a sequence's items (their own field paths and texts) and
    replaces those of the sequence itself only when no item failed; `length` checks a fixed
    length first (a pair)."""

    def validate(value: Any, handler: Callable[[Any], Any]) -> Any:
        if length is not None and (not isinstance(value, (list, tuple)) or len(value) != length):
            raise problem(expected)
        try:
            return handler(value)
        except ValidationError as error:
            item_errors = [e for e in error.errors() if e["loc"]]
            if items and item_errors:  # a list too short after dropping bad items: those count
                raise combined(item_errors) from None
            raise problem(expected) from None

    validate.expected = expected  # read by the message of a missing field
    return WrapValidator(validate)


def number(expected: str, **bounds: float) -> Any:
    """A finite float (ints accepted, bools and strings refused) within `bounds` (gt, ge, lt, le)."""
    return Annotated[float, Strict(), Field(allow_inf_nan=False, **bounds), expecting(expected)]


def _whole(value: Any) -> int:
    if isinstance(value, bool):
        raise problem("an integer")
    try:
        return operator.index(value)  # int and numpy integers; floats and strings refused
    except TypeError:
        raise problem("an integer") from None


def integer(low: int, high: int, why: str = "") -> Any:
    """An integer within [low, high]; `why` explains the bounds in the message."""
    return Annotated[int, Field(ge=low, le=high), BeforeValidator(_whole),
                     expecting(f"an integer between {low} and {high}" + (f" ({why})" if why else ""))]


def choice(values: tuple, expected: str | None = None) -> Any:
    expected = expected or "one of " + ", ".join(map(str, values))
    return Annotated[Literal[values], expecting(expected)]


def described(kind: Any, description: str, *, drop: tuple[str, ...] = (), **schema: Any) -> Any:
    """`kind` with a description for the JSON Schema, and further `schema` keywords (a
    `maximum` that a file's values keep, checked by the block); `drop`: keywords the schema
    must not state (a Python default that is not the one a file gets). With `drop`, `kind`
    must carry no schema keywords of its own (within's): pydantic ignores the callable then."""
    extra: Any = schema
    if drop:
        def extra(field_schema: dict) -> None:
            for key in drop:
                field_schema.pop(key, None)
            field_schema.update(schema)
    return Annotated[kind, Field(description=description, **({"json_schema_extra": extra} if extra else {}))]


def within(kind: Any, high: float, expected: str, low: float | None = None) -> Any:
    """`kind` refusing, after its own check, a value above `high` (or below `low`; None: the
    kind's own lower bound stands) with `expected`: a magnitude that is a unit mistake, told
    as such (a negative length keeps its kind's message). The JSON Schema carries the bounds."""

    def check(value: float) -> float:
        if value > high or (low is not None and value < low):
            raise problem(expected)
        return value

    schema = {"maximum": high, **({"minimum": low} if low is not None else {})}
    return Annotated[kind, AfterValidator(check), Field(json_schema_extra=schema)]


Number = number("a number (mm)")
Positive = number("a positive number", gt=0)
PositiveMM = number("a positive number (mm)", gt=0)
Point = Annotated[tuple[Number, Number], expecting("a pair [x, y] of numbers (mm)", items=True, length=2)]


def _one_line(text: str) -> str:
    """A label as run logs, CSV files and terminals take it: no control character (Unicode
    category Cc: NUL, tab, line breaks, escape, ...), so a label is one line and HDF5 can hold it."""
    for i, character in enumerate(text):
        if unicodedata.category(character) == "Cc":
            raise problem(f"a one-line string without control characters (U+{ord(character):04X} at "
                          f"character {i + 1})")
    return text


# a label: one line of text (JSON Schema: no character of category Cc, U+0000-001F and U+007F-009F)
LABEL = [AfterValidator(_one_line), Field(json_schema_extra={"pattern": "^[^\\u0000-\\u001f\\u007f-\\u009f]*$"})]
Name = Annotated[str, Strict(), expecting("a string"), *LABEL]
NonEmptyName = Annotated[str, Strict(), Field(min_length=1), expecting("a non-empty string"), *LABEL]
Flag = Annotated[bool, Strict(), expecting("true or false")]

# shared by the discretization, the needle and the families of a study
Dilation = number("a number > 1 (kernel support / spacing; at least ~1.5 for a linear basis, at most ~3: "
                  "wider kernels make the stiffness nearly singular)", gt=1)
MAX_QUADRATURE_ORDER = 10
QuadratureOrder = integer(1, MAX_QUADRATURE_ORDER)
BasisOrder = integer(1, 2)
CellsPerSpacing = integer(1, 4)
NeedleStep = number("a positive angle of at most 0.5 rad per step", gt=0, le=0.5)
TipTracking = choice(TIP_TRACKING)
LinearSolver = choice(LINEAR_SOLVERS)


def pair(expected: str, item: Any = Number) -> Any:
    """A pair [a, b] of `item`s; `expected` describes the pair as a whole."""
    return Annotated[tuple[item, item], expecting(expected, items=True, length=2)]


def sequence(item: Any, expected: str, min_length: int = 0) -> Any:
    """A list of `item`s, held as a tuple; `expected` describes the list as a whole."""
    return Annotated[tuple[item, ...], Field(min_length=min_length), expecting(expected, items=True)]
