"""The project's configuration, as package data (no build step copies it; rl_zoo3 ships its ``hyperparams/`` the
same way, with a top-level link in the repository):

- ``zoo_hyperparams/<algo>.yml``: one rl-zoo entry per env id for ``train.py`` (the repository's top-level
  ``zoo_hyperparams/`` is a link to this folder);
- ``presets/<preset>.yml``: the budget presets (``smoke``, ``cpu``, ``paper``), read by
  :func:`sb3_pearl.budgets.load_budget` for ``train.py --budget`` and for the paper's reproduction harness (the
  repository's ``pearl_paper``, which is not part of the package).
"""

from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent
HYPERPARAMS_DIR = CONFIG_DIR / "zoo_hyperparams"
PRESETS_DIR = CONFIG_DIR / "presets"
