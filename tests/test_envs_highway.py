"""HighwayMergeMeta-v0: env contract, task protocol, Hidas' rule, IDM calibration, costs, b_min, rendering."""

from __future__ import annotations

import copy
import json
import math

import gymnasium as gym
import numpy as np
import pytest
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle
from stable_baselines3.common.env_checker import check_env

import sb3_pearl  # noqa: F401  (registers the envs)
from sb3_pearl.envs.highway_merge import (
    ACCELERATE,
    CRUISE,
    DECELERATE,
    END_OF_LANE,
    LANE_LEFT,
    MAIN_LANES,
    MERGE_LANE,
    MPH,
    HidasIDMVehicle,
    HidasParams,
    HighwayMergeMetaEnv,
    IDMParams,
    MergeEgoVehicle,
    MergeRoad,
    calibrate_idm,
    hidas_should_yield,
    idm_acceleration,
    measure_main_lane_traffic,
    min_braking,
)

ENV_ID = "HighwayMergeMeta-v0"
CORNERS = [(density, mph * MPH) for density in (30.0, 50.0) for mph in (50.0, 70.0)]


def make(**kwargs: object) -> HighwayMergeMetaEnv:
    env = gym.make(ENV_ID, **kwargs).unwrapped
    assert isinstance(env, HighwayMergeMetaEnv)
    return env


def road_of(env: HighwayMergeMetaEnv) -> MergeRoad:
    assert isinstance(env.road, MergeRoad)
    return env.road


# -- contract and task protocol ----------------------------------------------------------------------
@pytest.mark.parametrize("normalize_obs", [True, False])
def test_check_env(normalize_obs: bool) -> None:
    env = gym.make(ENV_ID, normalize_obs=normalize_obs)
    check_env(env.unwrapped, warn=False)
    assert env.observation_space.shape == (24,) and env.action_space == gym.spaces.Discrete(5)
    assert env.spec is not None and env.spec.max_episode_steps == 60 == env.unwrapped.horizon
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and info["cost"] == 0.0
    assert obs[4] == 1.0 and obs[9] == 1.0  # nearest main-lane vehicles present


def test_sample_tasks_reproducible_and_in_range() -> None:
    env = make()
    tasks = env.sample_tasks(50, seed=3)
    assert tasks == env.sample_tasks(50, seed=3) and tasks != env.sample_tasks(50, seed=4)
    assert json.loads(json.dumps(tasks)) == tasks
    densities = np.array([t["density"] for t in tasks])
    speeds = np.array([t["speed"] for t in tasks])
    assert densities.min() >= 30.0 and densities.max() <= 50.0
    assert speeds.min() >= 50 * MPH and speeds.max() <= 70 * MPH  # m/s
    shifted = make(density_range=(50.0, 55.0), speed_range=(70 * MPH, 75 * MPH))
    assert all(50.0 <= t["density"] <= 55.0 and t["speed"] >= 70 * MPH for t in shifted.sample_tasks(10, seed=0))


def test_set_task_changes_dynamics_and_is_sticky() -> None:
    env = make(normalize_obs=False)
    slow_sparse = {"density": 30.0, "speed": 50 * MPH}
    fast_dense = {"density": 50.0, "speed": 70 * MPH}
    env.set_task(fast_dense)
    assert env.get_task() == fast_dense
    for seed in (0, 1, 2):  # sticky across resets
        obs, _ = env.reset(seed=seed)
        assert env.get_task() == fast_dense
        road = road_of(env)
        assert road.task_speed == fast_dense["speed"] and road.spacing == pytest.approx(20.0)
        assert road.idm == calibrate_idm(50.0, 70 * MPH)
    env.set_task(slow_sparse)
    obs_slow, _ = env.reset(seed=0)
    env.set_task(fast_dense)
    obs_fast, _ = env.reset(seed=0)
    # same seed, same ego: the observed traffic speed (dvx + ego vx) and spacing follow the task
    traffic_speed = lambda obs: obs[[7, 12, 17, 22]] + obs[2]  # noqa: E731
    np.testing.assert_allclose(traffic_speed(obs_slow), 50 * MPH, rtol=0.04)
    np.testing.assert_allclose(traffic_speed(obs_fast), 70 * MPH, rtol=0.04)
    assert road_of(env).idm.time_wanted < calibrate_idm(30.0, 50 * MPH).time_wanted
    with pytest.raises(ValueError, match="task keys"):
        env.set_task({"density": 40.0})
    with pytest.raises(ValueError, match="no IDM equilibrium"):
        env.set_task({"density": 200.0, "speed": 30.0})


