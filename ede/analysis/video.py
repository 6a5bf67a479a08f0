"""A trained policy's episodes as frames: what it does, step by step (``ede-pipeline render``).

The policy acts as in its run's evaluations: deterministic μ(s), a code every k steps decoded into
k actions (:class:`ede.run.executor.CodeExecutor`; TD3's code is the action, k = 1), each episode from the
start its run's final evaluation used. Each step's frame is MuJoCo's offscreen rendering
(``render_mode="rgb_array"``: ``MUJOCO_GL=egl`` or ``osmesa`` where there is no display), marked
with the episode, its return so far and, for EDE-TD3, the steps where a code starts.

Below them, the rest of the video code, which ``ede-pipeline render``, the report's clips and the
results pages' clips share: a run's policy (checked against its run: :mod:`ede.analysis.policy`)
played into frames (:func:`frames_of`, :func:`side_by_side`) and encoded (:func:`write_video`,
:func:`video_bytes`).
"""

from __future__ import annotations

import errno
import os
import resource
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from functools import partial
from itertools import zip_longest
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium
import imageio.v2 as imageio
import imageio_ffmpeg
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from ede.analysis.policy import PolicyRejected, adapter_of, observation_size, policy_of
from ede.config import ALGO_LABELS
from ede.errors import first_line
from ede.io.atomic import NotWritten, writing_files
from ede.method.adapters import ActionAdapter
from ede.method.embedding import ActionEmbedding
from ede.method.td3 import Actor
from ede.run.evaluation import EVAL_SEED_OFFSET
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
    """``task`` made to render, at ``size`` (:func:`smaller`; ``{}``: its own) with a shadow map to
    match its frames, 4 texels a pixel along their longer side: MuJoCo's default 4096² map is most
    of a software renderer's time (61 ms a 480² frame of Point, 30 ms with a 1920² map; 62 ms a
    240² frame of Pusher, 28 ms at 1024², on our 2-core machines)."""
    from gymnasium.envs.mujoco import MujocoEnv  # as in :func:`smaller`

    env = make(task, render_mode="rgb_array", **size)
    mujoco = env.unwrapped
    if isinstance(mujoco, MujocoEnv):
        quality = mujoco.model.vis.quality
        quality.shadowsize = min(quality.shadowsize, 4 * max(mujoco.width, mujoco.height))
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


# What follows plays a run's final policy (``policy/``, :func:`ede.run.runs.read_policy`) into frames
# and encodes them: the library of ``ede-pipeline render``, the report's clips and the results
# pages' clips. Its refusals are :class:`PolicyRejected` (the commands' bad input) and
# :class:`NoOffscreenGL` (a failure of the machine); a video that cannot be written whole is
# :class:`ede.io.atomic.NotWritten`.


class NoOffscreenGL(RuntimeError):
    """MuJoCo cannot render offscreen on this machine: one line naming ``MUJOCO_GL`` and what
    to install."""


VIDEO_KIND = "video"  # what a video's mark says made it (ede.io.atomic.writing_files)
FORMATS = (".mp4", ".gif")

# The most frames one video holds. An MP4's frames go to the encoder as they are made, so its
# length costs time, not memory: 100 episodes of our tasks' 100 steps (ten times the final
# evaluation's 10 episodes; 3.3 to 8.3 minutes at their 50 or 20 frames a second). Measured
# (2026-12-07, ede/Point-v0 at 480², on a 2-core machine shared by six test runs): 70 ms a frame,
# rendered, marked and encoded, so about 12 minutes for the lot, and a peak RSS of 480 MB for 100
# frames and for 600 alike. A GIF keeps what it shows (every other frame, halved to 240²) until
# its palette is drawn from all of them, and Pillow keeps its frames too: 0.6 MB a frame kept
# (670 MB for 600 frames), so it holds ten episodes. ``--episodes`` beyond these is refused
# before any work.
MAX_FRAMES = {".mp4": 10_000, ".gif": 1_000}

