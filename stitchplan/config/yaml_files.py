"""Reading YAML input files: text and data, or one clear line per problem naming the file.

Plain scalars follow the YAML 1.2 core schema (what `stitchplan schema` and editors assume):
`1e-6` is a number; `010` is ten; `5:00`, `yes`, `no`, `on`, `off` and dates stay strings,
where YAML 1.1 would silently read 300, True, False or a date. Refused besides syntax
errors: text that is not UTF-8, a key given twice in one mapping (the second would silently
win; every such key of a file is reported at once), YAML 1.1's merge key `<<` (YAML 1.2 has
none, and the keys it merges give way silently to the mapping's own: a second way to give a
key twice; both are listed with the file's other problems, read_yaml_file's keys_later), tags
without a plain-data meaning, and
aliases beyond a small bound (an "alias bomb" expands a few lines into billions of values),
and nesting deeper than a bound (the loader recurses once per level: 500 nested `[` would
end in Python's recursion limit)."""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, NamedTuple, TypeVar

import yaml

from ..errors import InputError
from .messages import input_error

T = TypeVar("T")

MAX_ALIASES = 100  # alias uses per file
MAX_VALUES = 100_000  # values after expanding every alias
MAX_DEPTH = 100  # nested sequences and mappings, aliases expanded (a scenario needs about 6)

# YAML 1.2 core schema (spec 1.2.2, section 10.3.2)
INTEGER = r"[-+]?[0-9]+"
OCTAL = r"0o[0-7]+"
HEXADECIMAL = r"0x[0-9a-fA-F]+"
FLOAT = r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
INFINITY = r"[-+]?\.(?:inf|Inf|INF)"
NAN = r"\.(?:nan|NaN|NAN)"
TRUE, FALSE = ("true", "True", "TRUE"), ("false", "False", "FALSE")


def _whole(*patterns: str) -> re.Pattern:
    return re.compile("(?:" + "|".join(patterns) + r")\Z")


# tag, the plain scalars it takes, the characters they can start with
CORE_SCALARS = [
    ("tag:yaml.org,2002:null", _whole("~", "null", "Null", "NULL", ""), ["~", "n", "N", ""]),
    ("tag:yaml.org,2002:bool", _whole(*TRUE, *FALSE), list("tTfF")),
    ("tag:yaml.org,2002:int", _whole(INTEGER, OCTAL, HEXADECIMAL), list("-+0123456789")),
    ("tag:yaml.org,2002:float", _whole(FLOAT, INFINITY, NAN), list("-+.0123456789")),
    # not YAML 1.2: `<<` is recognised only to be refused by name (_key_problems)
    ("tag:yaml.org,2002:merge", _whole("<<"), ["<"]),
]


class _Refused(Exception):
    """Problems of a file, one line each (without the file's name)."""

    def __init__(self, *lines: str):
        super().__init__("\n".join(lines))
        self.lines = list(lines)


class _Loader(yaml.SafeLoader):
    """yaml.safe_load's loader with YAML 1.2 core scalars, refusing duplicate keys and
    bounding aliases."""

    # a table of its own: the SafeLoader every other reader uses keeps YAML 1.1's
    yaml_implicit_resolvers: ClassVar[dict] = {}

    def __init__(self, stream: str):
        super().__init__(stream)
        self.aliases = 0
        self.depth = 0
        self.key_problems: list[str] = []

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_ALIASES:
                line = self.peek_event().start_mark.line + 1
                raise _Refused(f"line {line}: more than {MAX_ALIASES} YAML aliases, expected plain data")
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:
                raise _too_deep(self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None:
            if self.aliases:
                _count_values(node, {})
            self.key_problems = _key_problems(self, node)
        return node

    def construct_yaml_int(self, node) -> int:
        text = self.construct_scalar(node)
        if re.fullmatch(INTEGER, text):
            return int(text, 10)  # `010` is ten, not YAML 1.1's octal eight
        if re.fullmatch(OCTAL, text) or re.fullmatch(HEXADECIMAL, text):
            return int(text, 0)
        raise _tag_error(node, text, "an integer (decimal digits, 0o... or 0x...)")

    def construct_yaml_float(self, node) -> float:
        text = self.construct_scalar(node)
        if re.fullmatch(FLOAT, text):
            return float(text)
        if re.fullmatch(INFINITY, text):
            return -math.inf if text.startswith("-") else math.inf
        if re.fullmatch(NAN, text):
            return math.nan
        raise _tag_error(node, text, "a number such as 2.5, 1e-6, .inf or .nan")

    def construct_yaml_bool(self, node) -> bool:
        text = self.construct_scalar(node)
        if text in TRUE or text in FALSE:
            return text in TRUE
        raise _tag_error(node, text, "true or false")


for _tag, _pattern, _first in CORE_SCALARS:
    _Loader.add_implicit_resolver(_tag, _pattern, _first)
# explicit tags (`!!int 010`) read their value as YAML 1.2 does, too
_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _Loader.construct_yaml_float)
_Loader.add_constructor("tag:yaml.org,2002:bool", _Loader.construct_yaml_bool)


