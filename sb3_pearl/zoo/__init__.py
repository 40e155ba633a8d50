"""rl-zoo integration: the project's algorithms in ``rl_zoo3``, an ExperimentManager with the meta-test, and enjoy.

``train.py`` and ``enjoy.py`` at the repository root are thin wrappers over this package:

- :mod:`sb3_pearl.zoo.algos`: :func:`register_algos` (the algorithms in ``rl_zoo3.ALGOS``
  and the PEARL / PEARL+ Optuna samplers), :func:`constructor_kwargs`;
- :mod:`sb3_pearl.zoo.experiment_manager`: :class:`MetaExperimentManager` (rl_zoo3's
  ``ExperimentManager`` with the project's hyperparameter files and the meta-test) and :func:`train`, put together
  from :mod:`~sb3_pearl.zoo.meta_testing` (evaluation callback, Optuna score, final meta-test),
  :mod:`~sb3_pearl.zoo.interruptions` (signals and exceptions save the model) and :mod:`~sb3_pearl.zoo.flags`
  (``--budget``, ``--resume``); :mod:`~sb3_pearl.zoo.model_checks`: a saved model against its env;
- :mod:`sb3_pearl.zoo.replay`: :func:`enjoy`, prior and posterior rollouts of a trained model;
- :mod:`sb3_pearl.zoo.budget`: ``train.py --budget PRESET`` (a budget preset's entry as the hyperparameters);
- :mod:`sb3_pearl.zoo.usage`: :class:`UsageError`, user errors printed as one line with exit status 2.

After ``pip install``, ``python -m sb3_pearl.train`` / ``python -m sb3_pearl.enjoy`` (``sb3-pearl-train`` /
``sb3-pearl-enjoy``) run them from anywhere; ``python -m sb3_pearl.zoo`` prints how.
"""

from sb3_pearl.zoo.algos import (
    constructor_kwargs,
    convert_pearl_params,
    register_algos,
    sample_pearl_params,
    sample_pearlplus_params,
)
from sb3_pearl.zoo.experiment_manager import (
    HYPERPARAMS_DIR,
    ZOO_META_TEST_DEFAULTS,
    ZOO_SPECIAL_KEYS,
    MetaExperimentManager,
    check_model_env,
    check_model_spaces,
    default_config,
    train,
    write_meta_test,
)
from sb3_pearl.zoo.replay import enjoy, enjoy_parser
from sb3_pearl.zoo.usage import UsageError

__all__ = [
    "HYPERPARAMS_DIR",
    "ZOO_META_TEST_DEFAULTS",
    "ZOO_SPECIAL_KEYS",
    "MetaExperimentManager",
    "UsageError",
    "check_model_env",
    "check_model_spaces",
    "constructor_kwargs",
    "convert_pearl_params",
    "default_config",
    "enjoy",
    "enjoy_parser",
    "register_algos",
    "sample_pearl_params",
    "sample_pearlplus_params",
    "train",
    "write_meta_test",
]
