"""Reading run folders and config strings without running code.

rl_zoo3 reads a run folder's ``args.yml`` and ``config.yml`` with ``yaml.UnsafeLoader`` and turns
dict-valued strings into dicts with ``eval()``: opening a folder someone else wrote can run any code
(``!!python/object/apply:os.system [...]``). The project's commands read them here instead:

- :class:`RunFolderLoader`: YAML's safe loader plus the Python tags rl_zoo3's ``yaml.dump`` writes
  into these files, ``!!python/object/apply:collections.OrderedDict`` (the files themselves),
  ``!!python/tuple`` (tuple values such as ``train_freq``) and ``!!python/name:`` for torch's
  activation classes only (``activation_fn`` of an Optuna trial's ``policy_kwargs``, or of a
  ``-params policy_kwargs:"dict(activation_fn=nn.Tanh)"``: the class is looked up, nothing is
  called); any other ``!!python/...`` tag is refused with :class:`UnsafeConfigError`;
- :func:`parse_dict_string`: ``"dict(n_adapt=3)"`` / ``"{'n_adapt': 3}"`` parsed with :mod:`ast`,
  literals only;
- :func:`get_saved_hyperparams`: rl_zoo3's function of the same name over the safe loader.

Trust model: configs and run-folder YAML are data and never run code. Model zips and replay buffers
are pickles (as in SB3): loading one runs what its author put in it, so load only files you trust.
The hyperparameter file given to ``train.py`` is code as far as rl_zoo3 is concerned (it ``eval``s
``policy_kwargs`` strings and runs ``.py`` configs): use your own or trusted ones.
"""

from __future__ import annotations

import ast
import os
from collections import OrderedDict
from typing import Any

import yaml


class UnsafeConfigError(ValueError):
    """A run-folder YAML file asks to build a Python object the safe loader does not allow."""


class RunFolderLoader(yaml.SafeLoader):
    """
    ``yaml.SafeLoader`` plus the tags rl_zoo3 writes into ``args.yml`` / ``config.yml`` (module docstring).

    Usage: ``yaml.load(stream, Loader=RunFolderLoader)``, or :func:`load_run_yaml`.
    """


def _construct_ordered_dict(loader: yaml.SafeLoader, node: yaml.Node) -> OrderedDict[Any, Any]:
    # yaml.dump(OrderedDict(...)) writes "!!python/object/apply:collections.OrderedDict" then [[[key, value], ...]]
    if not isinstance(node, yaml.SequenceNode):
        raise UnsafeConfigError(f"{node.start_mark}: an OrderedDict must be written as a list of [key, value] pairs")
    args = loader.construct_sequence(node, deep=True)
    if len(args) > 1 or (args and not all(isinstance(pair, list) and len(pair) == 2 for pair in args[0])):
        raise UnsafeConfigError(f"{node.start_mark}: an OrderedDict must be written as a list of [key, value] pairs")
    return OrderedDict((key, value) for key, value in (args[0] if args else []))


def _construct_tuple(loader: yaml.SafeLoader, node: yaml.Node) -> tuple[Any, ...]:
    if not isinstance(node, yaml.SequenceNode):
        raise UnsafeConfigError(f"{node.start_mark}: a tuple must be written as a sequence")
    return tuple(loader.construct_sequence(node, deep=True))


ACTIVATION_MODULE = "torch.nn.modules.activation"  # the one module whose classes a run-folder YAML may name


def _construct_activation(loader: yaml.SafeLoader, name: str, node: yaml.Node) -> Any:
    """``!!python/name:torch.nn.modules.activation.<Class>``: that class (looked up, not called); anything else refused."""
    module, _, attribute = name.rpartition(".")
    if module != ACTIVATION_MODULE or not attribute.isidentifier() or attribute.startswith("_"):
        return _refuse(loader, f"name:{name}", node)
    import torch.nn.modules.activation as activations

    found = getattr(activations, attribute, None)
    if not (isinstance(found, type) and issubclass(found, activations.Module)):
        return _refuse(loader, f"name:{name}", node)
    return found


def _refuse(loader: yaml.SafeLoader, tag_suffix: str, node: yaml.Node) -> Any:
    raise UnsafeConfigError(
        f"refusing the YAML tag '!!python/{tag_suffix}' ({node.start_mark.name}, line {node.start_mark.line + 1}): "
        "run-folder files are read with a safe loader that builds plain data, OrderedDict and tuple only. train.py "
        "never writes this tag, so the file was edited or comes from elsewhere: inspect it, and remove the tag if you "
        "trust the run"
    )


