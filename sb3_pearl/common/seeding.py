"""Seeding for common random numbers and for exact resume: derived seeds, and saving / restoring RNG states.

The meta-test (``crn_seed``) and the diagnostics seed numpy's and torch's global generators from
(seed, task, repeat[, k]) so that every model or variant compared sees the same z0 draws, posterior
samples and env resets, and give the caller's RNG state back afterwards.

:func:`capture_training_rng_state` / :func:`restore_training_rng_state` hold every generator a
training run draws from (Python's, numpy's and torch's global ones, the model's action space and each
env's ``np_random``): a model saves them and a loaded model continues the same streams instead of
reseeding, so a run split at an iteration boundary gives the same weights as the unsplit run.
"""

from __future__ import annotations

import random
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


def capture_training_rng_state(env: Any = None, action_space: Any = None) -> dict[str, Any]:
    """
    Every RNG state a training run draws from: Python's, numpy's and torch's global generators, the action
    space's and each env's ``np_random`` (None where there is no such generator).

    :param env: the model's VecEnv (or None)
    :param action_space: the model's action space (or None)
    :return: the states, picklable
    """
    state: dict[str, Any] = {"python": random.getstate(), "global": get_global_rng_state(), "action_space": None, "envs": None}
    generator = getattr(action_space, "_np_random", None)
    if generator is not None:
        state["action_space"] = generator.bit_generator.state
    if env is not None and not getattr(env, "closed", False):  # a closed SubprocVecEnv cannot answer
        try:
            state["envs"] = [getattr(g, "bit_generator", None) and g.bit_generator.state for g in env.get_attr("np_random")]
        except (AttributeError, OSError, EOFError):  # no np_random, or workers gone: the env RNGs are not saved
            state["envs"] = None
    return state


def restore_training_rng_state(state: dict[str, Any], env: Any = None, action_space: Any = None) -> None:
    """
    Restore the states of :func:`capture_training_rng_state` (the env's only if it has as many envs).

    :param state: the captured states
    :param env: the model's VecEnv (or None: the env states are not restored)
    :param action_space: the model's action space (or None)
    """
    random.setstate(state["python"])
    set_global_rng_state(state["global"])
    if action_space is not None and state.get("action_space") is not None:
        action_space.seed(0)  # creates the generator, whose state is then replaced
        action_space.np_random.bit_generator.state = state["action_space"]
    envs = state.get("envs")
    if env is not None and envs is not None and len(envs) == env.num_envs:
        for index, env_state in enumerate(envs):
            if env_state is None:
                continue
            generator = np.random.Generator(getattr(np.random, env_state["bit_generator"])())
            generator.bit_generator.state = env_state
            env.set_attr("np_random", generator, indices=[index])
