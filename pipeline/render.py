"""``ede-pipeline render``: a trained run's final policy, played and written as a video.

    ede-pipeline render RUN_FOLDER [--episodes 1] [--out FILE.mp4|FILE.gif]
                        [--encoder DIR --decoder DIR] [--params params.yaml]

The run's ``policy/`` (TD3 or EDE-TD3, any task, a task of the user's own included) acts as in its
run's final evaluation, from the same starts (:mod:`ede.video`); each step's frame is MuJoCo's
offscreen rendering (``MUJOCO_GL=egl``, or ``osmesa``), marked with the episode, the step and the
return so far, and for EDE-TD3 with a bar at each step where a code starts. The format follows
``--out``'s suffix: ``.mp4`` (H.264 through the ffmpeg that imageio-ffmpeg's wheel carries, at the
task's frame rate) or ``.gif`` (every other frame, halved where taller than 240 pixels, for pages).
An EDE-TD3 run needs its family's embedding, the one its ``run.json`` names: the decoder published
beside it, where ``ede-pipeline experiment export --policies`` published the run, else the
pipeline's for its task.

Bad input is one line (exit 2): a folder with no policy (a published copy keeps one only where
exported with ``--policies``), a damaged
policy (its SHA-256 not the one ``run.json`` records, or unreadable), an EDE-TD3 run without its
embedding, a task that cannot be made or cannot render; a machine where MuJoCo has no offscreen GL
is one line, exit 1. The video appears whole or not at all.
"""

from __future__ import annotations

import os
from pathlib import Path

import click
import gymnasium
import imageio.v3 as iio
import numpy as np
import torch
from PIL import Image

from ede.artifacts import ArtifactError, load_action_embedding
from ede.atomic import writing_files
from ede.config import ALGO_LABELS, Params
from ede.embedding import ActionEmbedding
from ede.errors import first_line
from ede.runs import RunRejected, read_policy
from ede.tasks import make
from ede.td3 import ActionAdapter, EmbeddingAdapter, IdentityAdapter
from ede.training import EVAL_SEED_OFFSET
from ede.video import actor_of, annotate, play
from ede_pipeline import layout
from ede_pipeline.common import BadInput, Failed, embedding_options, hold_outputs, params_option

VIDEO_KIND = "video"  # what a video's mark says made it (ede.atomic.writing_files)
FORMATS = (".mp4", ".gif")
OFFSCREEN = ("egl", "osmesa")  # MuJoCo's offscreen GL backends; egl where MUJOCO_GL is unset


def embedding_for(
    run: Path, meta: dict, params: Params, encoder: Path | None, decoder: Path | None
) -> ActionEmbedding:
    """The embedding an EDE-TD3 run acts through, which must be the one it trained with: the
    one ``encoder`` and ``decoder`` name; else, for a published run, the decoder published
    beside it (``experiment export --policies``; a policy acts through the decoder alone); else
    its family's in the pipeline's data."""
    task = meta["task"]
    beside = layout.embedding_beside(run, str(meta.get("embedding"))) / layout.DECODER
    if encoder is None and decoder is None and beside.is_dir():
        paths: tuple[Path | None, Path] = (None, beside)
    else:
        family = params.runs.tasks.get(task) or layout.own_family(task, params.families)
        folder = layout.embedding(family)
        paths = (encoder or folder / layout.ENCODER, decoder or folder / layout.DECODER)
    try:
        found, embedding = load_action_embedding(*paths)
    except ArtifactError as error:
        raise BadInput(
            f"{error} (an EDE-TD3 run on {task} acts through its family's embedding)"
        ) from None
    if found.identity != meta.get("embedding"):
        raise BadInput(
            f"{paths[1]}: not the embedding the run trained with (its "
            f"checksum {found.identity[:12]}…, the run's policy.json names "
            f"{str(meta.get('embedding'))[:12]}…); name the run's with --encoder and --decoder"
        )
    return embedding


def adapter_of(meta: dict, embedding: ActionEmbedding | None) -> ActionAdapter:
    """How the policy's codes become actions: as they are (TD3), or decoded by the embedding
    (EDE-TD3), in the code box its run acted in."""
    if embedding is None:
        low, high = np.array(meta["code_low"]), np.array(meta["code_high"])
        return IdentityAdapter(low, high, torch.device("cpu"))
    return EmbeddingAdapter(embedding, meta["params"]["ede_td3"]["bound_scale"])


def frames_of(
    meta: dict, tensors: dict, adapter: ActionAdapter, episodes: int, shrink: int = 1
) -> tuple[list[np.ndarray], list[float]]:
    """The policy's episodes, one marked frame per step (``shrink`` times smaller than the task
    renders it by default), and each episode's return."""
    task = meta["task"]
    try:
        env = make(task, render_mode="rgb_array")
    except (gymnasium.error.Error, ValueError, TypeError) as error:
        raise BadInput(f"{task}: cannot be made to render ({first_line(error)})") from None
    obs_size = int(np.prod(env.observation_space.shape or ()))
    env.close()
    policy = actor_of(meta, tensors, obs_size)
    seed = EVAL_SEED_OFFSET * (int(meta["seed"]) + 1)  # the run's final evaluation's starts
    label = ALGO_LABELS[meta["algo"]]
    frames, returns = [], [0.0] * episodes
    try:
        for frame in play(task, policy, adapter, episodes, seed, shrink):
            frames.append(annotate(frame, adapter.k, label))
            returns[frame.episode] = frame.ret
    except gymnasium.error.Error as error:
        raise BadInput(f"{task}: cannot render ({first_line(error)})") from None
    except Exception as error:  # MuJoCo's renderer without a GL context names only its library
        if "GL" not in str(error) and "GL" not in type(error).__name__:
            raise
        raise Failed(
            f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}: MuJoCo cannot render offscreen here "
            f"({first_line(error)}); install Mesa's EGL or OSMesa libraries (docs/pipeline.md, "
            "'Videos')"
        ) from None
    return frames, returns


