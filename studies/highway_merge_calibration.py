"""Calibration table of HighwayMergeMeta-v0: IDM headway per task-box corner and the measured traffic.

For each corner of the task box (density 30 / 50 veh/km x speed 50 / 70 mph) it prints the calibrated IDM
parameters and the mean main-lane speed and spacing measured (a) on the traffic alone over the last 30 s of a
60 s run from the jittered start, (b) over whole episodes with a scripted ego (cruise, change lane on the merge
lane) so Hidas yielding is included (with that naive policy's crash rate), and (c) with highway-env's default
headway and jam distance (T = 1.5 s, d0 = 10 m) for contrast.

    python studies/highway_merge_calibration.py [--episodes 5]
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import sb3_pearl  # noqa: F401  (registers the envs)
from sb3_pearl.envs.highway_merge import (
    CRUISE,
    LANE_LEFT,
    MERGE_LANE,
    MPH,
    HighwayMergeMetaEnv,
    IDMParams,
    MergeRoad,
    measure_main_lane_traffic,
)


def episodes(env: HighwayMergeMetaEnv, n: int) -> tuple[float, float, float]:
    """Mean main-lane speed and spacing over ``n`` episodes of a scripted merge, and the crash rate."""
    speeds, spacings, crashes = [], [], 0
    for seed in range(n):
        env.reset(seed=seed)
        while True:
            action = LANE_LEFT if env.vehicle.lane_index == MERGE_LANE else CRUISE
            _, _, terminated, truncated, info = env.step(action)
            road = env.road
            assert isinstance(road, MergeRoad)
            speeds.append(road.v.mean())
            spacings.append(np.diff(road.x).mean())
            if terminated or truncated:
                crashes += int(info["cost"] > 0)
                break
    return float(np.mean(speeds)), float(np.mean(spacings)), crashes / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=5)
    args = parser.parse_args()
    env = gym.make("HighwayMergeMeta-v0").unwrapped
    assert isinstance(env, HighwayMergeMetaEnv)
    print(
        "| density [veh/km] | speed [mph] (m/s) | spacing [m] | T [s] | v0 [m/s] | traffic alone: speed, spacing "
        "| episodes: speed, spacing, crash rate | default IDM: speed, spacing |"
    )
    print("|---:|---:|---:|---:|---:|---|---|---|")
    for density in (30.0, 50.0):
        for mph in (50.0, 70.0):
            speed = mph * MPH
            env.set_task({"density": density, "speed": speed})
            env.reset(seed=0)
            idm = env.task_idm
            alone = measure_main_lane_traffic(env)
            ep_speed, ep_spacing, crash_rate = episodes(env, args.episodes)
            stock_idm = IDMParams(desired_speed=idm.desired_speed, time_wanted=1.5, distance_wanted=10.0)
            default = measure_main_lane_traffic(env, stock_idm)
            print(
                f"| {density:.0f} | {mph:.0f} ({speed:.2f}) | {1000 / density:.1f} | {idm.time_wanted:.3f} "
                f"| {idm.desired_speed:.1f} | {alone[0]:.2f}, {alone[1]:.2f} "
                f"| {ep_speed:.2f}, {ep_spacing:.2f}, {crash_rate:.2f} | {default[0]:.2f}, {default[1]:.2f} |"
            )


if __name__ == "__main__":
    main()
