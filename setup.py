"""Install-time glue that pyproject.toml cannot express: the ``ede_envs`` start-up hook.

Gymnasium 1.x no longer loads environment plugins from entry points, so ``gymnasium.make`` in a
fresh interpreter would not know the ``ede/`` tasks. The distribution therefore ships one ``.pth``
line that imports the (dependency-free) ``ede_envs`` package at start-up; it registers the tasks
the moment gymnasium is imported (see ``envs/_autoregister.py``). Both a regular and an editable
install get the file.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.editable_wheel import editable_wheel

PTH_NAME = "ede_envs-autoregister.pth"
PTH_TEXT = "import ede_envs\n"


class BuildPyWithPth(build_py):
    """Regular wheels: put the .pth at the root of the wheel, which is site-packages."""

    def run(self) -> None:
        super().run()
        Path(self.build_lib, PTH_NAME).write_text(PTH_TEXT)

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        return [*super().get_outputs(include_bytecode), str(Path(self.build_lib, PTH_NAME))]


class EditableWheelWithPth(editable_wheel):
    """Editable wheels hold only setuptools' own finder; add our .pth beside it."""

    def _select_strategy(self, name, tag, build_lib):
        strategy = super()._select_strategy(name, tag, build_lib)

        class WithPth:
            def __enter__(self):
                strategy.__enter__()
                return self

            def __exit__(self, *exc):
                return strategy.__exit__(*exc)

            def __call__(self, wheel, files, mapping):
                strategy(wheel, files, mapping)
                # Sorted after setuptools' own "__editable__" .pth, so ede_envs is importable.
                wheel.writestr(f"zz-{PTH_NAME}", PTH_TEXT)

        return WithPth()


setup(cmdclass={"build_py": BuildPyWithPth, "editable_wheel": EditableWheelWithPth})
