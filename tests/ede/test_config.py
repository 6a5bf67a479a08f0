"""The params model: the committed file, the paper's values, and what a bad file is told."""

from __future__ import annotations

import codecs
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from ede import config
from ede.config import Params, ParamsError, checks, load_params, overridden, read_yaml
from ede_pipeline.cli import main
from tests.support import HOSTILE_NAMES, REPO


def test_committed_params_hold_the_papers_configuration() -> None:
    params = load_params(REPO / "params.yaml")
    assert params.embedding.k == 4
    assert params.embedding.beta == params.decoder.lam == 1e-4
    assert params.embedding.dim is None  # the action size, as in the paper
    assert params.collect.steps == 100_000
    assert params.runs.seeds == list(range(8))
    assert params.runs.budgets == {
        "ede/ReacherVertical-v0": 50_000,
        "ede/ReacherTurn-v0": 1_000_000,
        "ede/ReacherPush-v0": 2_000_000,
        "ede/Pusher-v0": 2_000_000,
        "ede/Striker-v0": 4_000_000,
    }
    td3 = params.td3
    assert (td3.hidden, td3.batch_size, td3.lr, td3.discount, td3.tau) == (
        [400, 300],
        100,
        1e-3,
        0.99,
        0.005,
    )
    assert (td3.policy_noise, td3.noise_clip, td3.policy_delay, td3.exploration_noise) == (
        0.2,
        0.5,
        2,
        0.1,
    )
    assert params.families["sevendof"].source == "ede/Pusher-v0"
    assert params.runs.tasks["ede/Striker-v0"] == "sevendof"


def test_committed_params_spell_out_every_default() -> None:
    """The file, not the code, shows the numbers: no section may lean on a hidden default."""
    params = load_params(REPO / "params.yaml")
    for name in Params.model_fields:
        section = getattr(params, name)
        if hasattr(section, "model_fields_set"):
            assert section.model_fields_set == set(type(section).model_fields), name


