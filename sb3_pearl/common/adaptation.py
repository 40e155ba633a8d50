"""The adaptation API every algorithm of the project implements, and the checks for it.

The meta-test protocol (:func:`sb3_pearl.evaluation.meta_test.meta_test`) talks to a model only through
these four methods (``docs/design.md``): per test task it calls :meth:`~AdaptiveModel.reset_adaptation`,
then for each trajectory k = 0..K it calls :meth:`~AdaptiveModel.adapt` (for k >= 1 only), rolls the
trajectory out with :meth:`~AdaptiveModel.predict` and hands every transition to
:meth:`~AdaptiveModel.observe`. Non-finite values are refused where they enter: ``observe`` (every value),
``predict`` (the observation: :func:`check_finite_observation`).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from gymnasium import spaces

ADAPTATION_METHODS = ("reset_adaptation", "observe", "adapt", "predict")


@runtime_checkable
class AdaptiveModel(Protocol):
    """Structural type of a model the meta-test can adapt: PEARL, PEARL+, Fine-Tune and MAML all implement it."""

    def reset_adaptation(self) -> None:
        """
        Forget everything task-specific (observed transitions, adapted parameters, posterior).

        After this call the next trajectory acts with the prior policy: trajectory k = 0 of the protocol.
        """
        ...

    def observe(self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool) -> None:
        """
        Record one transition of the current task; it only changes how the model acts after the next :meth:`adapt`.

        :param obs: observation the action was taken in
        :param action: the action as sent to the env (env units, i.e. after any unscaling / clipping)
        :param reward: the reward of the step
        :param next_obs: observation after the step (the terminal one when the episode ended)
        :param done: whether the trajectory ended with this step (terminated, truncated or cut short)
        """
        ...

    def adapt(self) -> None:
        """
        Adapt to the current task with every transition observed since :meth:`reset_adaptation`.

        Called between trajectories (never inside one): trajectory k acts after ``adapt()`` on trajectories 0..k-1.
        """
        ...

    def predict(
        self,
        observation: Any,
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = False,
    ) -> tuple[Any, Any]:
        """
        Act with the current adaptation state (SB3's ``predict`` signature).

        :param observation: the observation
        :param state: the recurrent state (None for feed-forward policies)
        :param episode_start: episode-start flags of recurrent policies
        :param deterministic: deterministic actions
        :return: the action (env units) and the next state
        """
        ...


def stored_action(action_space: spaces.Space, action: Any) -> np.ndarray:
    """
    The action passed to ``observe()`` (env units, as from ``predict``) as every algorithm stores it.

    Box: clipped to the bounds (as SB3 clips the actions it sends to the env; an action outside the box
    is stored as the action the env executed) and scaled to [-1, 1] (SB3's ``scale_action``), shape
    (action_dim,); a non-finite action raises. Discrete: the index as a one-element float array, shape (1,),
    checked to be in range.

    :param action_space: the model's action space (Box or Discrete)
    :param action: the action
    :return: float32 array
    """
    if isinstance(action_space, spaces.Discrete):
        index = int(np.asarray(action).reshape(-1)[0])
        if not 0 <= index < int(action_space.n):
            raise ValueError(f"observe(): Discrete action {index} is out of range [0, {int(action_space.n)})")
        return np.array([index], dtype=np.float32)
    if not isinstance(action_space, spaces.Box):
        raise ValueError(f"observe(): Box and Discrete action spaces only, got {action_space}")
    env_action = np.asarray(action, dtype=np.float32)
    if env_action.size != int(np.prod(action_space.shape)):
        raise ValueError(f"observe(): expected one action of shape {action_space.shape}, got shape {env_action.shape}")
    if not np.all(np.isfinite(env_action)):
        raise ValueError(f"observe(): the action {env_action.tolist()} is not finite: pass the action sent to the env")
    low, high = action_space.low, action_space.high
    clipped = np.clip(env_action.reshape(action_space.shape), low, high)
    return (2.0 * ((clipped - low) / (high - low)) - 1.0).reshape(-1).astype(np.float32)


def check_finite_transition(obs: Any, reward: Any, next_obs: Any) -> None:
    """
    Raise a clear error if an observed transition holds a non-finite value (it would poison the adaptation).

    :param obs: observation passed to ``observe()``
    :param reward: reward passed to ``observe()``
    :param next_obs: next observation passed to ``observe()``
    """
    for name, value in (("obs", obs), ("reward", reward), ("next_obs", next_obs)):
        if not np.all(np.isfinite(np.asarray(value, dtype=np.float64))):
            raise ValueError(
                f"observe(): {name} holds a non-finite value ({np.asarray(value).tolist()}): the env diverged or the "
                "transition is corrupt; check the env (and its task) before adapting on it"
            )


def check_finite_observation(model: object, observation: Any) -> None:
    """
    Raise a clear error if an observation handed to ``predict()`` holds a nan or an inf (the action would too).

    :param model: the model (for the message)
    :param observation: the observation (an array, or a dict of arrays)
    """
    values = observation.values() if isinstance(observation, dict) else (observation,)
    for value in values:
        array = np.asarray(value)
        if array.dtype.kind in "fc" and not np.isfinite(array).all():
            raise ValueError(
                f"{type(model).__name__}.predict(): the observation holds a non-finite value ({array.tolist()}): refused, "
                "the action would be non-finite too; the env diverged or the observation is corrupt"
            )


def _missing_methods(obj: Any) -> list[str]:
    return [name for name in ADAPTATION_METHODS if not callable(getattr(obj, name, None))]


def check_adaptive(model: Any) -> None:
    """
    Raise a clear error unless ``model`` implements the adaptation API.

    :param model: the model to evaluate
    """
    missing = _missing_methods(model)
    if missing:
        raise TypeError(
            f"{type(model).__name__} does not implement the adaptation API (missing {missing}): the meta-test "
            "protocol needs reset_adaptation(), observe(obs, action, reward, next_obs, done), adapt() and predict()"
        )


def has_adaptation_api(algo_class: type) -> bool:
    """
    Whether instances of ``algo_class`` implement the adaptation API (every method of :data:`ADAPTATION_METHODS`).

    :param algo_class: an algorithm class
    :return: True when the meta-test protocol can run its models
    """
    return not _missing_methods(algo_class)


__all__ = [
    "ADAPTATION_METHODS",
    "AdaptiveModel",
    "check_adaptive",
    "check_finite_observation",
    "check_finite_transition",
    "has_adaptation_api",
    "stored_action",
]
