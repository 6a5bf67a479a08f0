"""A trained policy's episodes as frames: what it does, step by step (``ede-pipeline render``).

The policy acts as in its run's evaluations: deterministic μ(s), a code every k steps decoded into
k actions (:class:`ede.run.executor.CodeExecutor`; TD3's code is the action, k = 1), each episode from the
start its run's final evaluation used. Each step's frame is MuJoCo's offscreen rendering
(``render_mode="rgb_array"``: ``MUJOCO_GL=egl`` or ``osmesa`` where there is no display), marked
with the episode, its return so far and, for EDE-TD3, the steps where a code starts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from functools import partial
from typing import Any, NamedTuple

import gymnasium
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from ede.method.adapters import ActionAdapter
from ede.method.td3 import Actor
from ede.run.executor import CodeExecutor
from ede.run.vector import MemberEnvs
from ede.tasks import make

CODE_MARK = (255, 196, 0)  # the bar along a frame's top where a code starts


class Frame(NamedTuple):
    """One environment step, as rendered after it."""

    image: np.ndarray  # (H, W, 3) uint8
    episode: int
    step: int  # of the episode, from 1
    code_start: bool  # a new code was chosen for this step (every step of TD3's)
    ret: float  # the episode's return up to this step


def actor_of(
    meta: Mapping[str, Any], tensors: Mapping[str, torch.Tensor], obs_size: int
) -> Callable[[np.ndarray, np.ndarray], torch.Tensor]:
    """μ of a run's final policy (:func:`ede.run.runs.read_policy`), as :class:`CodeExecutor` calls
    a policy: observations ``(M, O)`` to codes ``(M, C)``."""
    low, high = (torch.tensor(meta[key], dtype=torch.float32) for key in ("code_low", "code_high"))
    actor = Actor(obs_size, low, high, list(meta["hidden"]))
    params = {k.removeprefix("net."): v for k, v in tensors.items() if k.startswith("net.")}

    @torch.no_grad()
    def mu(obs: np.ndarray, _choosing: np.ndarray) -> torch.Tensor:
        return actor(params, torch.as_tensor(obs, dtype=torch.float32))

    return mu


def smaller(task: str, shrink: int) -> dict[str, int]:
    """The size at which ``task`` renders frames ``shrink`` times smaller than its own, where it
    can (MuJoCo's ``width`` and ``height``); ``{}`` where it cannot (its frames are strided)."""
    # Imported here: MuJoCo reads MUJOCO_GL as it is imported, and fails there on a value it does
    # not know; importing this module must leave that to the command's own check of the variable.
    from gymnasium.envs.mujoco import MujocoEnv

    env = make(task, render_mode="rgb_array")
    try:
        mujoco = env.unwrapped
        if shrink == 1 or not isinstance(mujoco, MujocoEnv):
            return {}
        return {"width": mujoco.width // shrink, "height": mujoco.height // shrink}
    finally:
        env.close()


def video_env(task: str, size: dict[str, int]) -> gymnasium.Env:
    """``task`` made to render, at ``size`` (:func:`smaller`) with a shadow map to match: MuJoCo's
    4096² map is most of a software renderer's time (62 ms a 240² frame of Pusher, 28 ms at
    1024², on our 2-core machines)."""
    env = make(task, render_mode="rgb_array", **size)
    if size:
        quality = env.unwrapped.model.vis.quality  # type: ignore[attr-defined]  # a MujocoEnv's
        quality.shadowsize = min(quality.shadowsize, 4 * max(size.values()))
    return env


def play(
    task: str,
    policy: Callable[[np.ndarray, np.ndarray], torch.Tensor],
    adapter: ActionAdapter,
    episodes: int,
    seed: int,
    shrink: int = 1,
) -> Iterator[Frame]:
    """``episodes`` episodes of ``policy`` in ``task``, episode e from ``reset(seed + e)``, one
    frame per step, ``shrink`` times smaller than the task's own frames."""
    size = smaller(task, shrink)
    stride = 1 if size else shrink
    envs = MemberEnvs([partial(video_env, task, size)])
    try:
        executor = CodeExecutor(envs, adapter)
        ret, step, last = 0.0, 0, 0
        for code_step, _, episode in executor.episodes(policy, episodes, [seed], np.ones(1, bool)):
            if int(episode[0]) != last:  # (the executor counts an episode done as it ends)
                ret, step, last = 0.0, 0, int(episode[0])
            ret, step = ret + float(code_step.reward[0]), step + 1
            rendered = envs.vector.render()
            if not rendered:
                raise gymnasium.error.Error(f"{task} rendered no frame")
            image = np.asarray(rendered[0])
            yield Frame(image[::stride, ::stride], last, step, bool(code_step.i[0] == 0), ret)
    finally:
        envs.vector.close()


def annotate(frame: Frame, k: int, label: str) -> np.ndarray:
    """The frame's image with the policy's ``label`` (its algorithm), the episode, step and return
    written in it, and, for a policy of codes (``k`` > 1), a bar along its top at each step where
    a code starts."""
    image = Image.fromarray(frame.image)
    draw = ImageDraw.Draw(image)
    if k > 1 and frame.code_start:
        draw.rectangle((0, 0, image.width - 1, max(3, image.height // 60)), fill=CODE_MARK)
    text = f"episode {frame.episode + 1}  step {frame.step}  return {frame.ret:.1f}"
    if k > 1:
        label += f" (a code every {k} steps)"
    font = ImageFont.load_default(size=max(11, image.height // 32))
    draw.text((6, image.height - 6), text, fill=(255, 255, 255), font=font, anchor="ld")
    draw.text((6, image.height // 40 + 6), label, fill=(255, 255, 255), font=font, anchor="la")
    return np.asarray(image)
