"""Gradient-step cost of PEARL / PEARL+ against SB3 SAC and a bare-torch step of the same math.

All rows in one run, on the same data size: 16 tasks x 256 RL rows = 4096 rows (SAC: batch 4096),
3x300 actor and critics, 100 context transitions per task through a 3x200 encoder, for 1 and 2
torch threads. Prints seconds per gradient step and the ratios the project targets:
PEARL+ <= 1.5x SAC, PEARL <= 1.0x SAC, both <= 1.15x their bare-torch step.

    python benchmarks/throughput.py [--steps 20] [--threads 1 2]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from torch import nn
from torch.nn import functional as F

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.envs.point_goal import PointGoalMetaEnv

OBS_DIM, ACT_DIM, LATENT, TASKS, ROWS, CONTEXT = 20, 6, 5, 16, 256, 100
NET, ENC = [300, 300, 300], [200, 200, 200]


class BenchEnv(PointGoalMetaEnv):
    """A task env with the dimensions of a mid-size MuJoCo task (20-dim observation, 6-dim action)."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32)


def fill_meta_buffer(model: PEARLPlus) -> None:
    rng = np.random.default_rng(0)
    for buf in (model.replay_buffer.rl, model.replay_buffer.context):
        n = min(buf.capacity, 2000)
        buf.observations[:, :n] = rng.standard_normal(buf.observations[:, :n].shape)
        buf.next_observations[:, :n] = rng.standard_normal(buf.next_observations[:, :n].shape)
        buf.actions[:, :n] = rng.uniform(-1, 1, buf.actions[:, :n].shape)
        buf.rewards[:, :n] = rng.standard_normal(buf.rewards[:, :n].shape)
        buf.size[:] = n


def make_pearl(cls: type[PEARLPlus], use_bf16: bool = False) -> PEARLPlus:
    kwargs = dict(
        n_train_tasks=TASKS,
        n_test_tasks=1,
        meta_batch=TASKS,
        batch_size=ROWS,
        embedding_batch_size=CONTEXT,
        latent_dim=LATENT,
        encoder_arch=ENC,
        buffer_size=2000,
        num_initial_steps=2000,
        policy_kwargs=dict(net_arch=NET),
        seed=0,
        use_bf16=use_bf16,
    )
    if cls is PEARLPlus:
        kwargs["prior_critic_arch"] = NET
    model = cls("MlpPolicy", BenchEnv(), **kwargs)  # type: ignore[arg-type]
    fill_meta_buffer(model)
    model.set_logger(__import__("stable_baselines3.common.logger", fromlist=["configure"]).configure(None, [""]))
    return model


def make_sac() -> SAC:
    env = gym.wrappers.TimeLimit(BenchEnv(), 20)
    model = SAC("MlpPolicy", env, batch_size=TASKS * ROWS, buffer_size=10_000, policy_kwargs=dict(net_arch=NET), seed=0)
    rng = np.random.default_rng(0)
    for _ in range(5000):
        obs = rng.standard_normal((1, OBS_DIM)).astype(np.float32)
        model.replay_buffer.add(obs, obs, rng.uniform(-1, 1, (1, ACT_DIM)), rng.standard_normal(1), np.zeros(1), [{}])
    model.set_logger(__import__("stable_baselines3.common.logger", fromlist=["configure"]).configure(None, [""]))
    return model


def mlp(inp: int, out: int, hidden: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(inp, h), nn.ReLU(inplace=True)]  # in-place, as the project's networks
        inp = h
    return nn.Sequential(*layers, nn.Linear(inp, out))


