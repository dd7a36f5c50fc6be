"""Validation errors as the user reads them: every problem of a file, one line each,
`<field>: got <value>, expected <what>`, in one InputError."""

from __future__ import annotations

import dataclasses
import difflib
import functools
import types
import typing
from typing import Any

from pydantic import TypeAdapter, ValidationError
from pydantic_core import PydanticCustomError

from ..errors import InputError

MAX_VALUE_CHARS = 60
MAPPING_ERRORS = ("dataclass_type", "dataclass_exact_type", "model_type", "dict_type",
                  "model_attributes_type")


def input_error(lines: list[str]) -> InputError:
    """One InputError for all `lines`: str() joins them, `.lines` keeps them apart."""
    error = InputError("\n".join(lines))
    error.lines = list(lines)
    return error


@functools.cache
def adapter(kind: Any) -> TypeAdapter:
    return TypeAdapter(kind)


def validate(kind: Any, raw: Any, path: str = "", root: str | None = None,
             context: dict | None = None) -> Any:
    """`raw` validated as `kind`, or an InputError listing every problem. Field paths start
    at `path` (a block's name, "" for a whole file); `root` names the value itself (default:
    `path`)."""
    try:
        return adapter(kind).validate_python(raw, context=context)
    except ValidationError as error:
        raise input_error(error_lines(error, kind, path, root or path or "value", raw)) from None


def valid_or_none(kind: Any, raw: Any) -> Any:
    """`raw` as `kind`, or None when it is not valid (its own errors are reported elsewhere)."""
    try:
        return adapter(kind).validate_python(raw)
    except ValidationError:
        return None


def combined(errors: list, title: str = "config") -> ValidationError:
    """One ValidationError from pydantic's error dicts and `problem(...)`s (errors of the
    validated value itself) together: a validator adding its own problems to those of the
    fields raises this, and pydantic places them below the validator's own path."""
    details = []
    for error in errors:
        if isinstance(error, PydanticCustomError):
            error = {"type": error, "loc": (), "input": None}
        elif not isinstance(error["type"], PydanticCustomError):
            error = {**error, "type": PydanticCustomError(error["type"], error["msg"], error.get("ctx"))}
        details.append({key: error[key] for key in ("type", "loc", "input")})
    return ValidationError.from_exception_data(title, details)


# --- one line per error ------------------------------------------------------------------


class _Null:
    """YAML's word for a missing value (`radius:` left blank), where Python would say None."""

    def __repr__(self) -> str:
        return "null"


class Shown(str):
    """A value shown as it reads (no quotes) in an error line."""

    def __repr__(self) -> str:
        return str(self)


