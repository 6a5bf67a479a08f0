"""``ede-pipeline render``: a trained run's final policy, played and written as a video.

    ede-pipeline render RUN_FOLDER [--episodes 1] [--out FILE.mp4|FILE.gif]
                        [--encoder DIR --decoder DIR] [--params params.yaml]

The run's ``policy/`` (TD3 or EDE-TD3, any task, a task of the user's own included) acts as in its
run's final evaluation, from the same starts (:mod:`ede.analysis.video`, which holds the rest of the video code); each step's frame is MuJoCo's
offscreen rendering (``MUJOCO_GL=egl``, or ``osmesa``), marked with the episode, the step and the
return so far, and for EDE-TD3 with a bar at each step where a code starts. The format follows
``--out``'s suffix: ``.mp4`` (H.264 through the ffmpeg that imageio-ffmpeg's wheel carries, at the
task's frame rate) or ``.gif`` (every other frame, halved where taller than 240 pixels, for pages).
An EDE-TD3 run needs its family's embedding, the one its ``run.json`` names: the decoder published
beside it, where ``ede-pipeline experiment export --policies`` published the run, else the
pipeline's for its task.

Frames go to the encoder as they are made, and a video holds at most :data:`ede.analysis.video.MAX_FRAMES` (an
MP4 10,000, a GIF 1,000): more ``--episodes`` than fit are refused before anything is played.

Bad input is one line (exit 2): a folder with no policy (a published copy keeps one only where
exported with ``--policies``), a damaged
policy (its SHA-256 not the one ``run.json`` records, or unreadable), a policy that disagrees with
its run or with itself (:func:`ede.analysis.video.policy_of`), an EDE-TD3 run without its
embedding, a task that cannot be made or cannot render; a machine where MuJoCo has no offscreen GL
is one line, exit 1, and so is a video that cannot be written whole (a full disk). The video
appears whole or not at all.
"""

from __future__ import annotations

import os
from pathlib import Path

import click
import numpy as np

from ede.analysis.policy import PolicyRejected, adapter_of, policy_of, trained_embedding
from ede.analysis.video import (
    FORMATS,
    MAX_FRAMES,
    VIDEO_KIND,
    NoOffscreenGL,
    episode_steps,
    fps_of,
    frames_of,
    write_video,
)
from ede.config import Params
from ede.io.atomic import NotWritten
from ede_pipeline import layout
from ede_pipeline.common import BadInput, Failed, embedding_options, hold_outputs, params_option

OFFSCREEN = ("egl", "osmesa")  # MuJoCo's offscreen GL backends; egl where MUJOCO_GL is unset


def check_episodes(task: str, episodes: int, suffix: str) -> None:
    """Refuse more episodes of ``task`` than a video of ``suffix``'s format holds
    (:data:`ede.analysis.video.MAX_FRAMES`), before any work.

    Raises:
        BadInput: naming the option, its value and the most episodes of ``task`` that fit.
    """
    most = MAX_FRAMES[suffix]
    steps = episode_steps(task) or most  # a task without a time limit: one episode at most
    fits = max(1, most // steps)
    if episodes > fits:
        raise BadInput(
            f"--episodes {episodes}: at most {fits} of {task} (episodes of up to {steps} steps) "
            f"fit in {'an MP4' if suffix == '.mp4' else 'a GIF'} of {most:,} frames"
        )


@click.command()
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--episodes",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help=f"Episodes to play, one after another (at most {MAX_FRAMES['.mp4']:,} frames in all, "
    f"{MAX_FRAMES['.gif']:,} in a GIF).",
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
    try:
        _play(run, episodes, out, params, encoder, decoder)
    except PolicyRejected as error:
        raise BadInput(str(error)) from None
    except (NoOffscreenGL, NotWritten) as error:
        raise Failed(str(error.strerror if isinstance(error, NotWritten) else error)) from None


def _play(
    run: Path,
    episodes: int,
    out: Path | None,
    params: Params,
    encoder: Path | None,
    decoder: Path | None,
) -> None:
    """The command's work, refused in the video library's errors (:func:`render` turns them into
    its own)."""

    def check_out(out: Path) -> None:
        if out.suffix not in FORMATS:
            raise BadInput(f"--out {out}: expected a file ending in {' or '.join(FORMATS)}")
        hold_outputs((None, VIDEO_KIND), files=((out, VIDEO_KIND),), inputs=(run,))

    if out is not None:  # checked before anything is read
        check_out(out)
    meta, tensors = policy_of(run)
    task, algo, seed = meta["task"], meta["algo"], int(meta["seed"])
    if out is None:
        out = layout.video(task, algo, seed)
        if not Path(os.path.normpath(out)).is_relative_to(layout.VIDEOS):  # names from the run
            raise BadInput(
                f"{run}: its policy's task {task!r} and algo {algo!r} put the video at {out}, "
                f"outside {layout.VIDEOS}; expected names of a task and an algorithm, or --out"
            )
        check_out(out)
    check_episodes(task, episodes, out.suffix)
    embedding = None
    if algo == "ede-td3":
        paths = layout.run_embedding(run, meta, params, encoder, decoder)
        embedding = trained_embedding(meta, *paths)
    frames, returns = frames_of(meta, tensors, adapter_of(meta, embedding), episodes)
    out.parent.mkdir(parents=True, exist_ok=True)
    count = write_video(out, frames, fps_of(task))
    click.echo(
        f"{out}: {count} frames, {task} {algo} seed {seed}; returns "
        + ", ".join(f"{r:.4f}" for r in returns)
        + f" (mean {np.mean(returns):.4f})"
    )
