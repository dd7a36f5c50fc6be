"""Reading YAML input files: text and data, or one clear line naming the file.

Refused besides syntax errors: text that is not UTF-8, a key given twice in one mapping
(the second would silently win), and aliases beyond a small bound (an "alias bomb" expands a
few lines into billions of values)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from .messages import input_error

MAX_ALIASES = 100  # alias uses per file
MAX_VALUES = 100_000  # values after expanding every alias


class _Refused(Exception):
    pass


class _Loader(yaml.SafeLoader):
    """yaml.safe_load's loader, refusing duplicate keys and bounding aliases."""

    def __init__(self, stream: str):
        super().__init__(stream)
        self.aliases = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_ALIASES:
                line = self.peek_event().start_mark.line + 1
                raise _Refused(f"line {line}: more than {MAX_ALIASES} YAML aliases, expected plain data")
        return super().compose_node(parent, index)

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None and self.aliases:
            _count_values(node, {})
        return node

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            first: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` may override
                    continue
                key, line = self.construct_object(key_node, deep=True), key_node.start_mark.line + 1
                try:
                    if key in first:
                        raise _Refused(f"line {line}: duplicate key {key!r} (first given at line "
                                       f"{first[key]}), expected each key once")
                    first[key] = line
                except TypeError:  # an unhashable key: the constructor reports it
                    continue
        return super().construct_mapping(node, deep)


def _count_values(node, memo: dict) -> int:
    """Values under `node` with every alias expanded; refuses more than MAX_VALUES."""
    key = id(node)
    if key in memo:
        if memo[key] is None:
            raise _Refused(f"line {node.start_mark.line + 1}: a recursive YAML alias, expected plain data")
        return memo[key]
    memo[key] = None
    count = 1
    if isinstance(node, yaml.SequenceNode):
        count += sum(_count_values(child, memo) for child in node.value)
    elif isinstance(node, yaml.MappingNode):
        count += sum(_count_values(k, memo) + _count_values(v, memo)
                     for k, v in node.value)
    if count > MAX_VALUES:
        raise _Refused(f"line {node.start_mark.line + 1}: YAML aliases expand to more than "
                       f"{MAX_VALUES} values, expected plain data")
    memo[key] = count
    return count


def parse_yaml(text: str) -> Any:
    """The data of one YAML document (raises _Refused or yaml.YAMLError)."""
    loader = _Loader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read_yaml(path: str | Path) -> tuple[Any, str]:
    """The data and the text of a YAML file; every problem is an InputError naming the file."""
    path = Path(path)
    try:
        content = path.read_bytes()
    except OSError as error:
        raise input_error([f"{path}: cannot be read ({error.strerror or error})"]) from None
    try:
        text = content.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        byte = f"0x{content[error.start]:02x}"
        line = f"{path}: not UTF-8 text (byte {byte} at offset {error.start}), expected a YAML text file"
        raise input_error([line]) from None
    try:
        return parse_yaml(text), text
    except _Refused as error:
        raise input_error([f"{path}: {error}"]) from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(error, "problem", None)
        raise input_error([f"{path}: not valid YAML{where}" + (f" ({problem})" if problem else "")]) from None
