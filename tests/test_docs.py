"""The README and docs/ say only what exists: every relative link and image resolves (anchors
included), and every command a page shows in a shell block names a real `make` target, an
`ede-pipeline` subcommand and its options, or a file of the repository."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import click
import pytest

from ede_pipeline.cli import main
from tests.support import REPO

PAGES = [
    REPO / "README.md",
    *sorted((REPO / "docs").glob("*.md")),
    *sorted((REPO / "docs" / "results").glob("*.md")),  # the results pages
]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
SHELLS = {"bash", "sh", "shell", "console"}
# Commands a page may show that are not ours: their words are theirs to check.
OTHERS = {
    "dvc",
    "git",
    "docker",
    "podman",
    "pip",
    "source",
    "ray",
    "apt-get",
    "cd",
    "export",
    "xargs",
    "aws",
    "mkdir",
    "cat",
    "ls",
    "unset",
    "kill",
    "nvidia-smi",
    "pytest",
}


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(line.lstrip("#")) for line in text.splitlines() if re.match(r"#{1,6} ", line)}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_and_image_resolves(page: Path) -> None:
    broken = []
    for target in LINK.findall(FENCE.sub("", page.read_text())):
        if re.match(r"[a-z]+:", target):
            continue  # a URL: not ours to check offline
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.exists():
            broken.append(f"{target}: no such file")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target}: no heading #{anchor} in {resolved.name}")
    assert broken == []


def make_targets() -> set[str]:
    text = (REPO / "Makefile").read_text()
    return set(re.findall(r"^([a-z][\w-]*):", text, re.M))


def commands(page: Path) -> list[str]:
    """Each command line of the page's shell blocks, continuation lines joined."""
    lines = []
    for language, body in FENCE.findall(page.read_text()):
        if language not in SHELLS:
            continue
        joined = re.sub(r"\\\n\s*", " ", body)
        for line in joined.splitlines():
            line = re.sub(r"(^|\s)#.*$", "", line).strip()  # a trailing comment
            if line:
                lines.append(line)
    return lines


def problems_with(line: str, defined: frozenset[str] = frozenset()) -> list[str]:
    """What is wrong with one command line; ``defined``: shell functions the page defines."""
    if re.match(r"[\w-]+\(\) *\{", line):
        return []  # a shell function's definition: its body runs what the page says elsewhere
    words = shlex.split(line)
    while words and re.fullmatch(r"[A-Z_]+=\S*", words[0]):  # VAR=value before the command
        words = words[1:]
    if not words:
        return []
    first, rest = words[0], words[1:]
    if first.startswith(".venv/"):
        return [
            f"{first}: run it from the activated environment (README: source .venv/bin/activate)"
        ]
    if first in defined:
        return []
    if first == "make":
        return [
            f"make {w}: no such target"
            for w in rest
            if not w.startswith("-") and "=" not in w and w not in make_targets()
        ]
    if first == "ede-pipeline":
        return _pipeline_problems(rest)
    if first == "python":
        script = next((w for w in rest if not w.startswith("-")), "")
        return (
            [] if rest[:1] == ["-m"] or (REPO / script).is_file() else [f"{script}: no such file"]
        )
    if "/" in first:
        return [] if (REPO / first).is_file() else [f"{first}: no such file"]
    return [] if first in OTHERS else [f"{first}: not a command the pages may show"]


def _pipeline_problems(words: list[str]) -> list[str]:
    command: click.Command = main
    path = ["ede-pipeline"]
    context = click.Context(main)
    while isinstance(command, click.Group) and words and not words[0].startswith("-"):
        name, words = words[0], words[1:]
        found = command.get_command(context, name)
        if found is None:
            return [f"{' '.join(path)} {name}: no such subcommand"]
        command, path = found, [*path, name]
    options = {opt for param in command.params for opt in [*param.opts, *param.secondary_opts]}
    options |= {"--help", "-h"}
    if command.context_settings.get("ignore_unknown_options"):  # `experiment run`: to the sweep
        sweep = main.get_command(context, "sweep")
        assert sweep is not None
        options |= {opt for param in sweep.params for opt in [*param.opts, *param.secondary_opts]}
    return [
        f"{' '.join(path)} {w.split('=')[0]}: no such option"
        for w in words
        if w.startswith("-") and w.split("=")[0] not in options and not re.fullmatch(r"-\d.*", w)
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_command_shown_names_something_real(page: Path) -> None:
    lines = commands(page)
    defined = frozenset(m.group(1) for line in lines if (m := re.match(r"([\w-]+)\(\) *\{", line)))
    problems = [f"{line!r}: {p}" for line in lines for p in problems_with(line, defined)]
    assert problems == []


def test_the_checks_catch_what_they_are_for(tmp_path: Path) -> None:
    assert problems_with("make tset") == ["make tset: no such target"]
    assert problems_with("ede-pipeline trian --task x") == [
        "ede-pipeline trian: no such subcommand"
    ]
    assert problems_with("ede-pipeline train --tsak x") == [
        "ede-pipeline train --tsak: no such option"
    ]
    assert problems_with("python benchmarks/nope.py") == ["benchmarks/nope.py: no such file"]
    assert problems_with(".venv/bin/dvc exp show") == [
        ".venv/bin/dvc: run it from the activated environment (README: source .venv/bin/activate)"
    ]
    assert problems_with("MUJOCO_GL=egl make test") == []
    page = tmp_path / "page.md"
    page.write_text("# Title\n\n[ok](#title) [gone](#nowhere) [file](missing.md)\n")
    with pytest.raises(AssertionError, match=r"no heading #nowhere in page\.md"):
        test_every_relative_link_and_image_resolves(page)
