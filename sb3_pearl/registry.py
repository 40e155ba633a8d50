"""The one registry of the project's algorithms and activation names (everything that maps a name to a class).

- :data:`ALGORITHM_NAMES` and :func:`algorithm_class`: the zoo names (``pearl``, ``pearlplus``, ``finetune``, ``maml``,
  ``oracle``), used by ``train.py`` / ``enjoy.py`` (``rl_zoo3.ALGOS``, filled by :func:`sb3_pearl.zoo.register_algos`),
  the reproduction harness and its presets;
- :func:`constructor_kwargs`: the keyword arguments an algorithm's constructor takes (YAML entries, presets and
  variant overrides are checked against it);
- :data:`ACTIVATIONS`: the activation names a preset or a YAML entry may give for ``policy_kwargs.activation_fn``.

It imports the algorithms and nothing else of the project's tools, so the budget presets' loader, ``zoo/`` and the
paper's harness beside the package (``pearl_paper``) all read it without importing each other (tests/test_layout.py).
"""

from __future__ import annotations

import inspect

from torch import nn

ALGORITHM_NAMES: tuple[str, ...] = ("pearl", "pearlplus", "finetune", "maml", "oracle")
ACTIVATIONS: dict[str, type[nn.Module]] = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}
# Set by the zoo and the harness themselves when they build a model: not allowed in a YAML entry or a preset.
ZOO_SET_KWARGS = frozenset({"env", "tensorboard_log", "seed", "verbose", "device", "_init_setup_model"})


def algorithm_classes() -> dict[str, type]:
    """Zoo name -> algorithm class (imported on first use: the algorithms import torch and the envs)."""
    from sb3_pearl.finetune import FineTune
    from sb3_pearl.maml import MAML
    from sb3_pearl.oracle import Oracle
    from sb3_pearl.pearl import PEARL, PEARLPlus

    return {"pearl": PEARL, "pearlplus": PEARLPlus, "finetune": FineTune, "maml": MAML, "oracle": Oracle}


def algorithm_class(name: str) -> type:
    """
    The algorithm class of a zoo name (``pearl`` -> PEARL, ...).

    :param name: ``pearl``, ``pearlplus``, ``finetune`` or ``maml``
    :return: the class
    """
    classes = algorithm_classes()
    if name not in classes:
        raise ValueError(f"unknown algorithm {name!r}: choose among {sorted(classes)}")
    return classes[name]


def constructor_parameters(algo_class: type) -> dict[str, inspect.Parameter]:
    """
    The parameters ``algo_class(...)`` takes: ``inspect.signature`` of the class. A constructor that forwards
    ``**kwargs`` to its parent's (``PEARLPlus`` to ``PEARL``, ``FineTune`` to ``DiscreteSAC``) shows its parent's too
    (:func:`~sb3_pearl.common.meta_algorithm.forwards_arguments_to`).

    :param algo_class: an algorithm class
    :return: name -> parameter (``*args`` and ``**kwargs`` left out)
    """
    parameters = inspect.signature(algo_class).parameters.values()
    return {p.name: p for p in parameters if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)}


def constructor_kwargs(algo_class: type) -> set[str]:
    """
    Keyword arguments ``algo_class(...)`` takes (:func:`constructor_parameters`). PEARL's own signature has no PEARL+
    setting, so ``pearl`` refuses ``prior_coef``.

    :param algo_class: an algorithm class
    :return: the accepted names (without the ones the zoo and the harness set themselves)
    """
    return set(constructor_parameters(algo_class)) - ZOO_SET_KWARGS


__all__ = [
    "ACTIVATIONS",
    "ALGORITHM_NAMES",
    "ZOO_SET_KWARGS",
    "algorithm_class",
    "algorithm_classes",
    "constructor_kwargs",
    "constructor_parameters",
]