def test_defaults_in_the_model_match_the_committed_file() -> None:
    params = load_params(REPO / "params.yaml")
    for name in ("collect", "embedding", "decoder", "td3", "ede_td3", "report"):
        section = getattr(params, name)
        assert section == type(section)(), f"{name}: params.yaml and ede/config.py disagree"


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda p: p.update(surprise=1), "surprise: unknown key"),
        (lambda p: p["td3"].update(batch_size="many"), "td3.batch_size: got 'many'"),
        (
            lambda p: p["runs"]["budgets"].update({"ede/Pusher-v0": -5}),
            "runs.budgets.ede/Pusher-v0: got -5",
        ),
        (lambda p: p["embedding"].update(k=0), "embedding.k: got 0"),
        (lambda p: p["report"].update(bin_steps=0), "report.bin_steps: got 0"),
        (lambda p: p["td3"].update(start_steps=-1), "td3.start_steps: got -1"),
        (lambda p: p["td3"].update(eval_every=0), "td3.eval_every: got 0"),
        (
            lambda p: p["runs"]["tasks"].update({"ede/Nope-v0": "reacher"}),
            "runs.tasks.ede/Nope-v0: got 'ede/Nope-v0'",
        ),
        (
            lambda p: p["runs"]["tasks"].update({"ede/Pusher-v0": "reacher"}),
            "runs.tasks.ede/Pusher-v0: not a task of the reacher family",
        ),
        (
            lambda p: p["runs"]["tasks"].update({"ede/Pusher-v0": "moon"}),
            "runs.tasks.ede/Pusher-v0: got 'moon'; expected a family of `families`",
        ),
        (
            lambda p: p["runs"].update(tasks={"reacher": ["ede/ReacherVertical-v0"]}),
            "runs.tasks: expected each task mapped to its family",
        ),
        (lambda p: p["families"]["reacher"].pop("source"), "families.reacher.source: missing"),
        (
            lambda p: p["families"]["point"].update(source="CartPole-v1"),
            "families.point.source: got 'CartPole-v1'; not usable: its actions are Discrete(2)",
        ),
        (lambda p: p["td3"].update(discount=1.5), "td3.discount: got 1.5"),
        (
            lambda p: p["collect"].update(saturated_episodes=1.5),
            "collect.saturated_episodes: got 1.5",
        ),
        (lambda p: p["runs"]["budgets"].pop("ede/Striker-v0"), "no budget for ede/Striker-v0"),
        (
            lambda p: p["families"].pop("sevendof"),
            "runs.tasks.ede/Pusher-v0: got 'sevendof'; expected a family of `families`",
        ),
        (lambda p: p["runs"].update(seeds=[0, 0]), "runs.seeds: [0, 0] repeats a seed"),
        (lambda p: p["decoder"].update(z_source="posterior"), "decoder.z_source: got 'posterior'"),
        (lambda p: p["td3"].update(noise_units="percent"), "td3.noise_units: got 'percent'"),
        (lambda p: p["td3"].update(critic_action_repeat=0), "td3.critic_action_repeat: got 0"),
        (
            lambda p: p["td3"].update(critic_action_repeat=2**63),
            f"td3.critic_action_repeat: got {2**63}; expected at most {2**63 - 1}",
        ),
        (  # torch.set_num_threads takes a C int: past it, a traceback in the stage
            lambda p: p["td3"].update(threads=2**31),
            "td3.threads: got 2147483648; expected less than or equal to 1024",
        ),
        (
            lambda p: p["td3"].update(critic_action_repeat="twice"),
            "td3.critic_action_repeat: got 'twice'",
        ),
        (
            lambda p: p["ede_td3"].update(target_noise_clip="none"),
            "ede_td3.target_noise_clip: got 'none'",
        ),
        (
            lambda p: p["ede_td3"].update(plan_step_input="binary"),
            "ede_td3.plan_step_input: got 'binary'",
        ),
        (lambda p: p["td3"].update(update_schedule="batch"), "td3.update_schedule: got 'batch'"),
        # Keys valid one by one that together leave a stage nothing to do.
        (
            lambda p: p["runs"]["budgets"].update({"ede/Pusher-v0": 102}),
            "runs.budgets.ede/Pusher-v0: got 102; expected at least 103 = max(td3.start_steps 0, "
            "td3.batch_size 100 + embedding.k 4 - 1 (ede-td3's k-step samples)), the step of the "
            "first update: the run would never update",
        ),
        (
            lambda p: (
                p["runs"]["budgets"].update({"ede/Pusher-v0": 4_999}),
                p["td3"].update(start_steps=5_000),
            ),
            "runs.budgets.ede/Pusher-v0: got 4999; expected at least 5000 = max(td3.start_steps 5000",
        ),
        (
            lambda p: (
                p["runs"]["budgets"].update({"ede/Pusher-v0": 99}),
                p["runs"].update(algos=["td3"]),
            ),
            "runs.budgets.ede/Pusher-v0: got 99; expected at least 100 = max(td3.start_steps 0, "
            "td3.batch_size 100), the step",
        ),
        (
            lambda p: p["runs"]["budgets"].update({"ede/ReacherVertical-v0": 999}),
            "runs.budgets.ede/ReacherVertical-v0: got 999; expected at least td3.eval_every (1000): "
            "the run would have only its initial and final evaluations",
        ),
        (
            lambda p: p["td3"].update(buffer_size=102),
            "td3.buffer_size: got 102; expected at least 103 = td3.batch_size 100 + embedding.k 4 "
            "- 1 (ede-td3's k-step samples): no batch could ever be sampled",
        ),
        (
            lambda p: (p["td3"].update(buffer_size=99), p["runs"].update(algos=["td3"])),
            "td3.buffer_size: got 99; expected at least 100 = td3.batch_size 100: no batch",
        ),
        (
            lambda p: p["embedding"].update(batch_size=90_001),
            "embedding.batch_size: got 90001; expected at most 90000 = collect.steps 100000 × "
            "(1 - embedding.holdout 0.1) / embedding.window_stride 1, the most training windows",
        ),
        (
            lambda p: p["embedding"].update(window_stride=1_000),
            "embedding.batch_size: got 128; expected at most 90 = collect.steps 100000 × "
            "(1 - embedding.holdout 0.1) / embedding.window_stride 1000",
        ),
        (
            lambda p: p["decoder"].update(batch_size=90_001),
            "decoder.batch_size: got 90001; expected at most 90000 = collect.steps 100000 × "
            "(1 - embedding.holdout 0.1), the most",
        ),
        # Rollouts are whole episodes, at least one per sub-environment (every source: 100 steps).
        (
            lambda p: p["collect"].update(steps=2_000, num_envs=2_000),
            "collect.num_envs: got 2000; expected at most 20 = collect.steps 2000 // 100, the episode "
            "length of ede/ReacherVertical-v0 (families.reacher.source): each sub-environment records "
            "whole episodes, at least one, so 2000 of them would record about 200000 steps, not 2000",
        ),
        (
            lambda p: p["collect"].update(steps=299, num_envs=3),
            "collect.num_envs: got 3; expected at most 2 = collect.steps 299 // 100",
        ),
        (
            lambda p: p["collect"].update(steps=99),
            "collect.steps: got 99; expected at least 100, the episode length of "
            "ede/ReacherVertical-v0 (families.reacher.source): collect records whole episodes, at "
            "least one per sub-environment, so it would record about 100 steps, not 99",
        ),
        (
            lambda p: p["collect"].update(steps=4, num_envs=5),
            "collect.steps: got 4; expected at least 100",
        ),
        (
            lambda p: (p["collect"].update(steps=150), p["embedding"].update(k=151)),
            "collect.steps: got 150; expected at least embedding.k (151): no window of k actions",
        ),
        # The longest source bounds the sub-environments (Pendulum-v1: 200 steps).
        (
            lambda p: (
                p["families"].update(pendulum={"source": "Pendulum-v1"}),
                p["collect"].update(num_envs=501),
            ),
            "collect.num_envs: got 501; expected at most 500 = collect.steps 100000 // 200, the "
            "episode length of Pendulum-v1 (families.pendulum.source)",
        ),
        # Each task of a family once.
        (
            lambda p: p["families"]["point"].update(targets=["ede/Point-v0"]),
            "families.point.targets: ede/Point-v0 given twice in the family (its source counts); "
            "expected each task once",
        ),
        (
            lambda p: p["families"]["reacher"].update(
                targets=["ede/ReacherTurn-v0", "ede/ReacherPush-v0", "ede/ReacherTurn-v0"]
            ),
            "families.reacher.targets: ede/ReacherTurn-v0 given twice in the family",
        ),
        (lambda p: p["runs"].update(algos=[]), "runs.algos: got []"),
        (
            lambda p: p["runs"].update(algos=["td3", "ppo"]),
            "runs.algos.1: got 'ppo'; expected 'td3', 'ede-td3', 'sb3-td3-ede', 'sb3-sac-ede' or "
            "'sb3-sac'",
        ),
        (  # stable-baselines3's agents in the EDE space store one transition a code
            lambda p: (
                p["runs"]["budgets"].update({"ede/Pusher-v0": 399}),
                p["runs"].update(algos=["td3", "sb3-sac-ede"]),
            ),
            "runs.budgets.ede/Pusher-v0: got 399; expected at least 400 = td3.batch_size 100 × "
            "embedding.k 4: sb3-sac-ede store one transition a code and would never update",
        ),
        (
            lambda p: p["runs"].update(algos=["td3", "td3"]),
            "runs.algos: ['td3', 'td3'] repeats an algorithm",
        ),
        (
            lambda p: p["runs"].update(tasks={}),
            "runs.tasks: got {}; Dictionary should have at least 1",
        ),
        (
            lambda p: p["families"]["sevendof"].update(
                targets=["ede/Striker-v0", "ede/ReacherTurn-v0"]
            ),
            "families.sevendof.targets: ede/ReacherTurn-v0's actions are not ede/Pusher-v0's",
        ),
        # Numbers that are not finite mean nothing a parameter can (and are not valid JSON).
        (
            lambda p: p["td3"].update(noise_clip=float("inf")),
            "td3.noise_clip: got inf; expected a finite number",
        ),
        (lambda p: p["td3"].update(lr=float("nan")), "td3.lr: got nan; expected a finite number"),
        (lambda p: p["embedding"].update(beta=float("inf")), "embedding.beta: got inf"),
        (lambda p: p["decoder"].update(lam=float("nan")), "decoder.lam: got nan"),
        (lambda p: p["ede_td3"].update(bound_scale=float("inf")), "ede_td3.bound_scale: got inf"),
        (
            lambda p: p["report"]["thresholds"].update({"ede/Pusher-v0": float("-inf")}),
            "report.thresholds.ede/Pusher-v0.0: got -inf; expected a finite number",
        ),
    ],
)
def test_a_bad_file_names_the_key_and_value(write_params, edit, key: str) -> None:
    path = write_params(edit)
    with pytest.raises(ParamsError) as caught:
        load_params(path)
    assert any(key in problem for problem in caught.value.problems), caught.value.problems
    assert all(str(path) in line for line in str(caught.value).splitlines())


