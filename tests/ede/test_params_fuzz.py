"""Whatever a params or experiment file holds, reading it ends in params or in one line per problem
naming the file: never a traceback, never a hang.

Hypothesis generates the files from the committed ``params.yaml``: values of other types, hostile
names, keys deleted and added, random bytes spliced into its text, random experiment files. The
examples are derandomized (the same on every run and machine) and bounded, a deadline on each.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ede.config import Params, ParamsError, load_params, overridden
from ede_pipeline.cli import main
from tests.support import HOSTILE_NAMES, REPO

FUZZ = settings(
    max_examples=120,
    deadline=5_000,  # ms an example: reading and validating one takes about 20
    derandomize=True,
    database=None,  # nothing written into the checkout
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

TEXT = (REPO / "params.yaml").read_text()
COMMITTED: dict[str, Any] = yaml.safe_load(TEXT)

names = st.sampled_from(HOSTILE_NAMES) | st.text(max_size=12)
scalars = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=2**62, max_value=2**80)
    | st.floats()
    | names
    | st.sampled_from(["ede/Point-v0", "Pendulum-v1", "auto", "td3", "null", "1e-05"])
)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(names, inner, max_size=4),
    max_leaves=8,
)


@st.composite
def mutated_params(draw: st.DrawFn) -> dict[str, Any]:
    """The committed params with one to four keys set to other values, deleted or added, or a
    family renamed."""
    params = copy.deepcopy(COMMITTED)
    for _ in range(draw(st.integers(1, 4))):
        section = draw(st.sampled_from([*params, "families", "runs"]))
        if section not in params or not isinstance(params[section], dict) or not params[section]:
            params[section] = draw(values)
            continue
        mapping = params[section]
        if section in ("families", "runs") and draw(st.booleans()):  # one level deeper
            inner = mapping[draw(st.sampled_from(sorted(mapping)))]
            mapping = inner if isinstance(inner, dict) and inner else mapping
        key = draw(st.sampled_from(sorted(mapping)))
        action = draw(st.sampled_from(["set", "delete", "add", "rename"]))
        if action == "set":
            mapping[key] = draw(values)
        elif action == "delete":
            del mapping[key]
        elif action == "add":
            mapping[draw(names)] = draw(values)
        else:
            mapping[draw(names)] = mapping.pop(key)
    return params


@st.composite
def spliced_text(draw: st.DrawFn) -> bytes:
    """The committed file's bytes with random bytes put in, or some of it cut out."""
    data = TEXT.encode()
    start = draw(st.integers(0, len(data)))
    end = draw(st.integers(start, min(len(data), start + 200)))
    return data[:start] + draw(st.binary(max_size=40)) + data[end:]


experiments = st.dictionaries(
    st.sampled_from([*COMMITTED]) | names,
    st.dictionaries(names | st.sampled_from(["steps", "lr", "seeds", "tasks"]), values, max_size=3)
    | values,
    max_size=3,
)


def one_line_each(error: ParamsError, path: Path) -> None:
    assert error.problems, "a ParamsError names at least one problem"
    assert all(problem and "\n" not in problem for problem in error.problems), error.problems
    assert str(error).splitlines() == [f"{path}: {problem}" for problem in error.problems]


def read(path: Path, content: bytes, as_experiment: bool = False) -> None:
    """Read ``content`` as a params (or experiment) file: params, or one line per problem."""
    path.write_bytes(content)
    try:
        result = overridden(COMMITTED, path)[0] if as_experiment else load_params(path)
    except ParamsError as error:
        one_line_each(error, path)
    else:
        assert isinstance(result, dict if as_experiment else Params)


def dumped(data: Any) -> bytes:
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True).encode()


@pytest.fixture(scope="module")
def path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    load_params(REPO / "params.yaml")  # the tasks' facts cached: no example pays for them
    return tmp_path_factory.mktemp("fuzz") / "params.yaml"


@FUZZ
@given(params=mutated_params())
def test_mutated_params_are_params_or_one_line_each(path: Path, params: dict[str, Any]) -> None:
    read(path, dumped(params))


@FUZZ
@given(content=spliced_text() | st.binary(max_size=300))
def test_random_bytes_are_params_or_one_line_each(path: Path, content: bytes) -> None:
    read(path, content)


@FUZZ
@given(changes=experiments)
def test_experiment_files_apply_or_are_one_line_each(path: Path, changes: dict[str, Any]) -> None:
    read(path, dumped(changes), as_experiment=True)


@settings(FUZZ, max_examples=12)
@given(content=mutated_params().map(dumped) | spliced_text())
def test_validate_ends_in_success_or_exit_2_with_a_line_a_problem(
    path: Path, content: bytes
) -> None:
    path.write_bytes(content)
    result = CliRunner().invoke(main, ["validate", "--params", str(path)])
    assert result.exit_code in (0, 2), result.output
    assert isinstance(result.exception, SystemExit | None), result.exception
    if result.exit_code == 2:
        lines = result.stderr.splitlines()
        assert lines and all(line.startswith(f"Error: {path}: ") for line in lines), lines
