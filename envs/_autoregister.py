"""Register the ``ede/`` tasks as soon as gymnasium is imported, without importing it ourselves.

Gymnasium 1.x dropped its plugin entry point, so nothing it does at import time can find us. The
installed ``.pth`` file imports :mod:`ede_envs` (cheap: no gymnasium, no MuJoCo) at interpreter
start; this module then either registers at once, when gymnasium is already loaded, or puts a
finder on ``sys.meta_path`` that runs the registration right after ``gymnasium.envs`` has
executed (its built-in tasks, ``Pusher-v5`` among them, are registered by then).
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import sys
from collections.abc import Callable, Sequence
from types import ModuleType

_HOOKED_MODULE = "gymnasium.envs"


class _RunAfterExec(importlib.abc.Loader):
    """Wraps a module's loader and calls ``then()`` once the module has executed."""

    def __init__(self, inner: importlib.abc.Loader, then: Callable[[], None]) -> None:
        self._inner = inner
        self._then = then

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return self._inner.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        self._inner.exec_module(module)
        self._then()


class _PostImportFinder(importlib.abc.MetaPathFinder):
    """Finds nothing itself; wraps the real loader of ``gymnasium.envs`` the one time it loads."""

    def __init__(self, then: Callable[[], None]) -> None:
        self._then = then

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname != _HOOKED_MODULE:
            return None
        sys.meta_path.remove(self)  # one shot; also keeps the lookup below from recursing
        spec = importlib.util.find_spec(fullname)
        if spec is not None and spec.loader is not None:
            spec.loader = _RunAfterExec(spec.loader, self._then)
        return spec


def install(register: Callable[[], None]) -> None:
    """Run ``register`` now if gymnasium's registry is loaded, else right after it loads."""
    if _HOOKED_MODULE in sys.modules:
        register()
    elif not any(isinstance(finder, _PostImportFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, _PostImportFinder(register))
