"""Returns and advantages for MAML: GAE over a linear feature baseline fitted per task by least squares.

The baseline is a ridge regression of the discounted returns on ``[o, o^2, t, t^2, t^3, 1]`` (``o``
clipped to +-10, ``t`` = step / horizon). Episodes end at their last step (no bootstrap: a
finite-horizon objective). See docs/maml.md. :func:`split_task_samples` then gives each task's valid
steps with their advantages, the input of the inner and outer losses.
"""

from __future__ import annotations

import numpy as np
import torch as th

from sb3_pearl.maml.policies import MAMLPolicy
from sb3_pearl.maml.sampling import act_store_dim
from sb3_pearl.maml.type_aliases import EpisodeBatch, TaskSamples


def baseline_features(observations: th.Tensor, max_episode_steps: int | None) -> th.Tensor:
    """
    Features of the linear baseline: ``[o, o^2, t, t^2, t^3, 1]`` with ``t`` = step / horizon.

    :param observations: shape ``(T, E, H, obs_dim)``
    :param max_episode_steps: the horizon that scales ``t``; ``None`` (or 0) uses ``H``
    :return: shape ``(T, E, H, 2 * obs_dim + 4)``, float64
    """
    obs = observations.double().clamp(-10.0, 10.0)
    n_tasks, n_eps, horizon, _ = obs.shape
    scale = float(max_episode_steps or horizon)
    time_ = (th.arange(horizon, dtype=th.float64, device=obs.device) / scale).view(1, 1, horizon, 1)
    time_ = time_.expand(n_tasks, n_eps, horizon, 1)
    return th.cat([obs, obs**2, time_, time_**2, time_**3, th.ones_like(time_)], dim=-1)


def compute_advantages(
    batch: EpisodeBatch,
    gamma: float,
    gae_lambda: float,
    baseline_reg: float,
    normalize_advantage: bool,
    max_episode_steps: int | None,
    device: th.device | str,
) -> th.Tensor:
    """
    GAE advantages over a linear feature baseline fitted per task by ridge least squares on the
    discounted returns (episodes end at their last step: no bootstrap, a finite-horizon objective).

    :param batch: the episodes
    :param gamma: discount factor
    :param gae_lambda: GAE lambda (1: Monte-Carlo returns minus the baseline)
    :param baseline_reg: ridge coefficient of the least-squares fit (multiplied by 10, up to 4 times,
        while the solution is not finite)
    :param normalize_advantage: standardise the advantages per task over its valid steps
    :param max_episode_steps: the horizon that scales the time features (see :func:`baseline_features`)
    :param device: torch device of the computation
    :return: advantages, shape ``(T, E, H)``, float32, 0 after the end of each episode; standardised per task
        over its valid steps if ``normalize_advantage``
    """
    rewards = th.as_tensor(batch.rewards, dtype=th.float64, device=device)  # (T, E, H)
    n_tasks, n_eps, horizon = rewards.shape
    steps = th.arange(horizon, device=device).view(1, 1, horizon)
    mask = (steps < th.as_tensor(batch.lengths, device=device).unsqueeze(-1)).double()  # (T, E, H)
    rewards = rewards * mask

    returns = th.zeros_like(rewards)
    running = th.zeros_like(rewards[..., 0])
    for t in reversed(range(horizon)):
        running = rewards[..., t] + gamma * running
        returns[..., t] = running
    returns = returns * mask

    features = baseline_features(th.as_tensor(batch.observations, device=device), max_episode_steps)  # (T, E, H, F)
    x = (features * mask.unsqueeze(-1)).reshape(n_tasks, n_eps * horizon, -1)  # (T, N, F)
    y = returns.reshape(n_tasks, n_eps * horizon, 1)  # (T, N, 1)
    xtx = x.transpose(1, 2) @ x  # (T, F, F)
    xty = x.transpose(1, 2) @ y  # (T, F, 1)
    eye = th.eye(xtx.shape[-1], dtype=xtx.dtype, device=device)
    reg = baseline_reg
    for _ in range(5):
        coeffs = th.linalg.lstsq(xtx + reg * eye, xty).solution  # (T, F, 1)
        if th.isfinite(coeffs).all():
            break
        reg *= 10
    values = (features @ coeffs.unsqueeze(1)).squeeze(-1) * mask  # (T, E, H)

    advantages = th.zeros_like(rewards)
    last = th.zeros_like(rewards[..., 0])
    next_value = th.zeros_like(rewards[..., 0])
    for t in reversed(range(horizon)):
        delta = rewards[..., t] + gamma * next_value - values[..., t]
        last = (delta + gamma * gae_lambda * last) * mask[..., t]
        advantages[..., t] = last
        next_value = values[..., t]
    if normalize_advantage:
        count = mask.sum(dim=(1, 2), keepdim=True).clamp(min=1)
        mean = advantages.sum(dim=(1, 2), keepdim=True) / count
        var = (((advantages - mean) * mask) ** 2).sum(dim=(1, 2), keepdim=True) / count
        advantages = (advantages - mean) / (var.sqrt() + 1e-8) * mask
    return advantages.float()


def split_task_samples(
    batch: EpisodeBatch, advantages: th.Tensor, policy: MAMLPolicy, device: th.device | str
) -> list[TaskSamples]:
    """
    The valid steps of each task of ``batch``, with their advantages, as tensors for the losses.

    :param batch: the episodes
    :param advantages: their advantages, shape ``(T, E, H)`` (see :func:`compute_advantages`)
    :param policy: the MAML policy (observation size, action type)
    :param device: torch device of the tensors
    :return: one :class:`TaskSamples` per task; Discrete actions as a long tensor of indices
    """
    n_tasks, _, horizon = batch.rewards.shape
    valid = np.arange(horizon)[None, None, :] < batch.lengths[..., None]  # (T, E, H)
    samples = []
    for j in range(n_tasks):
        keep = th.as_tensor(valid[j].reshape(-1), device=device)
        obs = th.as_tensor(batch.observations[j], device=device).reshape(-1, policy.obs_dim)[keep]
        act = th.as_tensor(batch.actions[j], device=device).reshape(-1, act_store_dim(policy))[keep]
        if not policy.continuous:
            act = act.reshape(-1).long()
        samples.append(TaskSamples(obs, act, advantages[j].reshape(-1)[keep]))
    return samples