def test_bad_kwargs_raise() -> None:
    for kwargs, match in [
        ({"density_range": (50.0, 30.0)}, "density_range"),
        ({"speed_range": (0.0, 10.0)}, "speed_range"),
        ({"policy_frequency": 3}, "policy_frequency"),
        ({"horizon": 0}, "horizon"),
        ({"ego_start": 500.0}, "ego_start"),
        ({"w_gap": -1.0}, "w_gap"),
        ({"hidas_b_f": 0.0}, "b_f"),
        ({"render_mode": "video"}, "render_mode"),
    ]:
        with pytest.raises(ValueError, match=match):
            HighwayMergeMetaEnv(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="action"):
        env = make()
        env.step(5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"density_range": (30.0, math.inf)}, r"density_range must be two finite numbers"),
        ({"speed_range": (10.0, math.inf)}, r"speed_range must be two finite numbers"),
        ({"ego_speed_range": (15.0, math.nan)}, r"ego_speed_range must be two finite numbers"),
        ({"horizon": 2.5}, r"horizon must be an integer >= 1"),
        ({"policy_frequency": 2.0}, r"policy_frequency must be an integer >= 1"),
        ({"w_speed": math.nan}, r"w_speed must be a finite number >= 0"),
        ({"collision_penalty": math.inf}, r"collision_penalty must be a finite number >= 0"),
        ({"spawn_jitter": 1.5}, r"spawn_jitter must be a finite number in \[0, 1\)"),
        ({"speed_jitter": 1.0}, r"speed_jitter must be a finite number in \[0, 1\)"),
        ({"desired_speed_ratio": math.nan}, r"desired_speed_ratio must be a finite number > 1"),
        ({"jam_gap": -5.0}, r"jam_gap must be a finite number >= 0"),
        ({"hidas_dv": math.nan}, r"hidas_dv must be a finite number > 0"),
        ({"hidas_g_min": math.nan}, r"hidas_g_min must be a finite number >= 0"),
        ({"hidas_c": -1.0}, r"hidas_c must be a finite number >= 0"),
    ],
)
def test_kwargs_that_hide_violations_are_refused(kwargs: dict[str, object], match: str) -> None:
    """Every kwarg is checked (finite, in range), the error naming it: a nan weight or an infinite range built an env
    whose rewards or traffic were nonsense."""
    with pytest.raises(ValueError, match=match):
        HighwayMergeMetaEnv(**kwargs)  # type: ignore[arg-type]


