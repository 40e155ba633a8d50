"""Gradient-step cost of PEARL / PEARL+ against SB3 SAC and a bare-torch step of the same math, at two sizes.

Sizes (``--sizes``): ``cpu``, the `cpu` budget preset's Walker2D-vel entry (the size of every run of the science:
8 tasks x 128 RL rows, 2x128 actor and critics, 2x128 encoder on 100 context rows per task), and ``paper``, the
paper's (16 tasks x 256 rows, 3x300 networks, 3x200 encoder, 100 context rows). SB3 SAC trains on the same rows
(batch tasks x rows) with the same networks.

The bare step (:class:`BareStep`) is the same math written as fast as torch allows on a CPU: each critic of the
ensemble one ``linear`` per layer (stacked weights with one ``baddbmm`` per layer, ``--batched-bare``, were
slower on this project's CPUs: docs/speed.md), the frozen-critic passes on detached weights, one fused Adam over every
parameter, foreach Polyak updates, no SB3 classes, buffers, logging or divergence guard.

Every variant is timed in interleaved repeats (SAC, PEARL, bare PEARL, PEARL+, bare PEARL+, then again) and the
median of the repeats is reported, so that a neighbour's load hits them alike. Prints seconds per gradient step and
the ratios the project targets: PEARL+ <= 1.15x its bare step and <= 1.5x SAC, at both sizes.

    python benchmarks/throughput.py [--sizes cpu paper] [--steps 10] [--repeats 7] [--threads 1] [--batched-bare]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.logger import configure
from torch import nn
from torch.nn import functional as F

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.envs.point_goal import PointGoalMetaEnv

OBS_DIM, ACT_DIM, LATENT = 20, 6, 5  # a mid-size MuJoCo task (Walker2D: 17 / 6)


@dataclass(frozen=True)
class Size:
    """One problem size: tasks x rows per gradient step, network and encoder hidden sizes, context rows per task."""

    tasks: int
    rows: int
    net: list[int]
    encoder: list[int]
    context: int

    def describe(self) -> str:
        net, enc = "x".join(map(str, self.net)), "x".join(map(str, self.encoder))
        return f"{self.tasks} tasks x {self.rows} rows, nets {net}, encoder {enc} on {self.context} context rows"


SIZES = {
    "cpu": Size(8, 128, [128, 128], [128, 128], 100),  # sb3_pearl/config/presets/cpu.yml, walker2d-vel
    "paper": Size(16, 256, [300, 300, 300], [200, 200, 200], 100),  # the paper's (paper.yml)
}


class BenchEnv(PointGoalMetaEnv):
    """A task env with the dimensions of a mid-size MuJoCo task (20-dim observation, 6-dim action)."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32)


def fill_meta_buffer(model: PEARL) -> None:
    rng = np.random.default_rng(0)
    for buf in (model.replay_buffer.rl, model.replay_buffer.context):
        n = min(buf.capacity, 2000)
        buf.observations[:, :n] = rng.standard_normal(buf.observations[:, :n].shape)
        buf.next_observations[:, :n] = rng.standard_normal(buf.next_observations[:, :n].shape)
        buf.actions[:, :n] = rng.uniform(-1, 1, buf.actions[:, :n].shape)
        buf.rewards[:, :n] = rng.standard_normal(buf.rewards[:, :n].shape)
        buf.size[:] = n


def make_pearl(cls: type[PEARL], size: Size, use_bf16: bool = False) -> PEARL:
    kwargs = dict(
        n_train_tasks=size.tasks,
        n_test_tasks=1,
        meta_batch=size.tasks,
        batch_size=size.rows,
        embedding_batch_size=size.context,
        latent_dim=LATENT,
        encoder_arch=size.encoder,
        buffer_size=2000,
        num_initial_steps=2000,
        policy_kwargs=dict(net_arch=size.net),
        seed=0,
        use_bf16=use_bf16,
    )
    if cls is PEARLPlus:
        kwargs["prior_critic_arch"] = size.net
    model = cls("MlpPolicy", BenchEnv(), **kwargs)  # type: ignore[arg-type]
    fill_meta_buffer(model)
    model.set_logger(configure(None, [""]))
    return model


