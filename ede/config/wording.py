"""How a bad params file is told: :class:`ParamsError`, one line per problem, in YAML's words.

Each problem names the key path (``runs.budgets.ede/Pusher-v0``), the value found and what is
expected; a value is shown short and on one line, a key quoted where it is no plain key, a list of
names cut after a few.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml

from ede.errors import first_line

__all__ = [
    "ParamsError",
    "both",
    "found",
    "key_name",
    "listed",
    "shown",
    "validation_problem",
    "yaml_problem",
]


class ParamsError(ValueError):
    """A params file that cannot be used; ``problems`` holds one line per problem."""

    def __init__(self, path: Path, problems: list[str]) -> None:
        self.path = path
        self.problems = problems
        super().__init__("\n".join(f"{path}: {problem}" for problem in problems))


def validation_problem(error: Any) -> str:
    """One of pydantic's errors (an item of ``ValidationError.errors()``) as a file's problem: the
    key path, the value found and what is expected; a cross-key check's lines as they are."""
    loc = error["loc"][:-1] if error["loc"][-1:] == ("[key]",) else error["loc"]  # a bad key
    where = ".".join(key_name(part) for part in loc) or "(top level)"
    message = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        return f"{where}: unknown key"
    if error["type"] == "missing":
        return f"{where}: missing; this key is required"
    if error["type"] == "value_error" and isinstance(error.get("input"), dict):
        return message  # cross-key checks name their own keys, one line per problem
    if error["type"] in _EXPECTED:  # a value of another type: say which, in YAML's words
        value = error.get("input")
        kind = "" if value is None else f", {_KINDS.get(type(value), 'a ' + type(value).__name__)}"
        return f"{where}: got {shown(value)}{kind}; expected {_EXPECTED[error['type']]}"
    if message.startswith("Input should be "):
        message = "expected " + message.removeprefix("Input should be ")
    elif message.startswith("a registered"):
        message = "expected " + message
    return f"{where}: got {shown(error.get('input'))}; {message}"


# A YAML value's type, and what each of pydantic's errors for a value of another type expects.
_KINDS = {
    bool: "a boolean",
    int: "an integer",
    float: "a number",
    str: "a string",
    list: "a list",
    dict: "a mapping",
}
_EXPECTED = {
    "bool_type": "true or false",
    "int_type": "an integer",
    "float_type": "a number",
    "string_type": "a string",
    "list_type": "a list",
    "dict_type": "a mapping",
    "model_type": "a mapping",
}


def key_name(part: str | int) -> str:
    """A key of a key path as written, or quoted and escaped where it is no plain key (a space, a
    line break, a name too long): a problem stays one line."""
    text = str(part)
    return text if _PLAIN_KEY.fullmatch(text) else shown(text)


_PLAIN_KEY = re.compile(r"[A-Za-z0-9_./-]{1,100}")


def both(names: list[str]) -> str:
    """``both a and b``, ``a, b, c``, or ``a, b, c and 7 more``."""
    return f"both {names[0]} and {names[1]}" if len(names) == 2 else listed(names, most=3)


def listed(names: Iterable[str], most: int = 8) -> str:
    """``a, b, c``, each once; past ``most`` of them, the first ``most`` and how many more (a
    problem stays a line however many families the params hold)."""
    distinct = list(dict.fromkeys(names))
    if len(distinct) <= most:
        return ", ".join(distinct)
    return f"{', '.join(distinct[:most])} and {len(distinct) - most} more"


def found(content: Any) -> str:
    """What a file or section holds instead of the mapping expected, in YAML's words."""
    if content is None or content == {}:
        return "empty"
    return f"{_KINDS.get(type(content), 'a ' + type(content).__name__)}, not a mapping"


def shown(value: Any) -> str:
    """A value as one short line: its repr (JSON's null, true, false), cut at 60 characters."""
    text = json.dumps(value) if value is None or isinstance(value, bool) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def yaml_problem(error: yaml.YAMLError, text: str) -> str:
    """One line: where (1-based, as editors count), what PyYAML says, and the line's text.

    A problem found at the end of the stream (an unclosed bracket or quote) is placed where its
    context began, the line to fix, rather than past the last line.
    """
    if isinstance(error, yaml.reader.ReaderError):  # a character YAML refuses (a NUL byte)
        number = text.count("\n", 0, error.position) + 1
        return f"line {number}: not readable YAML ({first_line(error)})"
    if not (isinstance(error, yaml.MarkedYAMLError) and error.problem_mark and error.problem):
        return f"not readable YAML ({first_line(error)})"
    mark, problem = error.problem_mark, error.problem
    context, context_mark = error.context, error.context_mark
    if context_mark is not None and not text[mark.index :].strip():  # at the end of the stream
        mark = context_mark
    if context and context_mark is not None and context_mark.index != mark.index:
        context += f" from line {context_mark.line + 1}, column {context_mark.column + 1}"
    lines = text.splitlines()
    line = lines[mark.line] if mark.line < len(lines) else ""
    shown = line if len(line) <= 100 else line[:97] + "..."
    return (
        f"line {mark.line + 1}, column {mark.column + 1}: not readable YAML: {problem}"
        + (f" ({context})" if context else "")
        + f"; the line reads: {json.dumps(shown, ensure_ascii=False)}"
    )