# -- Hidas' rule and IDM -------------------------------------------------------------------------------
def test_hidas_hand_computed() -> None:
    # Dt = dv / b_f = 2.7 / 1.5 = 1.8 s, b_f Dt^2 / 2 = 1.5 * 3.24 / 2 = 2.43 m, so
    # g_sld = g_f - 1.8 v_f + 2.43 + 1.8 v_s.
    # Equal speeds 25/25, g_f = 10: g_sld = 10 - 45 + 2.43 + 45 = 12.43 > g_min = 2 -> yields.
    assert hidas_should_yield(10.0, 25.0, 25.0)
    # Level merger, g_f = 0.5, equal speeds: g_sld = 2.93 > 2 -> yields.
    assert hidas_should_yield(0.5, 25.0, 25.0)
    # Faster follower 30 vs 25, g_f = 5: g_sld = 5 - 54 + 2.43 + 45 = -1.57;
    # g_f_min = 2 + 0.9 * 5 = 6.5 -> does not yield.
    assert not hidas_should_yield(5.0, 30.0, 25.0)
    # With v_f - v_s = 5 the rule is g_f + 2.43 - 9 > 6.5, i.e. g_f > 13.07: 13.0 no, 13.2 yes.
    assert not hidas_should_yield(13.0, 30.0, 25.0)
    assert hidas_should_yield(13.2, 30.0, 25.0)
    # Slower follower 20 vs merger 25, g_f = 0: g_sld = 0 - 36 + 2.43 + 45 = 11.43 > 2 -> yields.
    assert hidas_should_yield(0.0, 20.0, 25.0)
    # Equal speeds, g_f = -0.5 (merger overlapping the follower): g_sld = 1.93 < 2 -> does not yield.
    assert not hidas_should_yield(-0.5, 25.0, 25.0)
    # Other parameters: dv = 3, b_f = 3 -> Dt = 1, g_sld = g_f - (20 - 1.5) + 20 = g_f + 1.5;
    # g_min = 1: yields iff g_f > -0.5.
    assert hidas_should_yield(-0.4, 20.0, 20.0, dv=3.0, b_f=3.0, g_min=1.0)
    assert not hidas_should_yield(-0.6, 20.0, 20.0, dv=3.0, b_f=3.0, g_min=1.0)


def test_idm_matches_highway_env_vehicle() -> None:
    """The vectorised IDM is ``IDMVehicle.acceleration`` (with Treiber's floor on the desired gap) on the main lane."""
    env = make()
    env.reset(seed=0)
    road = road_of(env)
    idm = road.idm
    rng = np.random.default_rng(0)
    speeds = rng.uniform(0.0, 40.0, size=50)
    gaps = rng.uniform(6.0, 80.0, size=50)
    leader_speeds = rng.uniform(0.0, 40.0, size=50)
    vectorised = idm_acceleration(speeds, gaps, leader_speeds, idm)
    for i in range(50):
        follower = HidasIDMVehicle(road, [0.0, 0.0], float(speeds[i]), idm, HidasParams())
        leader = HidasIDMVehicle(road, [float(gaps[i]), 0.0], float(leader_speeds[i]), idm, HidasParams())
        expected = float(np.clip(follower.acceleration(follower, leader), -idm.acc_limit, idm.acc_limit))
        assert vectorised[i] == pytest.approx(expected, abs=1e-9)
        assert idm_acceleration(float(speeds[i]), float(gaps[i]), float(leader_speeds[i]), idm) == pytest.approx(expected)


@pytest.mark.parametrize("density, speed", CORNERS)
def test_calibration_equilibrium(density: float, speed: float) -> None:
    params = calibrate_idm(density, speed)
    assert 0.2 < params.time_wanted < 1.0
    assert idm_acceleration(speed, 1000.0 / density, speed, params) == pytest.approx(0.0, abs=1e-9)


def test_ego_float_math_matches_highway_env() -> None:
    """The ego's steering, kinematics and lane detection are highway-env's formulas in float math."""
    env = make()
    env.reset(seed=0)
    road = road_of(env)
    rng = np.random.default_rng(1)
    for lane_index, longitudinal in [(("j", "k", 0), 40.0), (("k", "b", 0), 30.0), (MERGE_LANE, 60.0), (("b", "c", 0), 20.0)]:
        lane = road.network.get_lane(lane_index)
        for _ in range(5):
            position = lane.position(longitudinal + rng.uniform(-5, 5), rng.uniform(-1.5, 1.5))
            heading = lane.heading_at(longitudinal) + rng.uniform(-0.2, 0.2)
            ego = MergeEgoVehicle(road, position, heading, rng.uniform(5.0, 35.0))
            target = ("b", "c", 0) if lane_index == MERGE_LANE else ego.lane_index
            assert ego.steering_control(target) == pytest.approx(ControlledVehicle.steering_control(ego, target), abs=1e-9)
            ego.action = {"steering": ego.steering_control(target), "acceleration": rng.uniform(-3, 3)}
            twin = copy.deepcopy(ego)
            ego.step(0.1)
            Vehicle.step(twin, 0.1)
            np.testing.assert_allclose(ego.position, twin.position, atol=1e-9)
            assert (ego.heading, ego.speed) == pytest.approx((twin.heading, twin.speed))
            assert ego.lane_index == twin.lane_index  # full search over all lanes in highway-env


