"""The default number of torch threads: the count that is fastest for the network sizes in use, unless the user chose.

torch starts with one intra-op thread per core. At this project's network sizes that is not faster than one thread
and, on a machine whose cores are busy, many times slower (the threads of a matrix product wait on each other;
docs/speed.md, "The thread default", has the measurements behind the rule).

The rule (:func:`default_num_threads`):

- networks narrower than :data:`WIDE_LAYER` units (every ``cpu`` and ``smoke`` preset, the zoo's SafePoint and
  Highway-Merge PEARL entries, MAML): **one thread**;
- wider networks (the ``paper`` preset's 3x300, the zoo's Fine-Tune entries): one thread per idle core (the cores
  this process may run on minus the 1-minute load average, rounded down), at least 1 and at most :data:`MAX_THREADS`.

It is applied by ``learn()`` of every algorithm of the project (:class:`~sb3_pearl.common.meta_algorithm.MetaAlgorithm`),
and so by ``train.py``, and by ``enjoy.py`` after it loads a model, only when the thread count is not explicit
(:func:`num_threads_is_explicit`): an ``OMP_NUM_THREADS`` or ``MKL_NUM_THREADS`` variable, ``--num-threads N``
(``train.py`` / ``enjoy.py``, which call :func:`mark_num_threads_explicit`), or a ``torch.set_num_threads`` call
made after ``import sb3_pearl`` (the count then differs from the one seen at import, or from the last default
applied here). A ``torch.set_num_threads`` call made *before* ``import sb3_pearl`` cannot be told from torch's own
default: call :func:`mark_num_threads_explicit` too, or set ``OMP_NUM_THREADS``. The reproduction harness sets one
thread per run itself (its runs share the cores).
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence

import torch as th
from torch import nn

#: networks with a layer at least this wide get more than one thread where cores are idle
WIDE_LAYER = 256
#: the most threads the default gives
MAX_THREADS = 4
#: environment variables that set the thread count of torch's OpenMP / MKL pools
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")

_count_at_import = th.get_num_threads()  # torch's default unless the user set it before importing sb3_pearl
_state: dict[str, int | bool | None] = {"applied": None, "explicit": False}


def mark_num_threads_explicit() -> None:
    """Record that the user chose the thread count (``--num-threads``): no default replaces it in this process."""
    _state["explicit"] = True


def num_threads_is_explicit() -> bool:
    """Whether the thread count was chosen by the user (the module docstring says how that is told)."""
    if _state["explicit"] or any(os.environ.get(name) for name in THREAD_VARIABLES):
        return True
    applied = _state["applied"]
    return th.get_num_threads() != (_count_at_import if applied is None else applied)


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def idle_cores() -> int:
    """The cores this process may run on minus the 1-minute load average, rounded down (at least 0)."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # pragma: no cover - no load average on this platform
        load = 0.0
    return max(0, math.floor(available_cores() - load))


def network_width(module: nn.Module) -> int:
    """The widest ``Linear`` layer (its output units) of ``module``: what sets the cost of a matrix product here."""
    return max((layer.out_features for layer in module.modules() if isinstance(layer, nn.Linear)), default=0)


def default_num_threads(width: int) -> int:
    """
    The fastest thread count for networks whose widest layer has ``width`` units (the rule of the module docstring).

    :param width: :func:`network_width` of the model's networks
    :return: the number of torch threads
    """
    if width < WIDE_LAYER:
        return 1
    return max(1, min(MAX_THREADS, idle_cores()))


def num_threads_flag(args: Sequence[str]) -> int:
    """
    The value of a ``--num-threads N`` command-line flag (``train.py``, ``enjoy.py``), -1 without one.

    :param args: the command line
    """
    peek = argparse.ArgumentParser(add_help=False)
    peek.add_argument("--num-threads", type=int, default=-1)
    try:
        known, _ = peek.parse_known_args(list(args))
    except SystemExit:  # a malformed value: the command's own parser reports it
        return -1
    return int(known.num_threads)


def apply_default_num_threads(module: nn.Module) -> int | None:
    """
    Set torch's thread count to :func:`default_num_threads` for ``module``'s networks, unless the count is explicit.

    :param module: the networks (a policy)
    :return: the count set, or None when the user's count was kept
    """
    if num_threads_is_explicit():
        return None
    threads = default_num_threads(network_width(module))
    th.set_num_threads(threads)
    _state["applied"] = threads
    return threads


__all__ = [
    "MAX_THREADS",
    "THREAD_VARIABLES",
    "WIDE_LAYER",
    "apply_default_num_threads",
    "available_cores",
    "default_num_threads",
    "idle_cores",
    "mark_num_threads_explicit",
    "network_width",
    "num_threads_flag",
    "num_threads_is_explicit",
]
