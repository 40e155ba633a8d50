"""Build step of the wheel: the zoo's hyperparameter files travel inside the package.

The source of the files is the repository's top-level ``zoo_hyperparams/`` (edited there, read there in a checkout);
``build_py`` copies them to ``sb3_pearl/zoo/hyperparams/`` in the build, where an installed ``sb3_pearl.zoo``
finds them (``sb3_pearl.zoo.experiment_manager.HYPERPARAMS_DIR``). Everything else is in pyproject.toml.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

SOURCE = Path(__file__).resolve().parent / "zoo_hyperparams"
TARGET = Path("sb3_pearl", "zoo", "hyperparams")


class BuildPyWithHyperparams(build_py):
    """setuptools' ``build_py``, then ``zoo_hyperparams/*.yml`` copied into ``sb3_pearl/zoo/hyperparams/``."""

    def run(self) -> None:
        super().run()
        target = Path(self.build_lib) / TARGET
        target.mkdir(parents=True, exist_ok=True)
        for path in sorted(SOURCE.glob("*.yml")):
            shutil.copy2(path, target / path.name)


setup(cmdclass={"build_py": BuildPyWithHyperparams})