# -- scripted Hidas scenes -----------------------------------------------------------------------------
def test_follower_yields_to_level_merger() -> None:
    env = make(normalize_obs=False, simulation_frequency=10, policy_frequency=10, horizon=100)  # one frame per step
    env.set_task({"density": 30.0, "speed": 25.0})
    env.reset(seed=0)
    road = road_of(env)
    # The ego on the merge lane at x = 250, 25 m/s, accelerating; the follower about level with it (centre 7 m
    # behind: g_f = 2 m) at 25 m/s: g_sld = 2 + 2.43 = 4.43 > g_min = 2, it yields. Its real leader is 60 m ahead
    # at 25 m/s (IDM alone would accelerate it).
    env.place_vehicles(250.0, 25.0, [210.0, 243.0, 303.0], [25.0, 25.0, 25.0], ego_lane=MERGE_LANE, mode=ACCELERATE)
    road.act()
    follower = road.traffic[1]
    assert follower.yielding and road.follower is follower
    assert float(idm_acceleration(25.0, 60.0, 25.0, road.idm)) > 0
    assert road.acc[1] == pytest.approx(-1.5)  # IDM for the merger 7 m ahead is far below -b_f: capped at b_f
    # the ego changes lane: the follower keeps yielding, brakes at most b_f while the ego is on the ramp
    follower_acc = []
    for _ in range(10):
        _, _, terminated, _, info = env.step(LANE_LEFT)
        assert not terminated and info["cost"] == 0.0
        if info["merge_step"]:
            merge_info = info
            break
        assert follower.yielding
        follower_acc.append(float(road.acc[road.traffic.index(follower)]))
    else:
        pytest.fail("the ego did not merge")
    assert len(follower_acc) >= 2 and min(follower_acc) >= -1.5 - 1e-9
    assert env.vehicle.lane_index in MAIN_LANES
    assert merge_info["merged"] and merge_info["rear_deceleration"] > 0.0
    for _ in range(30):  # and nobody crashes afterwards
        _, _, terminated, _, info = env.step(CRUISE)
        assert not terminated and info["cost"] == 0.0 and info["merged"]
    assert not follower.yielding


def test_fast_follower_with_small_gap_does_not_yield() -> None:
    env = make(normalize_obs=False)
    env.set_task({"density": 30.0, "speed": 25.0})
    env.reset(seed=0)
    road = road_of(env)
    # follower 30 m/s, 10 m behind the ego's centre (g_f = 5 m), ego 25 m/s: g_sld = -1.57 < 6.5, it ignores the ego
    env.place_vehicles(250.0, 25.0, [180.0, 240.0, 300.0], [30.0, 30.0, 30.0], ego_lane=MERGE_LANE)
    road.act()
    assert not road.traffic[1].yielding
    assert road.acc[1] == pytest.approx(float(idm_acceleration(30.0, 60.0, 30.0, road.idm)))
    # the same scene with a slower follower (g_sld = 5 - 36 + 2.43 + 45 = 16.43 > 2): it yields
    env.place_vehicles(250.0, 25.0, [180.0, 240.0, 300.0], [20.0, 20.0, 20.0], ego_lane=MERGE_LANE)
    road.act()
    assert road.traffic[1].yielding


# -- calibration ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("density, speed", CORNERS)
def test_traffic_calibration_at_task_corners(density: float, speed: float) -> None:
    """Main-lane traffic alone (60 s, from the jittered start) drives at the task speed with the task spacing;
    highway-env's default IDM (T = 1.5 s, d0 = 10 m) does not hold the density."""
    env = make()
    env.set_task({"density": density, "speed": speed})
    for params in (None, IDMParams(desired_speed=1.3 * speed, time_wanted=1.5, distance_wanted=10.0)):
        mean_speed, mean_spacing = measure_main_lane_traffic(env, params)
        if params is None:
            assert mean_speed == pytest.approx(speed, rel=0.10)
            assert mean_spacing == pytest.approx(1000.0 / density, rel=0.10)
        else:
            assert mean_spacing > 1.5 * 1000.0 / density


