"""Errors as one line: how every refusal of bad input quotes what a library raised."""

from __future__ import annotations

__all__ = ["first_line"]


def first_line(error: BaseException | str) -> str:
    """The first non-blank line of ``error``'s message (or of a tool's output), or the error's
    type's name when it has none."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__
