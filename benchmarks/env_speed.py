"""Env steps per second of each task family against its raw base env, as ratios from one run.

Both envs of a row are built with ``gym.make`` (the same TimeLimit / order / checker wrappers),
driven by the same pre-drawn random actions and reset with the same seeds (for the MuJoCo families
the physics is then identical, only the reward differs), in alternating timed blocks; each env's
speed is its best block (the least disturbed by other processes on a shared machine). The target
is ratio >= 0.95 (at most 5% overhead).

    python benchmarks/env_speed.py [--families Walker2dVelMeta-v0 AntVelMeta-v0] [--steps 2000] [--repeats 7]

To add a family, add one entry to :data:`FAMILIES`: id -> (factory of the meta env, name of the
base env, factory of the base env); import heavy dependencies inside the factories.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np

import sb3_pearl  # noqa: F401  (registers the task families)

EnvFactory = Callable[[], gym.Env]


def _point_maze_base() -> gym.Env:
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return gym.make("PointMaze_MediumDense-v3", continuing_task=True, reset_target=False, max_episode_steps=300)


def _stock_merge() -> gym.Env:
    """highway-env's stock ``merge-v0`` at the merge family's simulation / policy frequencies (10 Hz / 2 Hz)."""
    import warnings

    import highway_env

    gym.register_envs(highway_env)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # "merge-v0 is out of date": it is the paper-era env
        env = gym.make("merge-v0")
    env.unwrapped.configure({"simulation_frequency": 10, "policy_frequency": 2})
    return env


# id -> (meta env factory, base env name, base env factory)
FAMILIES: dict[str, tuple[EnvFactory, str, EnvFactory]] = {
    "HalfCheetahVelMeta-v0": (
        lambda: gym.make("HalfCheetahVelMeta-v0"),
        "HalfCheetah-v5",
        lambda: gym.make("HalfCheetah-v5", ctrl_cost_weight=0.05, max_episode_steps=200),
    ),
    "Walker2dVelMeta-v0": (
        lambda: gym.make("Walker2dVelMeta-v0"),
        "Walker2d-v5",
        lambda: gym.make("Walker2d-v5", max_episode_steps=200),
    ),
    "AntVelMeta-v0": (lambda: gym.make("AntVelMeta-v0"), "Ant-v5", lambda: gym.make("Ant-v5", max_episode_steps=200)),
    "AntDirMeta-v0": (lambda: gym.make("AntDirMeta-v0"), "Ant-v5", lambda: gym.make("Ant-v5", max_episode_steps=200)),
    "AntGoalMeta-v0": (
        lambda: gym.make("AntGoalMeta-v0"),
        "Ant-v5 (with x, y)",
        lambda: gym.make("Ant-v5", exclude_current_positions_from_observation=False, max_episode_steps=200),
    ),
    "SparsePointGoalMeta-v0": (
        lambda: gym.make("SparsePointGoalMeta-v0"),
        "PointGoalMeta-v0",
        lambda: gym.make("PointGoalMeta-v0"),
    ),
    "PointMazeGoalMeta-v0": (lambda: gym.make("PointMazeGoalMeta-v0"), "PointMaze_MediumDense-v3", _point_maze_base),
    # target ratio >= 10: the meta env replaces highway-env's hot spots, see docs/highway_merge.md
    "HighwayMergeMeta-v0": (lambda: gym.make("HighwayMergeMeta-v0"), "merge-v0 (10 Hz / 2 Hz)", _stock_merge),
}


def time_block(env: gym.Env, actions: np.ndarray, seed: int) -> float:
    """
    Run ``len(actions)`` steps (resetting at episode ends) and return the elapsed seconds.

    :param env: the environment
    :param actions: the actions, one row per step
    :param seed: seed of the first reset (later resets add the episode count)
    :return: wall-clock seconds of the block, resets included
    """
    episode = 0
    env.reset(seed=seed)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            episode += 1
            env.reset(seed=seed + episode)
    return time.perf_counter() - start


def measure(env_id: str, steps: int, repeats: int, seed: int) -> tuple[str, float, float]:
    """
    Best-of-``repeats`` steps/s of a family and of its base env, measured in alternating blocks.

    :param env_id: a key of :data:`FAMILIES`
    :param steps: steps per timed block
    :param repeats: blocks per env
    :param seed: seed of the actions and resets
    :return: base env name, meta steps/s, base steps/s
    """
    make_meta, base_name, make_base = FAMILIES[env_id]
    meta, base = make_meta(), make_base()
    space = meta.action_space
    space.seed(seed)
    actions = np.array([space.sample() for _ in range(steps)])
    time_block(meta, actions[: steps // 10], seed)  # warm-up (caches, lazy imports)
    time_block(base, actions[: steps // 10], seed)
    meta_times, base_times = [], []
    for _ in range(repeats):
        meta_times.append(time_block(meta, actions, seed))
        base_times.append(time_block(base, actions, seed))
    meta.close()
    base.close()
    return base_name, steps / min(meta_times), steps / min(base_times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(FAMILIES), metavar="ENV_ID")
    parser.add_argument("--steps", type=int, default=2000, help="steps per timed block")
    parser.add_argument("--repeats", type=int, default=7, help="timed blocks per env (the best one counts)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print("| family | base env | meta steps/s | base steps/s | ratio |")
    print("|---|---|---:|---:|---:|")
    for env_id in args.families:
        base_name, meta_speed, base_speed = measure(env_id, args.steps, args.repeats, args.seed)
        print(
            f"| `{env_id}` | `{base_name}` | {meta_speed:,.0f} | {base_speed:,.0f} | {meta_speed / base_speed:.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