def scripted_merge_policy(env: HighwayMergeMetaEnv) -> int:
    """Cruise; change lane once on the merge lane."""
    return LANE_LEFT if env.vehicle.lane_index == MERGE_LANE else CRUISE


@pytest.mark.parametrize("density, speed", CORNERS)
def test_traffic_calibration_in_episodes(density: float, speed: float) -> None:
    """With the ego merging (Hidas yielding included), the main-lane mean speed stays within 10% of the task speed
    and the mean spacing within 10% of 1000 / density."""
    env = make()
    env.set_task({"density": density, "speed": speed})
    speeds, spacings = [], []
    for seed in range(2):
        env.reset(seed=seed)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(scripted_merge_policy(env))
            done = terminated or truncated
            road = road_of(env)
            speeds.append(road.v.mean())
            spacings.append(np.diff(road.x).mean())
    assert float(np.mean(speeds)) == pytest.approx(speed, rel=0.10)
    assert float(np.mean(spacings)) == pytest.approx(1000.0 / density, rel=0.10)


# -- costs, b_min, reward ------------------------------------------------------------------------------
def test_end_of_lane_crash_costs_one() -> None:
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    total_cost, steps = 0.0, 0
    while True:  # accelerate along the ramp, never change lane: hits the end of the merge lane
        _, reward, terminated, truncated, info = env.step(ACCELERATE)
        total_cost += info["cost"]
        steps += 1
        if terminated or truncated:
            break
    assert terminated and info["crashed"] and info["cost"] == 1.0 and total_cost == 1.0
    assert env.unwrapped.vehicle.position[0] <= END_OF_LANE
    assert info["rewards"]["collision"] == pytest.approx(-(10.0 + 1.05 * (60 - steps)))


def test_failure_to_merge_at_horizon_costs_one() -> None:
    env = make(horizon=30)
    env.reset(seed=0)
    for t in range(30):  # brake to a stop on the ramp (from 15-20 m/s at 1.5 m/s^2: within 14 s)
        _, reward, terminated, truncated, info = env.step(DECELERATE)
        assert info["ego_speed"] >= 0.0
        if t < 29:
            assert info["cost"] == 0.0 and not terminated and not truncated
    assert terminated and not truncated and info["failed_to_merge"] and info["cost"] == 1.0
    assert info["rewards"]["collision"] == pytest.approx(-10.0)
    assert env.vehicle.speed == 0.0


def test_side_collision_costs_one() -> None:
    env = make()
    env.reset(seed=0)
    # a main-lane vehicle level with the ego (0.5 m behind, g_f = -4.5 m: it does not yield); the ego cuts in
    env.place_vehicles(250.0, 25.0, [249.5, 300.0], [25.0, 25.0], ego_lane=MERGE_LANE)
    for _ in range(6):
        _, _, terminated, _, info = env.step(LANE_LEFT)
        if terminated:
            break
    assert terminated and info["crashed"] and info["cost"] == 1.0


def test_b_min_on_scripted_merge() -> None:
    # B(x0=30, v0=20; x1=0, v1=25) = (625 - 400) / 60 = 3.75 m/s^2; a slower follower needs none (negative)
    assert min_braking(30.0, 20.0, 0.0, 25.0) == pytest.approx(3.75)
    assert min_braking(30.0, 25.0, 0.0, 20.0) == pytest.approx(-3.75)
    env = make(simulation_frequency=10, policy_frequency=10, horizon=100)  # one frame per step
    env.set_task({"density": 40.0, "speed": 25.0})
    env.reset(seed=0)
    road = road_of(env)
    env.place_vehicles(250.0, 24.0, [200.0, 236.0, 270.0, 300.0], [25.0, 26.0, 22.0, 25.0], ego_lane=MERGE_LANE)
    for _ in range(40):
        _, _, terminated, _, info = env.step(LANE_LEFT)
        assert not terminated
        if info["merge_step"]:
            break
    else:
        pytest.fail("the ego did not merge")
    ego = env.vehicle
    ego_x, ego_v = float(ego.position[0]), ego.speed * math.cos(ego.heading)
    front, rear = road.neighbours_x(ego_x)
    assert front is not None and rear is not None
    xf, vf, xr, vr = float(road.x[front]), float(road.v[front]), float(road.x[rear]), float(road.v[rear])
    expected = max((ego_v**2 - vf**2) / (2 * (xf - ego_x)), (vr**2 - ego_v**2) / (2 * (ego_x - xr)))
    assert info["b_min"] == pytest.approx(expected)
    rear_acc = float(idm_acceleration(vr, ego_x - xr, ego_v, road.idm))
    assert info["rear_deceleration"] == pytest.approx(max(-rear_acc, 0.0))
    assert info["rewards"]["rear_deceleration"] == pytest.approx(-0.25 * info["rear_deceleration"])


