"""A family's EDE space as a gymnasium environment: any agent acts in codes, the wrapper steps.

:class:`EmbeddedActions` wraps a task so that its actions are the embedding's codes, the box
EDE-TD3's actor acts in; one ``step(code)`` decodes the code into k raw actions and executes them
in order, as EDE-TD3's executor does (:mod:`ede.run.executor`), through the same adapter
(:class:`ede.method.adapters.EmbeddingAdapter`) and so to the same actions, bit for bit. An agent
of stable-baselines3, CleanRL or one's own code learns in it unchanged::

    env = EmbeddedActions.load(gymnasium.make("ede_envs:ede/ReacherVertical-v0"), decoder_dir)
    model = stable_baselines3.SAC("MlpPolicy", env).learn(50_000)

**The semi-Markov form.** A step of the wrapper is a code of n ≤ k environment steps with
rewards r_0 … r_{n-1}. Its reward is their sum, or with ``gamma`` their discounted sum Σ γ^i r_i,
so that ``reward + γ^n V(s')`` is the discounted return from s: an off-policy agent learning the
task's discounted return in the wrapper should discount its own steps by γ^k (its ``gamma``
argument). A code cut short by the episode's end (``info["steps"]`` = n < k) is the one place a
constant γ^k is approximate: after a termination nothing is bootstrapped, so it does not matter;
after a truncation the exact discount of the value beyond it is γ^n, not γ^k.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, SupportsFloat

import gymnasium
import numpy as np
import torch

from ede.method.adapters import EmbeddingAdapter
from ede.method.embedding import ActionEmbedding
from ede.run.artifacts import ArtifactError, load_action_embedding
from ede_envs._actions import check_action

__all__ = ["EmbeddedActions"]


class EmbeddedActions(
    gymnasium.Wrapper[Any, np.ndarray, Any, np.ndarray], gymnasium.utils.RecordConstructorArgs
):
    """A task whose actions are codes of ``embedding``, each executed as k raw actions.

    Action space: ``Box(-b, b, (D,), float32)`` with b = ``embedding.bound`` × ``bound_scale``,
    exactly the box EDE-TD3's actor acts in (``ede_td3.bound_scale`` in params.yaml). Observation
    space, reset and rendering: the task's own.

    ``step(code)``: a code outside the box is clipped into it, as EDE-TD3 clips its own codes
    (:meth:`ede.method.td3.TD3.clip`); a code with a NaN or infinite component is refused with
    a ``ValueError`` before anything steps, as the tasks refuse such actions. The code is decoded
    into k actions (:meth:`EmbeddingAdapter.decode`, the call EDE-TD3's executor makes), which
    are executed in order, stopping at the first step that terminates or truncates the episode.

    Returns the last step's observation, ``terminated`` and ``truncated``; the reward is the sum
    of the steps' rewards, or Σ γ^i r_i with ``gamma`` (the module's docstring says why); and
    the last step's ``info`` with three keys added: ``steps`` (how many raw steps ran, k unless
    the episode ended), ``rewards`` (their rewards, ``(steps,)`` float64) and ``actions`` (the
    raw actions, ``(steps, A)``).

    Args:
        env: the task; its action space must be the Box the embedding decodes into.
        embedding: the family's embedding (:meth:`load` reads one from a decoder folder).
        gamma: discount the steps' rewards inside a code, in (0, 1]; None sums them.
        bound_scale: the code box's half-width in units of the embedding's bound.

    Raises:
        ArtifactError: the embedding decodes into another action box than ``env``'s.
        ValueError: ``gamma`` outside (0, 1], or ``bound_scale`` not positive.
    """

    def __init__(
        self,
        env: gymnasium.Env,
        embedding: ActionEmbedding,
        gamma: float | None = None,
        bound_scale: float = 1.0,
    ) -> None:
        gymnasium.utils.RecordConstructorArgs.__init__(  # so that env.spec can remake it
            self, embedding=embedding, gamma=gamma, bound_scale=bound_scale
        )
        gymnasium.Wrapper.__init__(self, env)
        if gamma is not None and not 0 < gamma <= 1:
            raise ValueError(f"gamma = {gamma}: expected a discount in (0, 1], or None to sum")
        if not bound_scale > 0:
            raise ValueError(f"bound_scale = {bound_scale}: expected a positive number")
        decoder = embedding.decoder
        low, high = decoder.centre - decoder.half_range, decoder.centre + decoder.half_range
        _check_box("the embedding", low.cpu().numpy(), high.cpu().numpy(), env)
        self.embedding, self.gamma = embedding, gamma
        self.adapter = EmbeddingAdapter(embedding, bound_scale)
        self.k = embedding.k
        self.action_space = gymnasium.spaces.Box(
            self.adapter.code_low.cpu().numpy(), self.adapter.code_high.cpu().numpy()
        )

    @classmethod
    def load(
        cls,
        env: gymnasium.Env,
        decoder_dir: str | Path,
        gamma: float | None = None,
        bound_scale: float = 1.0,
        device: torch.device | str = "cpu",
    ) -> EmbeddedActions:
        """``env`` acting through the embedding of a decoder folder: a family's own
        (``data/families/<family>/embedding/decoder``) or a published one
        (``docs/results/clips/ede/<task>/embedding/<id>/decoder``).

        Raises:
            ArtifactError: the folder holds no decoder, a damaged one, or one made for another
                action space than ``env``'s (the line names both).
        """
        meta, embedding = load_action_embedding(None, decoder_dir, device)
        space = meta.action_space
        _check_box(str(decoder_dir), np.asarray(space.low), np.asarray(space.high), env)
        return cls(env, embedding, gamma, bound_scale)

    def step(self, action: np.ndarray) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        check_action(self.env, action)  # refused before anything steps
        adapter = self.adapter
        code = torch.as_tensor(np.asarray(action, dtype=np.float32), device=adapter.code_low.device)
        if code.shape != adapter.code_low.shape:
            raise ValueError(
                f"expected a code of shape {tuple(adapter.code_low.shape)}, got {tuple(code.shape)}"
            )
        code = code.clamp(adapter.code_low, adapter.code_high)  # as TD3.clip
        plan = adapter.decode(code[None]).cpu().numpy()[0]  # (1, D) -> (1, K, A) -> (K, A)
        rewards: list[float] = []
        for action_i in plan:
            obs, reward, terminated, truncated, info = self.env.step(action_i)
            rewards.append(float(reward))
            if terminated or truncated:
                break
        discount = 1.0 if self.gamma is None else self.gamma
        total = sum(discount**i * r for i, r in enumerate(rewards))
        steps = len(rewards)
        info = {**info, "steps": steps, "rewards": np.asarray(rewards), "actions": plan[:steps]}
        return obs, total, bool(terminated), bool(truncated), info


def _check_box(source: str, low: np.ndarray, high: np.ndarray, env: gymnasium.Env) -> None:
    """Refuse an embedding whose actions (``low``, ``high``, from ``source``) are not ``env``'s."""
    space = env.action_space
    task = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
    if not isinstance(space, gymnasium.spaces.Box):
        raise ArtifactError(f"{task} acts in {space}: an embedding decodes into a Box")
    same = (
        low.shape == space.shape
        and np.allclose(low, space.low, rtol=1e-6, atol=1e-6)
        and np.allclose(high, space.high, rtol=1e-6, atol=1e-6)
    )
    if not same:
        raise ArtifactError(
            f"{source}: decodes into actions in [{_show(low)}, {_show(high)}], "
            f"but {task} acts in [{_show(space.low)}, {_show(space.high)}]"
        )


def _show(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:g}" for v in np.asarray(values, dtype=np.float64)) + "]"