@pytest.mark.parametrize(
    "edit",
    [
        lambda p: p["collect"].update(steps=2_000, num_envs=20),  # 100 steps each: one episode
        lambda p: p["collect"].update(steps=299, num_envs=2),
        lambda p: (
            p["families"].update(pendulum={"source": "Pendulum-v1"}),
            p["collect"].update(num_envs=500),
        ),
        lambda p: p["runs"].update(
            algos=["td3", "ede-td3", "sb3-td3-ede", "sb3-sac-ede", "sb3-sac"]
        ),
        lambda p: (  # the fewest steps whose codes fill a batch
            p["runs"]["budgets"].update({"ede/Pusher-v0": 1_000}),
            p["td3"].update(batch_size=250),
            p["runs"].update(algos=["sb3-td3-ede"]),
        ),
    ],
)
def test_numbers_that_just_fit_the_episodes_are_fine(write_params, edit) -> None:
    load_params(write_params(edit))


def test_sources_without_a_time_limit_bound_sub_environments_by_steps(
    write_params, monkeypatch
) -> None:
    """No episode length to hold: a sub-environment needs a step, the rollouts a window."""
    monkeypatch.setattr(checks, "episode_length", lambda task: None)
    load_params(write_params(lambda p: p["collect"].update(steps=200, num_envs=200)))
    with pytest.raises(ParamsError) as caught:
        load_params(write_params(lambda p: p["collect"].update(steps=3, num_envs=5)))
    assert caught.value.problems[:2] == [
        "collect.steps: got 3; expected at least embedding.k (4): no window of k actions fits in "
        "the rollouts",
        "collect.num_envs: got 5; expected at most collect.steps (3): each sub-environment "
        "records an equal share of the steps, so some would record none",
    ]