RunFolderLoader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict", _construct_ordered_dict)
RunFolderLoader.add_constructor("tag:yaml.org,2002:python/tuple", _construct_tuple)
RunFolderLoader.add_multi_constructor("tag:yaml.org,2002:python/name:", _construct_activation)
RunFolderLoader.add_multi_constructor("tag:yaml.org,2002:python/", _refuse)


def load_run_yaml(path: str | os.PathLike[str]) -> Any:
    """
    Read a run folder's ``args.yml`` / ``config.yml`` with :class:`RunFolderLoader`.

    :param path: the YAML file
    :return: its content (OrderedDicts as written by rl_zoo3)
    """
    with open(path) as file:
        try:
            return yaml.load(file, Loader=RunFolderLoader)  # noqa: S506 (RunFolderLoader is a SafeLoader)
        except yaml.constructor.ConstructorError as error:
            raise UnsafeConfigError(
                f"{path}: {error.problem} ({error.problem_mark}): run-folder files are read with a safe loader that "
                "builds plain data, OrderedDict and tuple only; inspect the file, and remove the tag if you trust the run"
            ) from None


def parse_dict_string(text: str, key: str) -> dict[str, Any]:
    """
    A dict given as a string (the zoo's convention for dict values), parsed without running code.

    Accepts a dict literal (``"{'n_adapt': 3}"``) or ``dict(...)`` with keyword arguments whose values
    are literals (``"dict(n_adapt=3, deterministic=False)"``).

    :param text: the string
    :param key: the config key it belongs to (for the message)
    :return: the dict
    """
    example = f'{key}:"dict(n_adapt=3)" or {key}:"{{\'n_adapt\': 3}}"'
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except SyntaxError as error:
        raise ValueError(f"{key}: cannot parse {text!r} ({error.msg}); write a dict of literals, e.g. {example}") from None
    try:
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "dict":
            if node.args or any(keyword.arg is None for keyword in node.keywords):
                raise ValueError("dict(...) with keyword arguments only")
            value: Any = {keyword.arg: ast.literal_eval(keyword.value) for keyword in node.keywords}
        else:
            value = ast.literal_eval(node)
    except ValueError:
        raise ValueError(
            f"{key}: {text!r} is not a dict of literals (numbers, strings, True / False / None, lists, dicts); names, "
            f"calls and expressions are not evaluated. Write e.g. {example}"
        ) from None
    if not isinstance(value, dict):
        raise ValueError(f"{key} must be a dict, got {text!r}; write e.g. {example}")
    return value


def get_saved_hyperparams(
    stats_path: str, norm_reward: bool = False, test_mode: bool = False
) -> tuple[dict[str, Any], str | None]:
    """
    ``rl_zoo3.utils.get_saved_hyperparams`` over :func:`load_run_yaml` and :func:`parse_dict_string` (same results).

    :param stats_path: the run's ``<EnvId>/`` folder (``config.yml``, ``vecnormalize.pkl``)
    :param norm_reward: normalise rewards (VecNormalize)
    :param test_mode: override ``norm_reward`` of a saved ``normalize`` string
    :return: the saved hyperparameters and ``stats_path`` (empty dict and None if the folder does not exist)
    """
    hyperparams: dict[str, Any] = {}
    if not os.path.isdir(stats_path):
        return hyperparams, None
    config_file = os.path.join(stats_path, "config.yml")
    if os.path.isfile(config_file):
        hyperparams = dict(load_run_yaml(config_file) or {})
        hyperparams["normalize"] = hyperparams.get("normalize", False)
    else:
        hyperparams["normalize"] = os.path.isfile(os.path.join(stats_path, "obs_rms.pkl"))
    if hyperparams["normalize"]:
        if isinstance(hyperparams["normalize"], str):
            normalize_kwargs = parse_dict_string(hyperparams["normalize"], "normalize")
            if test_mode:
                normalize_kwargs["norm_reward"] = norm_reward
        elif isinstance(hyperparams["normalize"], dict):
            normalize_kwargs = hyperparams["normalize"]
        else:
            normalize_kwargs = {"norm_obs": hyperparams["normalize"], "norm_reward": norm_reward}
        hyperparams["normalize_kwargs"] = normalize_kwargs
    return hyperparams, stats_path


__all__ = [
    "RunFolderLoader",
    "UnsafeConfigError",
    "get_saved_hyperparams",
    "load_run_yaml",
    "parse_dict_string",
]