def _tag_error(node, text: str, expected: str) -> yaml.constructor.ConstructorError:
    tag = node.tag.replace("tag:yaml.org,2002:", "!!")  # as the file spells it
    return yaml.constructor.ConstructorError(None, None, f"got {tag} {text!r}, expected {expected}",
                                             node.start_mark)


def _too_deep(mark) -> _Refused:
    return _Refused(f"line {mark.line + 1}: nesting too deep (more than {MAX_DEPTH} levels of lists and "
                    "mappings), expected plain data")


def _count_values(node, memo: dict, depth: int = 1) -> int:
    """Values under `node` with every alias expanded; refuses more than MAX_VALUES, and
    nesting deeper than MAX_DEPTH through aliases (`depth`: the level of `node`)."""
    key = id(node)
    if key in memo:
        if memo[key] is None:
            raise _Refused(f"line {node.start_mark.line + 1}: a recursive YAML alias, expected plain data")
        count, height = memo[key]
        if depth + height - 1 > MAX_DEPTH:
            raise _too_deep(node.start_mark)
        return count
    if depth > MAX_DEPTH:
        raise _too_deep(node.start_mark)
    memo[key] = None
    children = []
    if isinstance(node, yaml.SequenceNode):
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [child for pair in node.value for child in pair]
    count = 1 + sum(_count_values(child, memo, depth + 1) for child in children)
    height = 1 + max((memo[id(child)][1] for child in children), default=0)
    if count > MAX_VALUES:
        raise _Refused(f"line {node.start_mark.line + 1}: YAML aliases expand to more than "
                       f"{MAX_VALUES} values, expected plain data")
    memo[key] = (count, height)
    return count


def _key_problems(loader: _Loader, root) -> list[str]:
    """One line per key given more than once in a mapping, and per merge key `<<`, anywhere
    under `root`, in the order of the file: where it is (repeated), where it was first given,
    and the mapping's path (an aliased mapping is checked once, where its anchor is)."""
    found: list[tuple[tuple[int, int], str]] = []
    seen: set[int] = set()
    pending = [(root, "")]  # depth first, in the order of the file: an anchor before its aliases
    while pending:
        node, path = pending.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        children = []
        if isinstance(node, yaml.SequenceNode):
            children = [(child, f"{path}[{i}]") for i, child in enumerate(node.value)]
        elif isinstance(node, yaml.MappingNode):
            places: dict[Any, list] = {}
            for key_node, value_node in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    found.append(_merge_line(key_node.start_mark, path))
                    children.append((value_node, path))
                    continue
                key = _key(loader, key_node)
                if key is not None:
                    places.setdefault(key, []).append(key_node.start_mark)
                    children.append((value_node, f"{path}.{key}" if path else str(key)))
            found += [_duplicate_line(key, marks, path) for key, marks in places.items() if len(marks) > 1]
        pending += reversed(children)
    return [line for _, line in sorted(found)]


def _merge_line(mark, path: str) -> tuple[tuple[int, int], str]:
    """The line refusing a merge key at `mark` in the mapping at `path`, and where to sort it."""
    inside = f" in {path}" if path else ""
    return (mark.line, mark.column), (
        f"line {mark.line + 1}: merge key '<<'{inside} (YAML 1.1; files are read as YAML 1.2, which has no "
        "merge keys), expected the keys written out in this mapping (an alias such as `material: *phantom` "
        "may still stand for a whole value)")


def _key(loader: _Loader, key_node) -> Any:
    """The key as the mapping will hold it (1, 1.0 and true are one key there), None for a
    key the constructor refuses anyway (a list or a mapping)."""
    if not isinstance(key_node, yaml.ScalarNode):
        return None
    key = loader.construct_object(key_node)
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _duplicate_line(key: Any, marks: list, path: str) -> tuple[tuple[int, int], str]:
    """The line reporting `key` given at `marks` in the mapping at `path`, and where to sort it."""
    first, repeats = marks[0].line + 1, [mark.line + 1 for mark in marks[1:]]
    where = (f"line {repeats[0]}" if len(repeats) == 1
             else "lines " + ", ".join(map(str, repeats[:-1])) + f" and {repeats[-1]}")
    inside = f" in {path}" if path else ""
    line = f"{where}: duplicate key {key!r} (first given at line {first}){inside}, expected each key once"
    return (marks[1].line, marks[1].column), line