# A disk with less room than this is full for a video (ffmpeg writes in blocks of 256 KiB).
FULL = 2**20


def frames_of(
    meta: dict, tensors: dict, adapter: ActionAdapter, episodes: int, shrink: int = 1
) -> tuple[Iterator[np.ndarray], list[float]]:
    """The policy's episodes, one marked frame per step (``shrink`` times smaller than the task
    renders it by default), each made as it is read (none is kept), and each episode's return,
    filled in as the frames are read.

    Raises:
        PolicyRejected: the task cannot be made (here) or cannot render (as the frames are read).
        NoOffscreenGL: MuJoCo has no offscreen GL here (as the frames are read).
    """
    task = meta["task"]
    policy = actor_of(meta, tensors, observation_size(task))
    seed = EVAL_SEED_OFFSET * (int(meta["seed"]) + 1)  # the run's final evaluation's starts
    label = ALGO_LABELS[meta["algo"]]
    returns = [0.0] * episodes

    def frames() -> Iterator[np.ndarray]:
        try:
            for frame in play(task, policy, adapter, episodes, seed, shrink):
                returns[frame.episode] = frame.ret
                yield annotate(frame, adapter.k, label)
        except gymnasium.error.Error as error:
            raise PolicyRejected(f"{task}: cannot render ({first_line(error)})") from None
        except Exception as error:  # MuJoCo's renderer without a GL context names only its library
            if "GL" not in str(error) and "GL" not in type(error).__name__:
                raise
            raise NoOffscreenGL(
                f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}: MuJoCo cannot render offscreen here "
                f"({first_line(error)}); install Mesa's EGL or OSMesa libraries "
                "(docs/pipeline.md, 'Videos')"
            ) from None

    return frames(), returns


def side_by_side(
    runs: list[Path], embedding: tuple[ActionEmbedding, str] | None, episodes: int = 1
) -> tuple[Iterator[np.ndarray], list[float]]:
    """The runs' policies (TD3 and EDE-TD3 of one seed, say) played from the same starts, their
    frames side by side at half size (the shorter episodes hold their last frame), each made as
    it is read, and each one's mean return, filled in once the frames are read. An EDE-TD3 run's
    ``embedding`` (with its decoder's identity) must be the one it trained with."""
    played, each = [], []
    for run in runs:
        meta, tensors = policy_of(run)
        used = None
        if meta["algo"] == "ede-td3":
            if embedding is None or embedding[1] != meta.get("embedding"):
                raise PolicyRejected(
                    f"{run}: its family's embedding is not the one it trained with"
                )
            used = embedding[0]
        frames, returns = frames_of(meta, tensors, adapter_of(meta, used), episodes, shrink=2)
        played.append(frames)
        each.append(returns)
    means: list[float] = []

    def together() -> Iterator[np.ndarray]:
        last: list[np.ndarray] = []
        for row in zip_longest(*played):
            last = [frame if frame is not None else held for frame, held in zip_longest(row, last)]
            yield np.concatenate(last, axis=1)
        means.extend(float(np.mean(returns)) for returns in each)

    return together(), means


# A GIF's frames are halved where taller than this: a run's own 480-pixel frames are; TD3 beside
# EDE-TD3 (:func:`side_by_side`) is already half size, and its labels would not read halved again.
GIF_HEIGHT = 240