def side_by_side(
    runs: list[Path], embedding: tuple[ActionEmbedding, str] | None, episodes: int = 1
) -> tuple[list[np.ndarray], list[float]]:
    """The runs' policies (TD3 and EDE-TD3 of one seed, say) played from the same starts, their
    frames side by side at half size (the shorter episodes hold their last frame), and each
    one's mean return. An EDE-TD3 run's ``embedding`` (with its decoder's identity) must be the
    one it trained with."""
    played, returns = [], []
    for run in runs:
        try:
            meta, tensors = read_policy(run)
        except RunRejected as error:
            raise BadInput(str(error)) from None
        used = None
        if meta["algo"] == "ede-td3":
            if embedding is None or embedding[1] != meta.get("embedding"):
                raise BadInput(f"{run}: its family's embedding is not the one it trained with")
            used = embedding[0]
        frames, each = frames_of(meta, tensors, adapter_of(meta, used), episodes, shrink=2)
        played.append(frames)
        returns.append(float(np.mean(each)))
    length = max(len(frames) for frames in played)
    held = [frames + frames[-1:] * (length - len(frames)) for frames in played]
    return [np.concatenate(row, axis=1) for row in zip(*held, strict=True)], returns


# A GIF's frames are halved where taller than this: a run's own 480-pixel frames are; TD3 beside
# EDE-TD3 (:func:`side_by_side`) is already half size, and its labels would not read halved again.
GIF_HEIGHT = 240


def encode(frames: list[np.ndarray], fps: float, suffix: str, to: Path) -> None:
    """``frames`` into the file ``to`` as ``suffix`` says: H.264 MP4, or a GIF of every other
    frame (a page's clip, small), halved where taller than :data:`GIF_HEIGHT`."""
    if suffix == ".mp4":
        iio.imwrite(
            to, np.stack(frames), plugin="FFMPEG", fps=fps, codec="libx264", extension=suffix
        )
        return
    step = 2 if frames[0].shape[0] > GIF_HEIGHT else 1
    small = [f[::step, ::step] for f in frames[::2]]
    # One palette of 256 colours for the whole clip, drawn from all its frames, and no dithering:
    # Pillow's default (a palette per frame, dithered) scatters noise that compresses badly.
    # Measured on the results pages' clips (2026-12-06): Striker's 1.30 MB then, 0.29 now;
    # ReacherTurn's 0.50 and 0.24; Pusher's 0.30 and 0.10; the frames alike to the eye.
    palette = Image.fromarray(np.concatenate(small)).quantize(256)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in small]
    images[0].save(
        to, format="GIF", save_all=True, append_images=images[1:], duration=2000 / fps, loop=0
    )


def fps_of(task: str) -> float:
    """The task's own frame rate (its simulator's time step), as gymnasium renders it."""
    env = make(task)
    try:
        return float(env.metadata.get("render_fps") or 30)
    finally:
        env.close()


def write_video(out: Path, frames: list[np.ndarray], fps: float) -> None:
    """``frames`` as ``out``, in the format of its suffix, whole or not at all."""
    tmp = out.with_name(f".{out.stem}.tmp-{os.getpid()}{out.suffix}")
    with writing_files([(out, VIDEO_KIND)]):
        try:
            encode(frames, fps, out.suffix, tmp)
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)


@click.command()
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--episodes",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Episodes to play, one after another.",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    help="The video, .mp4 or .gif  [default: data/videos/<task>/<algo>/seed<N>.mp4]",
)
@embedding_options
@params_option
def render(
    params: Params,
    run: Path,
    episodes: int,
    out: Path | None,
    encoder: Path | None,
    decoder: Path | None,
) -> None:
    """Play a run's final policy for a few episodes and write them as a video (MP4 or GIF)."""
    gl = os.environ.setdefault("MUJOCO_GL", "egl")  # read as the first environment renders
    if gl not in OFFSCREEN:
        raise Failed(f"MUJOCO_GL={gl}: videos render offscreen, with {' or '.join(OFFSCREEN)}")

    def check_out(out: Path) -> None:
        if out.suffix not in FORMATS:
            raise BadInput(f"--out {out}: expected a file ending in {' or '.join(FORMATS)}")
        hold_outputs((None, VIDEO_KIND), files=((out, VIDEO_KIND),), inputs=(run,))

    if out is not None:  # checked before anything is read
        check_out(out)
    try:
        meta, tensors = read_policy(run)
    except RunRejected as error:
        raise BadInput(str(error)) from None
    task, algo, seed = meta["task"], meta["algo"], int(meta["seed"])
    if out is None:
        out = layout.video(task, algo, seed)
        if not Path(os.path.normpath(out)).is_relative_to(layout.VIDEOS):  # names from the run
            raise BadInput(
                f"{run}: its policy's task {task!r} and algo {algo!r} put the video at {out}, "
                f"outside {layout.VIDEOS}; expected names of a task and an algorithm, or --out"
            )
        check_out(out)
    embedding = embedding_for(run, meta, params, encoder, decoder) if algo == "ede-td3" else None
    frames, returns = frames_of(meta, tensors, adapter_of(meta, embedding), episodes)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_video(out, frames, fps_of(task))
    click.echo(
        f"{out}: {len(frames)} frames, {task} {algo} seed {seed}; returns "
        + ", ".join(f"{r:.4f}" for r in returns)
        + f" (mean {np.mean(returns):.4f})"
    )