@pytest.mark.parametrize("key", ["ede/Nope-v0", "ReacherVertical-v0"])
def test_a_budget_of_no_registered_task_is_refused_by_name(write_params, key: str) -> None:
    """A budgets key is a task id as runs.tasks' are (a typo is caught); the budgets of registered
    tasks that no run trains stay, so an experiment training fewer tasks keeps params.yaml's."""
    path = write_params(lambda p: p["runs"]["budgets"].update({key: 1000}))
    with pytest.raises(ParamsError) as caught:
        load_params(path)
    assert caught.value.problems == [
        f"runs.budgets.{key}: got '{key}'; expected a registered gymnasium task id "
        "(see `ede-pipeline envs`)"
    ]
    narrowed = write_params(lambda p: p["runs"]["tasks"].pop("ede/Pusher-v0"))
    assert "ede/Pusher-v0" in load_params(narrowed).runs.budgets


def test_every_problem_is_reported_not_just_the_first(write_params) -> None:
    def two_problems(p: dict) -> None:
        p["embedding"]["k"] = -1
        p["td3"]["tau"] = 0

    with pytest.raises(ParamsError) as caught:
        load_params(write_params(two_problems))
    assert len(caught.value.problems) == 2


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        # An unclosed bracket is found at the end of the file; the problem names where it opened.
        (
            "collect:\n  steps: 10\nruns:\n  seeds: [0, 1\n",
            "line 4, column 10: not readable YAML: expected ',' or ']', but got '<stream end>' "
            '(while parsing a flow sequence); the line reads: "  seeds: [0, 1"',
        ),
        (
            "td3:\n\tbatch_size: 3\n",
            "line 2, column 1: not readable YAML: found character '\\t' that cannot start any token "
            '(while scanning for the next token); the line reads: "\\tbatch_size: 3"',
        ),
        (
            "td3:\n  batch_size: 3\n   lr: 1\n",
            "line 3, column 6: not readable YAML: mapping values are not allowed here; "
            'the line reads: "   lr: 1"',
        ),
        (
            "td3:\n  lr: 1\n bad: 2\n",
            "line 3, column 2: not readable YAML: expected <block end>, but found "
            "'<block mapping start>' (while parsing a block mapping from line 1, column 1); "
            'the line reads: " bad: 2"',
        ),
        # PyYAML's reader gives a position: the line is counted from it.
        (
            "a: 1\nb: \x07\n",
            "line 2: not readable YAML (unacceptable character #x0007: special characters are not "
            "allowed)",
        ),
        ("- a list\n", "a list, not a mapping; expected a mapping of sections (families, runs, …)"),
        # A key given twice: PyYAML would keep the last, silently.
        (
            "td3:\n  lr: 0.001\n  batch_size: 100\n  lr: 5.0\n",
            "line 4: key 'lr' given twice, on lines 2 and 4; give it once",
        ),
        (
            "td3:\n  lr: 0.001\nembedding:\n  k: 4\ntd3:\n  lr: 5.0\n",
            "line 5: key 'td3' given twice, on lines 1 and 5; give it once",
        ),
        (
            "runs:\n  budgets:\n    ede/Pusher-v0: 10\n    ede/Pusher-v0: 20\n",
            "line 4: key 'ede/Pusher-v0' given twice, on lines 3 and 4; give it once",
        ),
        (
            "families: {a: {source: X}, a: {source: Y}}\n",
            "line 1: key 'a' given twice, on line 1; give it once",
        ),
    ],
)
def test_unparseable_files_are_one_clear_problem(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "params.yaml"
    path.write_text(text)
    with pytest.raises(ParamsError) as caught:
        load_params(path)
    assert caught.value.problems == [expected]
    assert str(caught.value) == f"{path}: {expected}"


def test_the_same_key_in_different_mappings_and_merge_keys_are_fine(tmp_path: Path) -> None:
    path = tmp_path / "x.yaml"
    path.write_text("base: &b {lr: 1, k: 2}\na: {lr: 3}\nb:\n  <<: *b\n  lr: 4\n")
    assert read_yaml(path) == {"base": {"lr": 1, "k": 2}, "a": {"lr": 3}, "b": {"lr": 4, "k": 2}}


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ParamsError, match="no such file"):
        load_params(tmp_path / "absent.yaml")