def encode(frames: Iterable[np.ndarray], fps: float, suffix: str, to: Path) -> int:
    """``frames`` into the file ``to`` as ``suffix`` says: H.264 MP4, each frame encoded as it
    comes, or a GIF of every other frame (a page's clip, small), halved where taller than
    :data:`GIF_HEIGHT`. Returns the number of frames read."""
    count = 0
    if suffix == ".mp4":
        with imageio.get_writer(to, format="FFMPEG", fps=fps, codec="libx264") as writer:
            for frame in frames:
                writer.append_data(frame)  # type: ignore[attr-defined]  # (FFMPEG's Writer has it)
                count += 1
        # ffmpeg may fail to finish the file (a full disk as it writes the index at the end)
        # and imageio does not say so (it ignores ffmpeg's exit status): count what it holds.
        try:
            held, _ = imageio_ffmpeg.count_frames_and_secs(str(to))
        except RuntimeError as error:
            raise OSError(f"ffmpeg cannot read it back ({first_line(error)})") from None
        if held != count:
            raise OSError(f"it holds {held} of the {count} frames")
        return count
    small: list[np.ndarray] = []  # every other frame, from the first
    for frame in frames:
        if count % 2 == 0:
            step = 2 if frame.shape[0] > GIF_HEIGHT else 1
            small.append(frame[::step, ::step].copy())  # (a view would keep the whole frame)
        count += 1
    # One palette of 256 colours for the whole clip, drawn from all its frames, and no dithering:
    # Pillow's default (a palette per frame, dithered) scatters noise that compresses badly.
    # Measured on the results pages' clips (2026-12-06): Striker's 1.30 MB then, 0.29 now;
    # ReacherTurn's 0.50 and 0.24; Pusher's 0.30 and 0.10; the frames alike to the eye.
    palette = Image.fromarray(np.concatenate(small)).quantize(256)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in small]
    images[0].save(
        to, format="GIF", save_all=True, append_images=images[1:], duration=2000 / fps, loop=0
    )
    return count


def fps_of(task: str) -> float:
    """The task's own frame rate (its simulator's time step), as gymnasium renders it."""
    env = make(task)
    try:
        return float(env.metadata.get("render_fps") or 30)
    finally:
        env.close()


def episode_steps(task: str) -> int | None:
    """The most steps an episode of ``task`` takes (its time limit), None where it has none."""
    env = make(task)
    try:
        return env.spec.max_episode_steps if env.spec else None
    finally:
        env.close()


def write_video(out: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """``frames`` as ``out``, in the format of its suffix, whole or not at all; the number of
    frames written.

    Raises:
        NotWritten: the file could not be written whole (a full disk): nothing of it is left.
    """
    tmp = out.with_name(f".{out.stem}.tmp-{os.getpid()}{out.suffix}")
    with writing_files([(out, VIDEO_KIND)]):
        try:
            count = encode(frames, fps, out.suffix, tmp)
            os.replace(tmp, out)
        except OSError as error:
            raise NotWritten(out, _cause(error, tmp)) from None
        finally:
            tmp.unlink(missing_ok=True)
    return count


def video_bytes(frames: Iterable[np.ndarray], fps: float, name: Path) -> bytes:
    """``frames`` as the bytes of an MP4 (a page's clip, ``name`` on the page), encoded through
    a temporary file.

    Raises:
        NotWritten: the clip could not be encoded whole (a full disk), naming it: a failure of
            the machine, not of the clip (the command stops in one line, exit 1).
    """
    with tempfile.TemporaryDirectory() as scratch:
        clip = Path(scratch) / name.name
        try:
            encode(frames, fps, ".mp4", clip)
        except OSError as error:
            raise NotWritten(name, _cause(error, clip)) from None
        return clip.read_bytes()


def _cause(error: OSError, written: Path) -> OSError:
    """Why a video could not be written, as the system says it: the error itself, or for the
    encoder's (ffmpeg stops where a write fails: imageio says "Broken pipe", or :func:`encode`
    finds the file short), the limit the file ``written`` reached: the process's largest file
    (RLIMIT_FSIZE), or a full disk."""
    if error.errno not in (None, errno.EPIPE):
        return error
    size = written.stat().st_size if written.exists() else 0
    largest = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if largest != resource.RLIM_INFINITY and size >= largest:
        return OSError(errno.EFBIG, os.strerror(errno.EFBIG))
    if shutil.disk_usage(written.parent).free < FULL:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return OSError(errno.EIO, f"the encoder failed: {first_line(error)}")
