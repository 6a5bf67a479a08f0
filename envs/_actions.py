"""What every task checks of an action before the simulator sees it.

A non-finite action has no meaning, and no task takes it harmlessly: ``ede/Point-v0`` adds it to
its position, which then stays NaN on every later step, and MuJoCo, given a NaN or infinite
control, warns and steps as if it were zero while the reward's control cost comes out NaN. So
every task's ``step`` calls :func:`check_action` before anything else, and a refused action
leaves the task as it was: the next valid step is the one it would have been.
"""

from __future__ import annotations

import gymnasium
import numpy as np
from numpy.typing import ArrayLike

__all__ = ["check_action"]


def check_action(env: gymnasium.Env, action: ArrayLike) -> None:
    """Refuse an action with a NaN or infinite component; any other action passes untouched.

    Raises:
        ValueError: naming the task (its id, or its class when it was not made by id) and the
            action.
    """
    values = np.asarray(action, dtype=np.float64)
    if not np.isfinite(values).all():
        task = env.spec.id if env.spec is not None else type(env).__name__
        raise ValueError(f"{task}: expected a finite action, got {values.tolist()}")
