"""The results pages: Markdown an author writes, with blocks ``ede-pipeline results --pages``
fills. A block names a section of the results of one runs folder, by its heading, and holds it:

    <!-- results runs: ede/ReacherTurn-v0 -->
    (the section, as `ede-pipeline results` prints it under its heading)
    <!-- /results -->

``runs`` is the runs folder, relative to the page; the heading is the section's, as printed
after ``### `` (a task's id, ``Across tasks: the reacher family``, ``The tasks at a glance``,
``step: ede/ReacherVertical-v0, TD3``; ``Clip: ede/ReacherPush-v0``, a runs folder's clip where
its policies are published: :mod:`ede_pipeline.results.clips`). Everything outside a block is the author's and is kept
byte for byte; a block's content is the command's and is replaced whole, so that no number of a
page's tables is ever typed.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from ede_pipeline.common import BadInput
from ede_pipeline.results.sections import Section

OPENING = re.compile(r"<!-- results (?P<runs>[^:\s]+): (?P<heading>.+?) -->\n")
CLOSING = "<!-- /results -->\n"


@dataclass(frozen=True)
class Block:
    """A block of a page: where its content lies in the page's text, and what it names."""

    page: Path
    start: int  # the content's first character, after the opening line
    end: int  # the closing line's first character
    runs: Path  # the runs folder, as found from the current directory
    heading: str


@dataclass(frozen=True)
class Pages:
    """The pages read, each with its text, and their blocks in order."""

    texts: dict[Path, str]
    blocks: list[Block]


def read_pages(given: Iterable[Path]) -> Pages:
    """The Markdown pages given (a folder: every ``*.md`` in it, not below) and their blocks,
    each checked: closed before the next opens, and its runs folder there."""
    files = [p for path in given for p in (sorted(path.glob("*.md")) if path.is_dir() else [path])]
    for page in files:
        if page.suffix != ".md":
            raise BadInput(f"--pages {page}: expected a Markdown page (.md) or a folder of them")
    texts, blocks = {}, []
    for page in dict.fromkeys(files):
        texts[page] = text = page.read_text()
        position = 0
        while opening := OPENING.search(text, position):
            line = text.count("\n", 0, opening.start()) + 1
            end = text.find(CLOSING, opening.end())
            if end < 0 or OPENING.search(text, opening.end(), end):
                raise BadInput(
                    f"{page}, line {line}: its block has no {CLOSING.strip()} line before the next "
                    "block or the page's end"
                )
            runs = Path(os.path.normpath(page.parent / opening["runs"]))
            if not runs.is_dir():
                raise BadInput(f"{page}, line {line}: no runs folder {runs}")
            blocks.append(Block(page, opening.end(), end, runs, opening["heading"]))
            position = end + len(CLOSING)
        if CLOSING in text[position:]:
            line = text.count("\n", 0, text.index(CLOSING, position)) + 1
            raise BadInput(f"{page}, line {line}: {CLOSING.strip()} closes no block")
    return Pages(texts, blocks)


def fill_pages(pages: Pages, sections: Mapping[Path, list[Section]]) -> dict[Path, str]:
    """Every block filled with the section it names from its runs folder's ``sections``: the new
    text of each page it changes (once every block has its section)."""
    by_heading = {
        (runs, s.heading): s for runs, found in sections.items() for s in found if s.heading
    }
    for block in pages.blocks:
        if (block.runs, block.heading) not in by_heading:
            line = pages.texts[block.page].count("\n", 0, block.start)
            raise BadInput(
                f"{block.page}, line {line}: {block.runs} has no section {block.heading!r} (its "
                f"sections: {', '.join(repr(s.heading) for s in sections[block.runs] if s.heading)})"
            )
    changed = {}
    for page, text in pages.texts.items():
        filled, position = [], 0
        for block in (b for b in pages.blocks if b.page == page):
            filled += [
                text[position : block.start],
                by_heading[(block.runs, block.heading)].body + "\n",
            ]
            position = block.end
        filled.append(text[position:])
        if (new := "".join(filled)) != text:
            changed[page] = new
    return changed