def _family_named(name: str):
    return lambda p: p["families"].update({name: {"source": "Pendulum-v1"}})


@pytest.mark.parametrize("name", HOSTILE_NAMES, ids=repr)
@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (_family_named, "families."),
        (lambda name: lambda p: p["runs"]["tasks"].update({"ede/Pusher-v0": name}), "runs.tasks."),
        (
            lambda name: lambda p: p["report"].update(effect_space_family=name),
            "report.effect_space_family: ",
        ),
        (lambda name: lambda p: p["runs"]["budgets"].update({name: 1000}), "runs.budgets."),
        (lambda name: lambda p: p["families"]["point"].update(source=name), "families.point."),
        (
            lambda name: lambda p: p["report"]["thresholds"].update({name: -10}),
            "report.thresholds.",
        ),
    ],
    ids=["family", "task's family", "figure's family", "budget's task", "source", "threshold"],
)
def test_a_name_that_is_no_name_is_one_line_naming_its_key(
    write_params, name: str, edit, key: str
) -> None:
    with pytest.raises(ParamsError) as caught:
        load_params(write_params(edit(name)))
    assert len(caught.value.problems) == 1, caught.value.problems
    (problem,) = caught.value.problems
    assert problem.startswith(key), problem
    assert "expected a name" in problem or "expected a task id" in problem or name == "a/b"
    assert "\n" not in str(caught.value) and len(problem) < 400


