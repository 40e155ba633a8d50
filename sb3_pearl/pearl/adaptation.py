"""PEARL's side of the adaptation API: task inference from the transitions observed on a new task.

``reset_adaptation`` draws z from the prior (trajectory k = 0 of the meta-test), ``observe`` records
transitions, ``adapt`` infers q(z | everything observed) and draws the z that ``predict`` acts with
until the next ``adapt``. SB3's ``predict`` never sees rewards, so inference happens here.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_pearl.common.adaptation import stored_action
from sb3_pearl.common.meta_algorithm import check_observed_transition
from sb3_pearl.pearl.policies import PEARLPolicy


class PosteriorSample(NamedTuple):
    """q(z | c) for T tasks and one z per task."""

    mean: th.Tensor  # (T, latent_dim)
    var: th.Tensor  # (T, latent_dim)
    z: th.Tensor  # (T, latent_dim): a reparameterised sample (carries encoder gradients), or the mean


class PosteriorAdaptationMixin:
    """The adaptation API of :class:`~sb3_pearl.PEARL` (mixed into it; uses its policy and :meth:`sample_posterior`)."""

    policy: PEARLPolicy
    observation_space: spaces.Space
    action_space: spaces.Space
    device: th.device
    _adapt_context: list[tuple[np.ndarray, np.ndarray, float, np.ndarray]]

    @property
    def latent_dim(self) -> int:
        """Size of z."""
        return self.policy.latent_dim

    def sample_posterior(self, context: th.Tensor, sample: bool = True) -> PosteriorSample:
        """
        Task inference, the one place where a context becomes a posterior and a z (losses, collection, adaptation).

        :param context: context transitions (T, N, context_dim)
        :param sample: draw z from q(z | c) with the reparameterisation trick, or take its mean
        :return: posterior mean and variance and z, each (T, latent_dim)
        """
        mean, var = self.policy.encoder.posterior(context)
        z = mean + var.sqrt() * th.randn_like(mean) if sample else mean
        return PosteriorSample(mean, var, z)

    def reset_adaptation(self) -> None:
        """Forget the observed context and draw z from the prior, held until :meth:`adapt` (k = 0)."""
        self._adapt_context = []
        self.policy.current_z = th.randn(self.latent_dim, device=self.device)

    def resample_prior(self) -> None:
        """A fresh z from the prior, the context kept (the reference's exploration trajectories, each with its own z)."""
        self.policy.current_z = th.randn(self.latent_dim, device=self.device)

    def observe(self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool) -> None:
        """
        Record one transition of the new task (env-space action, as returned by :meth:`predict`).

        :param obs: observation before the action, shape (obs_dim,)
        :param action: the action taken (env units for Box, an index for Discrete)
        :param reward: reward received
        :param next_obs: observation after the action
        :param done: whether the episode ended (not used by the encoder)
        """
        obs, next_obs = check_observed_transition(self.observation_space, obs, reward, next_obs)  # (obs_dim,) each
        self._adapt_context.append(
            (obs, stored_action(self.action_space, action), float(np.asarray(reward).reshape(-1)[0]), next_obs)
        )

    def _adaptation_context(self) -> th.Tensor:
        """Everything observed since the last reset as one task's context, (1, N, context_dim)."""
        obs, actions, rewards, next_obs = (np.stack(column) for column in zip(*self._adapt_context))
        tensors = [
            th.as_tensor(a, device=self.device, dtype=th.float32)[None] for a in (obs, actions, rewards[:, None], next_obs)
        ]
        return self.policy.make_context(*tensors)

    def infer_posterior(self) -> tuple[th.Tensor, th.Tensor]:
        """Posterior mean and variance (each (latent_dim,)) from everything observed since the last reset."""
        if not self._adapt_context:
            return th.zeros(self.latent_dim, device=self.device), th.ones(self.latent_dim, device=self.device)
        with th.no_grad():
            posterior = self.sample_posterior(self._adaptation_context(), sample=False)
        return posterior.mean[0], posterior.var[0]

    def adapt(self, sample_z: bool = True) -> None:
        """
        Infer the posterior from all observed transitions and act with a new z from it.

        :param sample_z: draw z from the posterior (the reference's meta-test) or use its mean
        """
        if not self._adapt_context:  # nothing observed: a new draw from the prior
            self.policy.current_z = (
                th.randn(self.latent_dim, device=self.device) if sample_z else th.zeros(self.latent_dim, device=self.device)
            )
            return
        with th.no_grad():
            self.policy.current_z = self.sample_posterior(self._adaptation_context(), sample=sample_z).z[0]