def make_sac(size: Size) -> SAC:
    env = gym.wrappers.TimeLimit(BenchEnv(), 20)
    batch = size.tasks * size.rows
    model = SAC("MlpPolicy", env, batch_size=batch, buffer_size=10_000, policy_kwargs=dict(net_arch=size.net), seed=0)
    rng = np.random.default_rng(0)
    for _ in range(5000):
        obs = rng.standard_normal((1, OBS_DIM)).astype(np.float32)
        model.replay_buffer.add(obs, obs, rng.uniform(-1, 1, (1, ACT_DIM)), rng.standard_normal(1), np.zeros(1), [{}])
    model.set_logger(configure(None, [""]))
    return model


def mlp(inp: int, out: int, hidden: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(inp, h), nn.ReLU(inplace=True)]  # in-place, as the project's networks
        inp = h
    return nn.Sequential(*layers, nn.Linear(inp, out))


class StackedMLP(nn.Module):
    """``n`` MLPs of the same shape held as stacked weights (n, in, out): one ``baddbmm`` per layer for all of them."""

    def __init__(self, n: int, inp: int, out: int, hidden: list[int]) -> None:
        super().__init__()
        sizes = [inp, *hidden, out]
        nets = [mlp(inp, out, hidden) for _ in range(n)]  # torch's default initialisation, per network
        linears = [[m for m in net if isinstance(m, nn.Linear)] for net in nets]
        self.weights = nn.ParameterList(
            nn.Parameter(th.stack([layers[i].weight.detach().t() for layers in linears])) for i in range(len(sizes) - 1)
        )
        self.biases = nn.ParameterList(
            nn.Parameter(th.stack([layers[i].bias.detach() for layers in linears]).unsqueeze(1)) for i in range(len(sizes) - 1)
        )

    def forward(self, x: th.Tensor, frozen: bool = False) -> th.Tensor:
        """(N, in) -> (n, N, out); ``frozen``: detached weights, gradients reach ``x`` only."""
        h = x.unsqueeze(0).expand(len(self.weights[0]), -1, -1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            if frozen:
                w, b = w.detach(), b.detach()
            h = th.baddbmm(b, h, w)
            if i < last:
                h = h.relu_()
        return h


class MLPList(nn.Module):
    """``n`` MLPs of the same shape, each run with its own ``linear`` calls (faster than ``baddbmm`` on a CPU)."""

    def __init__(self, n: int, inp: int, out: int, hidden: list[int]) -> None:
        super().__init__()
        self.nets = nn.ModuleList(mlp(inp, out, hidden) for _ in range(n))

    def forward(self, x: th.Tensor, frozen: bool = False) -> th.Tensor:
        """(N, in) -> (n, N, out); ``frozen``: detached weights, gradients reach ``x`` only."""
        outs = []
        for net in self.nets:
            h = x
            for layer in net:
                if isinstance(layer, nn.Linear):
                    w, b = (layer.weight.detach(), layer.bias.detach()) if frozen else (layer.weight, layer.bias)
                    h = F.linear(h, w, b)
                else:
                    h = h.relu_()
            outs.append(h)
        return th.stack(outs)


class BareStep:
    """The same math as PEARL(+)'s gradient step, as fast as plain torch allows (module docstring)."""

    def __init__(self, size: Size, prior: bool, batched: bool = False) -> None:
        x = OBS_DIM + LATENT
        self.size, self.prior = size, prior
        self.encoder = mlp(OBS_DIM + ACT_DIM + 1, 2 * LATENT, size.encoder)
        self.actor = mlp(x, 2 * ACT_DIM, size.net)
        ensemble = StackedMLP if batched else MLPList
        self.q = ensemble(2, x + ACT_DIM, 1, size.net)
        self.q_t = ensemble(2, x + ACT_DIM, 1, size.net).requires_grad_(False)
        self.q_t.load_state_dict(self.q.state_dict())
        self.pq = ensemble(1, x + ACT_DIM, 1, size.net)  # the paper's one extra Q-network
        self.pq_t = ensemble(1, x + ACT_DIM, 1, size.net).requires_grad_(False)
        self.pq_t.load_state_dict(self.pq.state_dict())
        self.log_alpha = th.zeros(1, requires_grad=True)
        params = [*self.encoder.parameters(), *self.actor.parameters(), *self.q.parameters(), self.log_alpha]
        self.targets = [(list(self.q.parameters()), list(self.q_t.parameters()))]
        if prior:
            params += list(self.pq.parameters())
            self.targets.append((list(self.pq.parameters()), list(self.pq_t.parameters())))
        self.opt = th.optim.Adam(params, lr=3e-4, fused=True)
        n = size.tasks * size.rows
        self.obs, self.next_obs = th.randn(n, OBS_DIM), th.randn(n, OBS_DIM)
        self.act, self.rew = th.rand(n, ACT_DIM) * 2 - 1, th.randn(n, 1)
        self.ctx = th.randn(size.tasks, size.context, OBS_DIM + ACT_DIM + 1)

    def pi(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        mu, log_std = self.actor(x).chunk(2, dim=-1)
        std = log_std.clamp(-20, 2).exp()
        u = mu + std * th.randn_like(mu)
        a = th.tanh(u)
        logp = (-0.5 * ((u - mu) / std) ** 2 - std.log() - 0.9189385).sum(-1, keepdim=True)
        return a, logp - th.log(1 - a.pow(2) + 1e-6).sum(-1, keepdim=True)

    def step(self) -> None:
        self.update(self.loss())

    def update(self, loss: th.Tensor) -> None:
        """Backward, one fused Adam step, the target networks' Polyak update."""
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        with th.no_grad():
            for src, dst in self.targets:
                th._foreach_mul_(dst, 0.995)
                th._foreach_add_(dst, src, alpha=0.005)

    def loss(self) -> th.Tensor:
        """Every loss of one gradient step, summed (each reaches only its own parameters, as in PEARL+)."""
        tasks, rows = self.size.tasks, self.size.rows
        out = self.encoder(self.ctx)
        mu, var = out[..., :LATENT], F.softplus(out[..., LATENT:]).clamp(min=1e-7)
        pv = 1 / (1 / var).sum(1)
        pm = pv * (mu / var).sum(1)
        z = (pm + pv.sqrt() * th.randn_like(pm)).repeat_interleave(rows, 0)
        z0 = th.randn(tasks, LATENT).repeat_interleave(rows, 0)
        kl = 0.5 * (pv + pm**2 - 1 - pv.log()).sum()
        alpha = self.log_alpha.detach().exp()
        xp, x0 = th.cat([self.obs, z.detach()], -1), th.cat([self.obs, z0], -1)
        a_all, lp_all = self.pi(th.cat([xp, x0]) if self.prior else xp)
        n = xp.shape[0]
        with th.no_grad():
            xn, xn0 = th.cat([self.next_obs, z.detach()], -1), th.cat([self.next_obs, z0], -1)
            an_all, lpn_all = self.pi(th.cat([xn, xn0]) if self.prior else xn)
            y = self.rew + 0.99 * (self.q_t(th.cat([xn, an_all[:n]], -1)).min(0).values - alpha * lpn_all[:n])
            if self.prior:
                y0 = self.rew + 0.99 * (self.pq_t(th.cat([xn0, an_all[n:]], -1))[0] - alpha * lpn_all[n:])
        loss = (self.q(th.cat([self.obs, z, self.act], -1)) - y).pow(2).mean(dim=(1, 2)).sum() + 0.1 * kl
        qa = self.q(th.cat([xp, a_all[:n]], -1), frozen=True).min(0).values
        loss = loss + (alpha * lp_all[:n] - qa).mean()
        if self.prior:
            loss = loss + (self.pq(th.cat([x0, self.act], -1))[0] - y0).pow(2).mean()
            qa0 = self.pq(th.cat([x0, a_all[n:]], -1), frozen=True)[0]
            loss = loss + 0.1 * (alpha * lp_all[n:] - qa0).mean()
        return loss - (self.log_alpha * (lp_all[:n] - ACT_DIM).detach()).mean()


def timed(step: Callable[[], None], steps: int) -> float:
    """Seconds per step over ``steps`` steps."""
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return (time.perf_counter() - start) / steps


def measure(variants: dict[str, Callable[[], None]], steps: int, repeats: int) -> dict[str, float]:
    """Median seconds per step of each variant, timed in interleaved repeats (a neighbour's load hits them alike)."""
    for step in variants.values():
        step()  # warm-up
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):
        for name, step in variants.items():
            times[name].append(timed(step, steps))
    return {name: statistics.median(values) for name, values in times.items()}


def make_variants(size: Size, bf16: bool, batched_bare: bool = False) -> dict[str, Callable[[], None]]:
    """One gradient step of each variant at ``size``, in the order they are timed (``batched_bare``: the bare steps
    hold each critic ensemble as stacked weights, one ``baddbmm`` per layer)."""
    sac, pearl, plus = make_sac(size), make_pearl(PEARL, size), make_pearl(PEARLPlus, size)
    bare, bare_plus = BareStep(size, prior=False, batched=batched_bare), BareStep(size, prior=True, batched=batched_bare)
    batch = size.tasks * size.rows
    variants: dict[str, Callable[[], None]] = {
        "sac": lambda: sac.train(gradient_steps=1, batch_size=batch),
        "pearl": lambda: pearl.train(gradient_steps=1, batch_size=size.rows),
        "bare": bare.step,
        "plus": lambda: plus.train(gradient_steps=1, batch_size=size.rows),
        "bare_plus": bare_plus.step,
    }
    if bf16:
        plus_bf16 = make_pearl(PEARLPlus, size, use_bf16=True)
        variants["bf16"] = lambda: plus_bf16.train(gradient_steps=1, batch_size=size.rows)
    return variants


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", choices=sorted(SIZES), default=["cpu", "paper"])
    parser.add_argument("--steps", type=int, default=10, help="gradient steps per timing repeat")
    parser.add_argument("--repeats", type=int, default=7, help="interleaved timing repeats (the median is reported)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1])
    parser.add_argument("--bf16", action="store_true", help="also time PEARL+ with use_bf16=True")
    parser.add_argument(
        "--batched-bare", action="store_true", help="bare steps with stacked critic weights and baddbmm (docs/speed.md)"
    )
    args = parser.parse_args()
    print(
        "| size | threads | SAC s/step | PEARL s/step | PEARL+ s/step | bare PEARL s/step | bare PEARL+ s/step "
        "| PEARL/bare | PEARL+/bare | PEARL/SAC | PEARL+/SAC |" + (" PEARL+ bf16 s/step |" if args.bf16 else "")
    )
    print("|---" * (11 + args.bf16) + "|")
    for name in args.sizes:
        size = SIZES[name]
        variants = make_variants(size, args.bf16, args.batched_bare)
        for threads in args.threads:
            th.set_num_threads(threads)
            t = measure(variants, args.steps, args.repeats)
            row = (
                f"| {name} | {threads} | {t['sac']:.4f} | {t['pearl']:.4f} | {t['plus']:.4f} | {t['bare']:.4f} "
                f"| {t['bare_plus']:.4f} | {t['pearl'] / t['bare']:.2f} | {t['plus'] / t['bare_plus']:.2f} "
                f"| {t['pearl'] / t['sac']:.2f} | {t['plus'] / t['sac']:.2f} |"
            )
            print(row + (f" {t['bf16']:.4f} |" if args.bf16 else ""), flush=True)
        print(f"  {name}: {size.describe()}")


if __name__ == "__main__":
    main()
