#!/usr/bin/env python3
"""Reads requirements.lock, the lock pip-compile writes (`make lock`), for the installs.

Standard library only: it runs before anything is installed (the Makefile's install step, the
Dockerfile's dependency layer), on any Python 3.

    lock.py select LOCK --only NAME...     the lock's entries for NAME... (hashes and all)
    lock.py select LOCK --without NAME...  every other entry: what pip installs with --no-deps
    lock.py version LOCK NAME              NAME's locked version ("2.13.0+cpu")
    lock.py simulator LOCK OUT             write the simulator's pins (SIMULATOR) to OUT

torch is installed by itself before the rest (its build, CPU or CUDA, comes from an index the lock
cannot name), which is what --only and --without are for.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

# What defines the tasks: the physics, the environments' API and the arrays they step in. The
# stages that step an environment depend on these pins (dvc.yaml), not on the whole lock.
SIMULATOR = ("gymnasium", "mujoco", "mujoco-core", "numpy")

SIMULATOR_HEADER = """\
# The simulator's pins, copied from requirements.lock by `make lock` (do not edit). The DVC stages
# that step an environment (collect, train_*, report) depend on this file: a new MuJoCo, gymnasium
# or NumPy reruns them, a new version of anything else in the lock reruns nothing.
"""

_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)")


def normalize(name: str) -> str:
    """PEP 503: ``Foo_Bar.baz`` and ``foo-bar-baz`` are one project."""
    return re.sub(r"[-_.]+", "-", name).lower()


@dataclass(frozen=True)
class Entry:
    name: str  # normalised
    version: str
    text: str  # the entry as written: the pin, its hashes and its "# via" comment
    via: tuple[str, ...]  # who asked for it, as pip-compile names them ("ede (pyproject.toml)")


def read(path: str | Path) -> dict[str, Entry]:
    """The lock's entries by normalised name."""
    entries: dict[str, Entry] = {}
    lines = Path(path).read_text().splitlines()
    i = 0
    while i < len(lines):
        match = _PIN.match(lines[i])
        if not match:
            i += 1
            continue
        block = [lines[i]]
        i += 1
        while i < len(lines) and lines[i][:1].isspace():
            block.append(lines[i])
            i += 1
        via = [line.strip()[1:].strip() for line in block if line.strip().startswith("#")]
        if via and via[0].startswith("via"):
            via[0] = via[0][len("via") :].strip()
        entry = Entry(
            normalize(match[1]), match[2], "\n".join(block) + "\n", tuple(v for v in via if v)
        )
        entries[entry.name] = entry
    return entries


def select(
    entries: dict[str, Entry], only: list[str] | None = None, without: list[str] | None = None
) -> str:
    names = {normalize(n) for n in only or ()} | {normalize(n) for n in without or ()}
    missing = names - entries.keys()
    if missing:
        raise SystemExit(f"lock.py: not in the lock: {', '.join(sorted(missing))}")
    keep = [e for e in entries.values() if (e.name in names) == bool(only)]
    return "# Selected from requirements.lock by scripts/lock.py.\n" + "".join(e.text for e in keep)


def simulator(entries: dict[str, Entry]) -> str:
    pins = [f"{entries[n].name}=={entries[n].version}\n" for n in SIMULATOR if n in entries]
    return SIMULATOR_HEADER + "".join(pins)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    sel = commands.add_parser("select")
    sel.add_argument("lock")
    group = sel.add_mutually_exclusive_group(required=True)
    group.add_argument("--only", nargs="+")
    group.add_argument("--without", nargs="+")
    ver = commands.add_parser("version")
    ver.add_argument("lock")
    ver.add_argument("name")
    sim = commands.add_parser("simulator")
    sim.add_argument("lock")
    sim.add_argument("out")
    args = parser.parse_args(argv)

    entries = read(args.lock)
    if args.command == "select":
        compiled = re.search(r"pip-compile with Python (\d+\.\d+)", Path(args.lock).read_text())
        running = f"{sys.version_info[0]}.{sys.version_info[1]}"
        if compiled and compiled[1] != running:
            print(
                f"lock.py: warning: {args.lock} was compiled for Python {compiled[1]}, this is "
                f"{running}; if the install fails, `make lock` with this Python",
                file=sys.stderr,
            )
        sys.stdout.write(select(entries, args.only, args.without))
    elif args.command == "version":
        name = normalize(args.name)
        if name not in entries:
            raise SystemExit(f"lock.py: {args.name} is not in {args.lock}")
        print(entries[name].version)
    else:
        Path(args.out).write_text(simulator(entries))


if __name__ == "__main__":
    main()