def short(value: Any) -> str:
    """The value as given, on one short line (tuples shown as the lists a file gives, a
    blank value as YAML's null, booleans as YAML's true and false)."""
    def plain(v: Any) -> Any:
        if v is None:
            return _Null()
        if isinstance(v, bool):  # YAML's true and false, not Python's True and False
            return Shown("true" if v else "false")
        if isinstance(v, (tuple, list)):
            return [plain(item) for item in v]
        if isinstance(v, dict):
            return {k: plain(item) for k, item in v.items()}
        return v

    text = " ".join(repr(plain(value)).split())
    if len(text) <= MAX_VALUE_CHARS:
        return text
    cut = text[:MAX_VALUE_CHARS - 4]
    cut = cut[:cut.rfind(" ")] if " " in cut[MAX_VALUE_CHARS // 2:] else cut  # not in a word's middle
    return cut + (" ...'" if text[0] == "'" and text[-1] == "'" else " ...")  # a string's quote closed


def field_path(base: str, loc: tuple) -> str:
    path = base
    for key in loc:
        if isinstance(key, int):
            path += f"[{key}]"
        else:
            path = f"{path}.{key}" if path else str(key)
    return path


class Line(str):
    """An error line that merged_typos can join with another: `mapping` (the field path of
    the mapping it is about), `suggests` (an unknown key's near key there) and `absent` (the
    keys whose absence it reports)."""

    mapping: str = ""
    suggests: str | None = None
    absent: tuple[str, ...] = ()

    @classmethod
    def of(cls, text: str, mapping: str, suggests: str | None = None, absent: tuple[str, ...] = ()) -> Line:
        line = cls(text)
        line.mapping, line.suggests, line.absent = mapping, suggests, tuple(absent)
        return line


def merged_typos(lines: list[str]) -> list[str]:
    """`lines` with one line per misspelt key: an unknown key whose near key is the one a
    line of the same mapping reports missing (or among those whose absence it reports, as a
    load giving neither force nor displacement) is one mistake, told on the unknown key's line,
    which says what is missing; that line is dropped."""
    absent = {(line.mapping, key): line for line in lines if isinstance(line, Line) for key in line.absent}
    merged, dropped = [], set()
    for line in lines:
        other = absent.get((line.mapping, line.suggests)) if isinstance(line, Line) and line.suggests else None
        if other is None:
            merged.append(line)
            continue
        dropped.add(id(other))
        if len(other.absent) == 1:
            what = f"{field_path(other.mapping, (other.absent[0],))} is missing"
        else:
            what = (f"{other.mapping or 'the file'} gives neither "
                    + " nor ".join(repr(key) for key in other.absent))
        merged.append(f"{line[:-1]} {what})")  # into the "(did you mean ...?)" that ends it
    return [line for line in merged if id(line) not in dropped]


def error_lines(error: ValidationError, kind: Any, base: str = "", root: str = "value",
                raw: Any = None) -> list[str]:
    """One line per error of `error`; `raw`, the data validated, shows unknown keys as given."""
    lines = []
    for e in error.errors(include_url=False):
        loc, ctx = tuple(e["loc"]), e.get("ctx") or {}
        mapping = field_path(base, loc)  # of a problem of the block at loc (before ctx's field)
        if "field" in ctx:
            loc += tuple(int(part) if part.isdigit() else part for part in ctx["field"].split("."))  # "1.name": [1].name
        path = field_path(base, loc) or root
        value = ctx.get("value", e.get("input"))
        if e["type"] == "expected":
            lines.append(Line.of(f"{path}: got {short(value)}, expected {ctx['expected']}", mapping,
                                 absent=ctx.get("absent", ())))
        elif e["type"] == "missing":
            what = expected_of(kind, loc)
            lines.append(Line.of(f"{path}: missing, required" + (f": {what}" if what else ""),
                                 field_path(base, loc[:-1]), absent=loc[-1:]))
        elif e["type"] in ("extra_forbidden", "unexpected_keyword_argument", "invalid_key"):
            text, close = _unknown_key(kind, loc, field_path(base, loc[:-1]) or root, raw)
            lines.append(Line.of(text, field_path(base, loc[:-1]), suggests=close))
        elif e["type"] in MAPPING_ERRORS:
            keys = _keys(_block_at(kind, loc))
            what = "a mapping" + (f" with keys among: {', '.join(keys)}" if keys else "")
            got = "an empty file" if value is None and not loc and not base else short(value)
            lines.append(f"{path}: got {got}, expected {what}")
        else:
            what = e["msg"].removeprefix("Input should be ").removeprefix("Value error, ")
            lines.append(f"{path}: got {short(value)}, expected {what}")
    return merged_typos(lines)


CIRCLE_KEYS = ("center", "centre", "radius", "r")


def _unknown_key(kind: Any, loc: tuple, parent: str, raw: Any = None) -> tuple[str, str | None]:
    """The line of an unknown key, and the near key it suggests (None: none, or the key
    belongs in another block)."""
    key, allowed = _given_key(raw, loc), _keys(_block_at(kind, loc[:-1]))
    line = f"{parent}: unknown key {_as_written(key)}, expected one of: {', '.join(allowed)}"
    if "circle" in allowed and str(key) in CIRCLE_KEYS:  # a hole's or region's circle given flat
        return line + " (a circle is given as circle: {center: [x, y], radius: r})", None
    home = [name for name, block in _blocks(kind) if name != (loc[-2] if len(loc) > 1 else None)
            and str(key) in _keys(block)]
    if home:  # a key of another block: say where it goes, not a near spelling here
        return line + f" ({_as_written(key)} belongs in {' or '.join(home)})", None
    close = difflib.get_close_matches(str(key), allowed, n=1)
    return (line + f" (did you mean {close[0]!r}?)", close[0]) if close else (line, None)


def _blocks(kind: Any) -> list[tuple[str, Any]]:
    """The top-level blocks of `kind` (name, type) that have keys of their own."""
    fields = getattr(_strip(kind), "__pydantic_fields__", None) or {}
    return [(name, _strip(info.annotation)) for name, info in fields.items() if _keys(_strip(info.annotation))]


def value_at(raw: Any, path: tuple) -> Any:
    """The value at `path` (keys and indices) in a file's data, None where there is none."""
    for step in path:
        try:
            raw = raw[step]
        except (KeyError, IndexError, TypeError):
            return None
    return raw


def _given_key(raw: Any, loc: tuple) -> Any:
    """The key of the mapping at loc[:-1] in `raw` that pydantic names loc[-1]: it names a key
    `true` 1, `1.5` '1.5' and `null` 'None' (loc[-1] itself when `raw` does not lead there)."""
    parent = value_at(raw, loc[:-1])
    if isinstance(parent, dict):
        for key in parent:
            if not isinstance(key, str) and (key == loc[-1] if isinstance(loc[-1], int) else str(key) == loc[-1]):
                return key
    return loc[-1]


def _as_written(key: Any) -> str:
    """A key as a YAML file writes it: 'name' quoted, true, false, null and numbers plain."""
    if isinstance(key, bool):
        return "true" if key else "false"
    return "null" if key is None else repr(key)


# --- what the models expect at a field path -------------------------------------------------


def _keys(block: Any) -> list[str]:
    fields = getattr(block, "__pydantic_fields__", None)
    return list(fields) if fields else []


def _strip(kind: Any) -> Any:
    """The type inside Optional[...] and Annotated[...]; of a union of a name and a block
    (tissue.clamped's edge or {segment: ...}) the block, whose keys a mapping has."""
    while True:
        if typing.get_origin(kind) is typing.Annotated:
            kind = typing.get_args(kind)[0]
        elif typing.get_origin(kind) in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(kind) if a is not type(None)]
            blocks = [a for a in args if _keys(_strip(a))]
            if len(args) != 1 and len(blocks) != 1:
                return kind
            kind = args[0] if len(args) == 1 else blocks[0]
        else:
            return kind