@pytest.mark.parametrize("name", ["a", "reacher-v5", "half_cheetah", "A1", "x" * 64])
def test_names_of_letters_digits_dashes_and_underscores_are_names(write_params, name) -> None:
    assert name in load_params(write_params(_family_named(name))).families


def test_every_registered_task_id_and_committed_name_is_a_name(committed_params) -> None:
    import gymnasium

    import ede_envs

    ede_envs.register_envs()
    assert [task for task in gymnasium.registry if config.task_id_problem(task)] == []
    experiments = [read_yaml(path) for path in sorted((REPO / "experiments").glob("*.yaml"))]
    families = [*committed_params["families"]]
    families += [name for changes in experiments for name in changes.get("families", {})]
    experiment_names = [path.stem for path in (REPO / "experiments").glob("*.yaml")]
    assert [n for n in families + experiment_names if config.name_problem(n)] == []


def _laughs() -> bytes:
    """Nine aliases of nine aliases of … a list of nine strings: 9**9 strings expanded."""
    text = 'a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n'
    for previous, name in zip("abcdefgh", "bcdefghi", strict=True):
        text += f"{name}: &{name} [{', '.join([f'*{previous}'] * 9)}]\n"
    return text.encode()


# Files no params can be, each with what its one line says (for a params file and an experiment's).
BAD_FILES = {
    "nested 100,000 levels": (
        b"a: " + b"[" * 100_000 + b"]" * 100_000 + b"\n",
        "line 1: nested more than 32 levels deep; params nest 4",
    ),
    "nested in blocks": (
        "".join(" " * i + "k:\n" for i in range(200)).encode(),
        "line 32: nested more than 32 levels deep",
    ),
    "billion laughs": (_laughs(), "line 4: more than 10000 values (each alias, *name, counted"),
    "a long list": (b"a: [" + b"0, " * 20_000 + b"0]\n", "line 1: more than 10000 values"),
    "an integer of 5000 digits": (
        b"collect:\n  steps: " + b"9" * 5000 + b"\n",
        "line 2: an integer of 5000 characters (999999999999…); no parameter takes more than "
        "2**63 - 1 (19 digits)",
    ),
    "UTF-16 with its byte order mark": (
        codecs.BOM_UTF16_LE + "collect:\n  steps: 10\n".encode("utf-16-le"),
        "UTF-16 or UTF-32 text (it starts with their byte order mark); expected UTF-8",
    ),
    "Latin-1": (
        "# Évaluation\ncollect:\n  steps: 10\n".encode("latin-1"),
        "not UTF-8 text (byte 0xc9 on line 1); expected UTF-8: save it as UTF-8",
    ),
    "a NUL byte": (
        b"collect:\n  steps: 10\x00\n",
        "line 2: not readable YAML (unacceptable character #x0000",
    ),
    "empty": (b"", "empty; expected"),
    "comments alone": (b"# nothing yet\n", "empty; expected"),
    "a list": (b"- collect\n- runs\n", "a list, not a mapping; expected"),
    "a scalar": (b"42\n", "an integer, not a mapping; expected"),
    "larger than 256 KiB": (b"#" + b"x" * (1 << 18) + b"\n", "larger than 256 KiB; expected"),
}


@pytest.mark.timeout(60)  # each in seconds, not minutes (PyYAML reads about 100 kB a second)
@pytest.mark.parametrize("as_experiment", [False, True], ids=["params", "experiment"])
@pytest.mark.parametrize(("content", "expected"), BAD_FILES.values(), ids=BAD_FILES)
def test_a_file_no_params_can_be_is_one_line_naming_it(
    tmp_path: Path, committed_params, content: bytes, expected: str, as_experiment: bool
) -> None:
    path = tmp_path / "file.yaml"
    path.write_bytes(content)
    with pytest.raises(ParamsError) as caught:
        if as_experiment:
            overridden(committed_params, path)
        else:
            load_params(path)
    assert len(caught.value.problems) == 1, caught.value.problems
    assert caught.value.problems[0].startswith(expected), caught.value.problems[0]
    assert str(caught.value) == f"{path}: {caught.value.problems[0]}"


