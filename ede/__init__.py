"""The EDE method as a library: the embedding of action sequences (:mod:`ede.method.embedding`), TD3 and
EDE-TD3 (:mod:`ede.method.td3`, :mod:`ede.run.training`), and what the pipeline's stages share (params,
artifacts, rollouts, runs, statistics). ``ede_pipeline`` is the command line around it.

One name is public at the top: :class:`ede.EmbeddedActions` (:mod:`ede.run.embedded`), a family's
EDE space as a gymnasium wrapper that any agent acts in. It is imported on first use, so that
``import ede`` (and ``ede.config``, ``ede.analysis.results``) loads neither torch nor gymnasium.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ede.run.embedded import EmbeddedActions

__all__ = ["EmbeddedActions"]


def __getattr__(name: str) -> Any:
    if name == "EmbeddedActions":
        from ede.run.embedded import EmbeddedActions

        return EmbeddedActions
    raise AttributeError(f"module 'ede' has no attribute {name!r}")