def _block_at(kind: Any, loc: tuple) -> Any:
    """The type at `loc` below `kind` (a pydantic dataclass or model, or a container of them)."""
    for key in loc:
        kind = _strip(kind)
        fields = getattr(kind, "__pydantic_fields__", None)
        if isinstance(key, str) and fields and key in fields:
            kind = fields[key].annotation
        elif isinstance(key, int) and typing.get_origin(kind) in (tuple, list):
            args = typing.get_args(kind)
            kind = args[0] if len(args) == 2 and args[1] is Ellipsis else args[min(key, len(args) - 1)]
        else:
            return None
    return _strip(kind)


def expected_of(kind: Any, loc: tuple) -> str | None:
    """The "expected ..." text of the field at `loc`, if its type carries one."""
    if not loc:
        return None
    parent = _block_at(kind, loc[:-1])
    fields = getattr(parent, "__pydantic_fields__", None) or {}
    info = fields.get(loc[-1]) if isinstance(loc[-1], str) else None
    if info is None:
        return None
    for item in info.metadata:
        text = getattr(getattr(item, "func", None), "expected", None)
        if text:
            return text
    block = _block_at(kind, loc)
    if dataclasses.is_dataclass(block):
        return "a mapping with keys among: " + ", ".join(_keys(block))
    return info.description
