"""Seeding for common random numbers: seeds derived from several integers, and saving / restoring the global RNGs.

The meta-test (``crn_seed``) and the diagnostics seed numpy's and torch's global generators from
(seed, task, repeat[, k]) so that every model or variant compared sees the same z0 draws, posterior
samples and env resets, and give the caller's RNG state back afterwards.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th


def derived_seed(*entropy: int) -> int:
    """
    A 32-bit seed derived from integers (``np.random.SeedSequence``): the same integers give the same seed.

    :param entropy: e.g. (crn_seed, task index, repeat, k)
    :return: the seed
    """
    return int(np.random.SeedSequence(list(entropy)).generate_state(1)[0])


def seed_global_rngs(*entropy: int) -> None:
    """
    Seed numpy's and torch's global RNGs (torch: every device) from integers, through ``np.random.SeedSequence``.

    :param entropy: e.g. (crn_seed, task index, repeat)
    """
    np_seed, th_seed = np.random.SeedSequence(list(entropy)).generate_state(2)
    np.random.seed(int(np_seed))
    th.manual_seed(int(th_seed))


def get_global_rng_state() -> tuple[Any, th.Tensor, list[th.Tensor] | None]:
    """numpy's and torch's global RNG states (CUDA ones only if CUDA is initialised), for :func:`set_global_rng_state`."""
    cuda = th.cuda.get_rng_state_all() if th.cuda.is_initialized() else None
    return np.random.get_state(), th.get_rng_state(), cuda


def set_global_rng_state(state: tuple[Any, th.Tensor, list[th.Tensor] | None]) -> None:
    """Restore the states returned by :func:`get_global_rng_state`."""
    np_state, th_state, cuda = state
    np.random.set_state(np_state)
    th.set_rng_state(th_state)
    if cuda is not None:
        th.cuda.set_rng_state_all(cuda)