def _parse_keys_apart(text: str) -> tuple[Any, list[str]]:
    """The data of one YAML document and the lines refusing its keys (duplicate and merge
    keys, _key_problems), which need not stop it: the data is built as YAML 1.1 would build
    it (the last of a duplicate key, the merged keys followed), so that the file's other
    problems can be listed with them, the ones left once the keys are written out once.
    Raises _Refused or yaml.YAMLError for what stops the reading."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        try:
            return (None if node is None else loader.construct_document(node)), loader.key_problems
        except yaml.YAMLError:
            if loader.key_problems:  # a merge of a scalar (`<<: 5`) cannot be followed: its line says so
                raise _Refused(*loader.key_problems) from None
            raise
    finally:
        loader.dispose()


class YamlFile(NamedTuple):
    data: Any
    text: str
    sha256: str  # of the bytes read, the ones parsed (a pipe cannot be read a second time)
    # lines refusing duplicate and merge keys, naming the file, for the reader to list with the
    # other problems of the data (read_yaml_file's keys_later)
    key_problems: tuple[str, ...] = ()


# the largest input file read: a scenario or a table of markers is kilobytes (a 10 MB scenario
# of comments reads in a second); an endless one (/dev/zero, a pipe that never ends) filled
# the machine's memory until the kernel killed the command without a word
MAX_INPUT_BYTES = 64 * 2**20
INPUT_CHUNK_BYTES = 2**20


def read_input_bytes(path: Path, where: str, expected: str) -> bytes:
    """The bytes of an input file, at most MAX_INPUT_BYTES; OSError as reading raises it, an
    InputError naming `where` for a file larger than that (`expected`: what was wanted)."""
    chunks, size = [], 0
    with path.open("rb") as handle:  # in pieces: one read of the cap would take its memory at once
        while size <= MAX_INPUT_BYTES and (chunk := handle.read(INPUT_CHUNK_BYTES)):
            chunks.append(chunk)
            size += len(chunk)
    content = b"".join(chunks)
    if len(content) > MAX_INPUT_BYTES:
        cap = MAX_INPUT_BYTES
        size = f"{cap // 2**20} MB" if cap % 2**20 == 0 else f"{cap} bytes"
        raise InputError(f"{where}: got more than {size}, expected {expected}")
    return content


def read_yaml_file(path: str | Path, keys_later: bool = False) -> YamlFile:
    """The data, text and SHA-256 of a YAML file, read once; every problem is an InputError
    naming the file. With `keys_later` duplicate and merge keys are not raised but returned
    in `key_problems`, for the reader to list with the problems of the data (with_key_problems)."""
    path = Path(path)
    try:
        content = read_input_bytes(path, str(path), "a YAML text file")
    except OSError as error:
        raise input_error([f"{path}: cannot be read ({error.strerror or error})"]) from None
    try:
        text = content.decode("utf-8")  # a spreadsheet's BOM kept: the text is the bytes sha256 hashes
    except UnicodeDecodeError as error:
        byte = f"0x{content[error.start]:02x}"
        line = f"{path}: not UTF-8 text (byte {byte} at offset {error.start}), expected a YAML text file"
        raise input_error([line]) from None
    try:
        data, problems = _parse_keys_apart(text.removeprefix("\ufeff"))
        if problems and not keys_later:
            raise _Refused(*problems)
    except _Refused as error:
        raise input_error([f"{path}: {line}" for line in error.lines]) from None
    except RecursionError:  # MAX_DEPTH stops the loader first; any deeper recursion ends here too
        raise input_error([f"{path}: nesting too deep, expected plain data"]) from None
    except yaml.reader.ReaderError as error:  # a character YAML refuses anywhere: no mark, a position
        body = text.removeprefix("\ufeff")
        line = body.count("\n", 0, error.position) + 1
        column = error.position - (body.rfind("\n", 0, error.position) + 1) + 1
        raise input_error([f"{path}: line {line}, character {column}: got U+{error.character:04X}, a character "
                           "YAML text may not hold, expected printable characters, tabs and line breaks (inside "
                           "double quotes a control character is written as an escape such as \\x1b)"]) from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(error, "problem", None)
        if problem is not None and "'\\t'" in problem:  # valid YAML 1.2 perhaps, but not for PyYAML's reader
            line = f"line {mark.line + 1}: " if mark is not None else ""
            raise input_error([f"{path}: {line}a tab character where the YAML reader takes spaces only (tabs "
                               "are read inside quoted text alone); expected spaces: replace the tab by "
                               "spaces"]) from None
        if problem is not None and "another document" in problem:  # `---` and more after the first
            raise input_error([f"{path}: a second YAML document{where} (after a `---` line), expected one "
                               "document a file; remove the `---` line and what follows it, or put that in a "
                               "file of its own"]) from None
        raise input_error([f"{path}: not valid YAML{where}" + (f" ({problem})" if problem else "")]) from None
    return YamlFile(data, text, hashlib.sha256(content).hexdigest(), tuple(f"{path}: {line}" for line in problems))


def with_key_problems(file: YamlFile, path: str | Path, parse: Callable[[Any], T]) -> T:
    """parse(file.data) for a file read with keys_later, every problem of the file listed at
    once: its key problems first, then parse's InputError lines (each given the file's path)."""
    try:
        result = parse(file.data)
    except InputError as error:
        lines = getattr(error, "lines", None) or [str(error)]
        raise input_error([*file.key_problems, *(f"{path}: {line}" for line in lines)]) from None
    if file.key_problems:
        raise input_error(list(file.key_problems))
    return result


def read_yaml(path: str | Path) -> tuple[Any, str]:
    """The data and the text of a YAML file; every problem is an InputError naming the file."""
    file = read_yaml_file(path)
    return file.data, file.text