def test_reward_components_and_side_effect_free() -> None:
    env = make(normalize_obs=False)
    env.set_task({"density": 40.0, "speed": 30.0})
    env.reset(seed=0)
    _, reward, _, _, info = env.step(ACCELERATE)
    assert reward == pytest.approx(sum(info["rewards"].values()))
    ego = env.vehicle
    front, _ = road_of(env).neighbours_x(float(ego.position[0]))
    assert front is not None
    gap = float(road_of(env).x[front] - ego.position[0])
    assert info["rewards"]["speed"] == pytest.approx(-0.05 * min(abs(ego.speed - 30.0), 10.0))
    assert info["rewards"]["gap"] == pytest.approx(-0.01 * min(abs(gap - 25.0), 50.0))
    assert info["rewards"]["action"] == pytest.approx(-0.02)
    state = (ego.position.copy(), ego.speed, road_of(env).x.copy(), env._merged)
    assert env._rewards(ACCELERATE) == env._rewards(ACCELERATE) == info["rewards"]
    np.testing.assert_array_equal(state[0], ego.position)
    assert state[1] == ego.speed and env._merged == state[3]
    np.testing.assert_array_equal(state[2], road_of(env).x)


def test_longitudinal_mode_persists_and_speed_never_negative() -> None:
    env = make()
    env.reset(seed=0)
    v0 = env.vehicle.speed
    env.step(ACCELERATE)
    env.step(LANE_LEFT)  # a lane change keeps the mode: still +1.5 m/s^2 over 0.5 s
    assert env.vehicle.speed == pytest.approx(v0 + 1.5, abs=1e-9)
    for _ in range(30):
        obs, _, terminated, _, info = env.step(DECELERATE)
        assert env.vehicle.speed >= 0.0 and obs[2] >= 0.0
        assert not terminated
    assert env.vehicle.speed == 0.0


def test_jam_behind_stopped_ego_never_overlaps() -> None:
    """An ego braking to a stop on the main lane jams the traffic behind it; main-lane vehicles never overlap."""
    env = make()
    env.set_task({"density": 50.0, "speed": 25.0})
    env.reset(seed=0)
    env.place_vehicles(250.0, 25.0, 250.0 - 20.0 * np.arange(1, 8), [25.0] * 7, ego_lane=("b", "c", 0), mode=DECELERATE)
    road = road_of(env)
    for _ in range(50):
        _, _, terminated, truncated, _ = env.step(DECELERATE)
        assert np.diff(road.x).min() >= Vehicle.LENGTH - 1e-9
        if terminated or truncated:
            break
    _, rear = road.neighbours_x(float(env.vehicle.position[0]))
    assert not env.vehicle.crashed and env.vehicle.speed == 0.0
    assert rear is not None and road.v[rear] < 0.5 and (road.v < 0.5).sum() >= 5  # a standing queue


def test_render_rgb_array() -> None:
    env = gym.make(ENV_ID, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(3):
        env.step(CRUISE)
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.mean() > 20 and len(np.unique(frame.reshape(-1, 3), axis=0)) > 5
    assert (frame.reshape(-1, 3) == (50, 200, 0)).all(axis=1).any()  # the green ego is drawn
    env.close()