class BareStep:
    """The same math as PEARL(+)'s gradient step in plain torch: no SB3 classes, no buffers, one backward."""

    def __init__(self, prior: bool) -> None:
        x = OBS_DIM + LATENT
        self.prior = prior
        self.encoder = mlp(OBS_DIM + ACT_DIM + 1, 2 * LATENT, ENC)
        self.actor = mlp(x, 2 * ACT_DIM, NET)
        self.q = nn.ModuleList(mlp(x + ACT_DIM, 1, NET) for _ in range(2))
        self.q_t = nn.ModuleList(mlp(x + ACT_DIM, 1, NET) for _ in range(2)).requires_grad_(False)
        self.pq = nn.ModuleList([mlp(x + ACT_DIM, 1, NET)])  # the paper's one extra Q-network
        self.pq_t = nn.ModuleList([mlp(x + ACT_DIM, 1, NET)]).requires_grad_(False)
        self.log_alpha = th.zeros(1, requires_grad=True)
        params = [*self.encoder.parameters(), *self.actor.parameters(), *self.q.parameters(), self.log_alpha]
        if prior:
            params += list(self.pq.parameters())
        self.opt = th.optim.Adam(params, lr=3e-4)
        n = TASKS * ROWS
        self.obs, self.next_obs = th.randn(n, OBS_DIM), th.randn(n, OBS_DIM)
        self.act, self.rew = th.rand(n, ACT_DIM) * 2 - 1, th.randn(n, 1)
        self.ctx = th.randn(TASKS, CONTEXT, OBS_DIM + ACT_DIM + 1)

    def pi(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        mu, log_std = self.actor(x).chunk(2, dim=-1)
        std = log_std.clamp(-20, 2).exp()
        u = mu + std * th.randn_like(mu)
        a = th.tanh(u)
        logp = (-0.5 * ((u - mu) / std) ** 2 - std.log() - 0.9189385).sum(-1, keepdim=True)
        return a, logp - th.log(1 - a.pow(2) + 1e-6).sum(-1, keepdim=True)

    def step(self) -> None:
        out = self.encoder(self.ctx)
        mu, var = out[..., :LATENT], F.softplus(out[..., LATENT:]).clamp(min=1e-7)
        pv = 1 / (1 / var).sum(1)
        pm = pv * (mu / var).sum(1)
        z = (pm + pv.sqrt() * th.randn_like(pm)).repeat_interleave(ROWS, 0)
        z0 = th.randn(TASKS, LATENT).repeat_interleave(ROWS, 0)
        kl = 0.5 * (pv + pm**2 - 1 - pv.log()).sum()
        alpha = self.log_alpha.detach().exp()
        xp, x0 = th.cat([self.obs, z.detach()], -1), th.cat([self.obs, z0], -1)
        a_all, lp_all = self.pi(th.cat([xp, x0]) if self.prior else xp)
        n = xp.shape[0]
        with th.no_grad():
            xn, xn0 = th.cat([self.next_obs, z.detach()], -1), th.cat([self.next_obs, z0], -1)
            an_all, lpn_all = self.pi(th.cat([xn, xn0]) if self.prior else xn)
            y = self.rew + 0.99 * (th.min(*[q(th.cat([xn, an_all[:n]], -1)) for q in self.q_t]) - alpha * lpn_all[:n])
            if self.prior:
                y0 = self.rew + 0.99 * (self.pq_t[0](th.cat([xn0, an_all[n:]], -1)) - alpha * lpn_all[n:])
        xq = th.cat([self.obs, z, self.act], -1)
        loss = sum(0.5 * F.mse_loss(q(xq), y) for q in self.q) + 0.1 * kl
        frozen = [{k: v.detach() for k, v in q.named_parameters()} for q in self.q]
        qa = [th.func.functional_call(q, p, (th.cat([xp, a_all[:n]], -1),)) for q, p in zip(self.q, frozen)]
        loss = loss + (alpha * lp_all[:n] - th.min(*qa)).mean()
        if self.prior:
            loss = loss + sum(0.5 * F.mse_loss(q(th.cat([x0, self.act], -1)), y0) for q in self.pq)
            frozen0 = {k: v.detach() for k, v in self.pq[0].named_parameters()}
            qa0 = th.func.functional_call(self.pq[0], frozen0, (th.cat([x0, a_all[n:]], -1),))
            loss = loss + 0.1 * (alpha * lp_all[n:] - qa0).mean()
        loss = loss - (self.log_alpha * (lp_all[:n] - ACT_DIM).detach()).mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        with th.no_grad():
            pairs = [(self.q, self.q_t)] + ([(self.pq, self.pq_t)] if self.prior else [])
            for src, dst in pairs:
                for p, pt in zip(src.parameters(), dst.parameters()):
                    pt.mul_(0.995).add_(p, alpha=0.005)


def seconds_per_step(step: Callable[[], None], steps: int) -> float:
    step()  # warm-up
    best = float("inf")
    for _ in range(3):  # best of three repeats of `steps` steps: robust to a busy neighbour
        start = time.perf_counter()
        for _ in range(steps):
            step()
        best = min(best, (time.perf_counter() - start) / steps)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=10, help="gradient steps per timing repeat")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    sac, pearl, pearl_plus = make_sac(), make_pearl(PEARL), make_pearl(PEARLPlus)
    pearl_plus_bf16 = make_pearl(PEARLPlus, use_bf16=True)
    bare, bare_plus = BareStep(prior=False), BareStep(prior=True)
    print(f"rows per step: {TASKS} tasks x {ROWS} = {TASKS * ROWS}; nets 3x300, encoder 3x200 on {CONTEXT} context rows/task")
    print(
        "| threads | SAC s/step | PEARL s/step | PEARL+ s/step | PEARL/SAC | PEARL+/SAC | PEARL/bare | PEARL+/bare "
        "| PEARL+ bf16 s/step | PEARL+ bf16/SAC |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for threads in args.threads:
        th.set_num_threads(threads)
        t_sac = seconds_per_step(lambda: sac.train(gradient_steps=1, batch_size=TASKS * ROWS), args.steps)
        t_pearl = seconds_per_step(lambda: pearl.train(gradient_steps=1), args.steps)
        t_plus = seconds_per_step(lambda: pearl_plus.train(gradient_steps=1), args.steps)
        t_bare = seconds_per_step(bare.step, args.steps)
        t_bare_plus = seconds_per_step(bare_plus.step, args.steps)
        t_bf16 = seconds_per_step(lambda: pearl_plus_bf16.train(gradient_steps=1), args.steps)
        print(
            f"| {threads} | {t_sac:.3f} | {t_pearl:.3f} | {t_plus:.3f} | {t_pearl / t_sac:.2f} | {t_plus / t_sac:.2f} "
            f"| {t_pearl / t_bare:.2f} | {t_plus / t_bare_plus:.2f} | {t_bf16:.3f} | {t_bf16 / t_sac:.2f} |"
        )


if __name__ == "__main__":
    main()