@pytest.mark.parametrize(
    "content", [*[c for c, _ in BAD_FILES.values()], None], ids=[*BAD_FILES, "a directory"]
)
def test_validate_says_a_bad_file_in_one_line_exit_2(
    tmp_path: Path, content: bytes | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "params.yaml"
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["validate", "--params", "params.yaml"])
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.splitlines()
    assert line.startswith("Error: params.yaml: "), line


def test_a_directory_where_the_file_goes_is_one_line(tmp_path: Path, committed_params) -> None:
    for read in (load_params, lambda path: overridden(committed_params, path)):
        with pytest.raises(ParamsError) as caught:
            read(tmp_path)
        assert caught.value.problems == ["a directory; expected a YAML file"]


def test_an_experiments_section_that_is_none_is_named(tmp_path: Path, committed_params) -> None:
    path = tmp_path / "experiment.yaml"
    for text, problem in [
        ("td3: 5\n", "td3: an integer, not a mapping; expected its keys"),
        ("tdd3: {lr: 1}\n", "tdd3: not a section of the params (families, collect, embedding,"),
        ('"a\\nb": {}\n', "'a\\nb': not a section of the params"),  # a line break: one line
    ]:
        path.write_text(text)
        with pytest.raises(ParamsError) as caught:
            overridden(committed_params, path)
        assert caught.value.problems[0].startswith(problem), caught.value.problems


def test_an_integer_past_what_a_stage_takes_is_named_by_its_key(write_params) -> None:
    with pytest.raises(ParamsError) as caught:
        load_params(write_params(lambda p: p["td3"].update(buffer_size=2**63)))
    assert caught.value.problems == [
        f"td3.buffer_size: got {2**63}; expected less than or equal to {2**63 - 1}"
    ]


@pytest.mark.parametrize(
    ("edit", "problems"),
    [
        (
            lambda p: p["families"].update(
                {f"f{i}": {"source": "ede/Point-v0"} for i in range(2_000)}
            ),
            ["families: ede/Point-v0 in point, f0, f1 and 1998 more; expected in one family"],
        ),
        (
            lambda p: p["families"]["reacher"].update(targets=["ede/ReacherTurn-v0"] * 5_000),
            [
                "runs.tasks.ede/ReacherPush-v0: not a task of the reacher family "
                "(ede/ReacherVertical-v0, ede/ReacherTurn-v0)",
                "families.reacher.targets: ede/ReacherTurn-v0 given twice in the family (its "
                "source counts); expected each task once",
            ],
        ),
        (
            lambda p: (
                p["families"].update(f0={"source": "Pendulum-v1"}),
                p["families"].update({f"g{i}": {"source": "ede/Point-v0"} for i in range(9)}),
                p["runs"]["tasks"].update({"ede/Pusher-v0": "moon"}),
            ),
            [
                "runs.tasks.ede/Pusher-v0: got 'moon'; expected a family of `families` (reacher, "
                "sevendof, point, pointmass, f0, g0, g1, g2 and 6 more)",
                "families: ede/Point-v0 in point, g0, g1 and 7 more; expected in one family",
            ],
        ),
    ],
    ids=["2,000 families of one source", "5,000 targets", "a family of many"],
)
def test_the_largest_files_are_checked_at_once_each_problem_a_short_line(
    write_params, edit, problems: list[str]
) -> None:
    """The cross-checks are linear in what the file holds (at most 10,000 values): a file of
    thousands of families or targets takes well under a second, and a problem names a few."""
    path = write_params(edit)
    start = time.perf_counter()
    with pytest.raises(ParamsError) as caught:
        load_params(path)
    assert caught.value.problems == problems
    assert time.perf_counter() - start < 10
