"""Reading a params or experiment file: YAML 1.2, each key given once, within bounds.

PyYAML's safe loader reads YAML 1.1; DVC writes YAML 1.2, whose floats (``1e-05``) the loader here
reads as numbers too. A key given twice, a file too large, nested too deep or holding too many
values (aliases expanded), or an integer too long to be a parameter is refused at once, in one
line naming the file and its line.
"""

from __future__ import annotations

import codecs
import re
from pathlib import Path
from typing import Any

import yaml

from ede.config.wording import ParamsError, shown, yaml_problem
from ede.errors import first_line

__all__ = ["MAX_BYTES", "MAX_DEPTH", "MAX_VALUES", "parse_yaml", "read_yaml"]


# What a params or experiment file may hold, bounded so that reading a bad one ends in a line at
# once (the committed params.yaml: 6 kB, 4 levels deep, about 250 values): its size, read before
# anything is parsed; how deep it nests (PyYAML composes recursively: a file nested 100,000 levels
# would end in a RecursionError); how many values it holds once its aliases are expanded (nine
# aliases of nine aliases of … of a list, "billion laughs", are a few lines that validation would
# walk for hours); and how long an integer is (Python converts no more than 4,300 digits; the
# schema bounds each integer parameter by :data:`MAX_INT`, naming its key).
MAX_BYTES = 1 << 18
MAX_DEPTH = 32
MAX_VALUES = 10_000
_INT_CHARS = 100  # an integer's longest spelling read at all: 2**63 has 19 digits (64 in binary)


class _Refused(yaml.MarkedYAMLError):
    """What the loader refuses in YAML it can read: a key given twice, too deep a nesting, too
    many values, too large an integer."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML keeps the last,
    silently; DVC refuses such a file) and what exceeds the bounds above."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0  # how many nodes the node being composed is inside
        self._values = 0  # how many values composed so far, each alias counted as what it names
        self._sizes: dict[int, int] = {}  # the values of each node counted (_expanded_size)

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        if self._depth == MAX_DEPTH:
            raise _Refused(
                problem=f"nested more than {MAX_DEPTH} levels deep; params nest 4",
                problem_mark=self.peek_event().start_mark,
            )
        alias = self.check_event(yaml.AliasEvent)
        self._depth += 1
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if node is None:
            return node
        self._values += _expanded_size(node, self._sizes) if alias else 1  # children counted
        if self._values > MAX_VALUES:
            raise _Refused(
                problem=f"more than {MAX_VALUES} values (each alias, *name, counted as what it "
                "names); params hold about 250",
                problem_mark=node.start_mark,
            )
        return node

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        spelled = self.construct_scalar(node)
        if len(spelled) > _INT_CHARS:  # checked by key once read; this long, it is not read
            raise _Refused(
                problem=f"an integer of {len(spelled)} characters ({spelled[:12]}…); no "
                f"parameter takes more than 2**63 - 1 (19 digits)",
                problem_mark=node.start_mark,
            )
        return super().construct_yaml_int(node)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        first: dict[Any, yaml.Mark] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                mark = first.setdefault(key, key_node.start_mark)
            except TypeError:  # an unhashable key: the base class says so
                break
            if mark is not key_node.start_mark:
                again = key_node.start_mark.line
                where = (
                    f"on line {again + 1}"
                    if again == mark.line
                    else f"on lines {mark.line + 1} and {again + 1}"
                )
                raise _Refused(
                    problem=f"key {shown(key)} given twice, {where}; give it once",
                    problem_mark=key_node.start_mark,
                )
        return super().construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:int", _UniqueKeyLoader.construct_yaml_int)


def _expanded_size(node: yaml.Node, sizes: dict[int, int]) -> int:
    """How many values ``node`` holds, itself included, each alias counted as what it names
    (``sizes``: those of the nodes counted so far, so that each is counted once)."""
    if id(node) not in sizes:
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            children = [child for pair in node.value for child in pair]
        sizes[id(node)] = 1 + sum(_expanded_size(child, sizes) for child in children)
    return sizes[id(node)]


# Floats of YAML 1.2 that PyYAML (YAML 1.1) reads as strings: an exponent after no dot, or without
# a sign (1e-4, 1.0e4). DVC writes YAML 1.2: `dvc exp run -S embedding.beta=0.00001` leaves
# `beta: 1e-05` in params.yaml.
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"),
)


def read_yaml(path: Path) -> Any:
    """A YAML file's content, each key of a mapping given once, within the bounds above.

    Raises:
        ParamsError: one line saying where the file cannot be read, and why.
    """
    try:
        with path.open("rb") as handle:
            data = handle.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise ParamsError(path, ["no such file"]) from None
    except IsADirectoryError:
        raise ParamsError(path, ["a directory; expected a YAML file"]) from None
    except OSError as error:
        raise ParamsError(path, [f"not readable ({first_line(error)})"]) from None
    if len(data) > MAX_BYTES:
        raise ParamsError(path, [_TOO_LARGE])
    return parse_yaml(_utf8(data, path), path)


_TOO_LARGE = (
    f"larger than {MAX_BYTES >> 10} KiB; expected a file of a few kilobytes, as params.yaml"
)


def _utf8(data: bytes, path: Path) -> str:
    """A file's bytes as UTF-8 text (YAML's and DVC's encoding), or one line saying why not."""
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):  # UTF-32's LE mark too
        problem = "UTF-16 or UTF-32 text (it starts with their byte order mark)"
        raise ParamsError(path, [f"{problem}; expected UTF-8: save it as UTF-8"])
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        problem = f"not UTF-8 text (byte {data[error.start]:#04x} on line {line})"
        raise ParamsError(path, [f"{problem}; expected UTF-8: save it as UTF-8"]) from None


def parse_yaml(text: str, path: Path) -> Any:
    """YAML text's content, each key of a mapping given once, within the bounds above; ``path``
    names it in errors.

    Raises:
        ParamsError: one line saying where the text cannot be read, and why.
    """
    if len(text) > MAX_BYTES:
        raise ParamsError(path, [_TOO_LARGE])
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except _Refused as error:
        where = f"line {error.problem_mark.line + 1}: " if error.problem_mark else ""
        raise ParamsError(path, [f"{where}{error.problem}"]) from None
    except yaml.YAMLError as error:
        raise ParamsError(path, [yaml_problem(error, text)]) from None
