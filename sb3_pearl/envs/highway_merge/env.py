"""The ``HighwayMergeMeta-v0`` env, :class:`HighwayMergeMetaEnv`, and its observation scale.

The observation, actions, reward, ``info`` and episode rules are described in the package docstring
(:mod:`sb3_pearl.envs.highway_merge`) and in ``docs/highway_merge.md``.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.road import LaneIndex
from highway_env.vehicle.objects import Obstacle

from sb3_pearl.envs.checks import check_count, check_number, check_pair_range
from sb3_pearl.envs.highway_merge.actions import ACCELERATE, CRUISE, DECELERATE, LANE_LEFT
from sb3_pearl.envs.highway_merge.ego import MergeEgoVehicle
from sb3_pearl.envs.highway_merge.geometry import (
    END_OF_LANE,
    LANE_WIDTH,
    MAIN_LANES,
    MERGE_LANE,
    MERGE_START,
    RAMP_LANES,
    RAMP_START,
    make_merge_network,
)
from sb3_pearl.envs.highway_merge.hidas import HidasParams, hidas_should_yield, min_braking
from sb3_pearl.envs.highway_merge.road import MergeRoad
from sb3_pearl.envs.highway_merge.traffic import IDMParams, calibrate_idm, idm_acceleration
from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task, refuse_non_finite_action

MPH = 0.44704
"""One mile per hour in m/s."""

OBS_LENGTH_SCALE = 100.0
OBS_SPEED_SCALE = 30.0
_OBS_SCALE = np.array(  # observation multipliers when normalize_obs
    [1 / OBS_LENGTH_SCALE, 1 / LANE_WIDTH, 1 / OBS_SPEED_SCALE, 1 / OBS_SPEED_SCALE]
    + [1.0, 1 / OBS_LENGTH_SCALE, 1 / LANE_WIDTH, 1 / OBS_SPEED_SCALE, 1 / OBS_SPEED_SCALE] * 4,
    dtype=np.float32,
)


class HighwayMergeMetaEnv(MetaTaskEnv, AbstractEnv):
    """
    Ramp merge into one main lane; the task is the traffic (density, speed). See the package docstring.

    :param density_range: task density range [veh/km]
    :param speed_range: task traffic speed range [m/s] (default 50-70 mph)
    :param horizon: episode length in policy steps (keep equal to ``max_episode_steps`` if you change it)
    :param simulation_frequency: simulation frequency [Hz]
    :param policy_frequency: policy frequency [Hz] (must divide ``simulation_frequency``)
    :param ego_speed_range: initial ego speed range [m/s]
    :param ego_start: initial ego x on the ramp [m] (the end of the merge lane is at 330 m)
    :param w_speed: weight of the speed error [1 / (m/s)]
    :param speed_error_clip: the speed error is clipped to this [m/s]
    :param w_gap: weight of the front-gap error [1 / m]
    :param gap_error_clip: the gap error is clipped to this [m]
    :param w_rear: weight of the rear vehicle's deceleration on the merge step [1 / (m/s^2)]
    :param collision_penalty: penalty of a crash or a failure to merge, plus the largest step penalty per skipped step
    :param accel_cost: cost of the accelerate / decelerate actions
    :param lane_change_cost: cost of the lane-change actions
    :param desired_speed_ratio: IDM desired speed / task speed (calibration,
        :func:`~sb3_pearl.envs.highway_merge.traffic.calibrate_idm`)
    :param jam_gap: IDM jam gap [m] (calibration)
    :param hidas_dv: Hidas' maximum speed decrease [m/s]
    :param hidas_b_f: Hidas' acceptable deceleration [m/s^2]
    :param hidas_g_min: Hidas' minimum gap [m]
    :param hidas_c: Hidas' acceptable-gap parameter [s]
    :param spawn_jitter: relative jitter of the spacing of spawned vehicles
    :param speed_jitter: relative jitter of the initial traffic speeds
    :param normalize_obs: scale the observation (see the package docstring)
    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"``
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 4}
    trajectory_info_keys: ClassVar[tuple[str, ...]] = ("merged", "crashed", "b_min", "rear_deceleration")
    step_trace_keys: ClassVar[tuple[str, ...]] = ("ego_speed",)
    WINDOW_BACK = 100.0
    WINDOW_FRONT = 150.0

    def __init__(
        self,
        density_range: tuple[float, float] = (30.0, 50.0),
        speed_range: tuple[float, float] = (50.0 * MPH, 70.0 * MPH),
        horizon: int = 60,
        simulation_frequency: int = 10,
        policy_frequency: int = 2,
        ego_speed_range: tuple[float, float] = (15.0, 20.0),
        ego_start: float = 30.0,
        w_speed: float = 0.05,
        speed_error_clip: float = 10.0,
        w_gap: float = 0.01,
        gap_error_clip: float = 50.0,
        w_rear: float = 0.25,
        collision_penalty: float = 10.0,
        accel_cost: float = 0.02,
        lane_change_cost: float = 0.05,
        desired_speed_ratio: float = 1.3,
        jam_gap: float = 2.0,
        hidas_dv: float = 2.7,
        hidas_b_f: float = 1.5,
        hidas_g_min: float = 2.0,
        hidas_c: float = 0.9,
        spawn_jitter: float = 0.1,
        speed_jitter: float = 0.03,
        normalize_obs: bool = True,
        render_mode: str | None = None,
    ) -> None:
        density_range = check_pair_range("density_range", density_range, min_open=True)
        speed_range = check_pair_range("speed_range", speed_range, min_open=True)
        ego_speed_range = check_pair_range("ego_speed_range", ego_speed_range)
        check_count("horizon", horizon, 1, hint="episode length in policy steps")
        check_count("simulation_frequency", simulation_frequency, 1, hint="Hz")
        check_count("policy_frequency", policy_frequency, 1, hint="Hz")
        if simulation_frequency % policy_frequency:
            raise ValueError(
                f"policy_frequency ({policy_frequency}) must divide simulation_frequency ({simulation_frequency})"
            )
        check_number("ego_start", ego_start, hint="initial ego x on the ramp [m]")
        if not RAMP_START <= ego_start < MERGE_START:
            raise ValueError(
                f"ego_start must be on the ramp before the merge lane, in [{RAMP_START}, {MERGE_START}), got {ego_start}"
            )
        weights = dict(
            w_speed=w_speed,
            speed_error_clip=speed_error_clip,
            w_gap=w_gap,
            gap_error_clip=gap_error_clip,
            w_rear=w_rear,
            collision_penalty=collision_penalty,
            accel_cost=accel_cost,
            lane_change_cost=lane_change_cost,
            jam_gap=jam_gap,
            hidas_g_min=hidas_g_min,
            hidas_c=hidas_c,
        )
        for name, value in weights.items():
            check_number(name, value, 0.0)
        for name, value in (("spawn_jitter", spawn_jitter), ("speed_jitter", speed_jitter)):
            check_number(name, value, 0.0, 1.0, high_open=True, hint="relative jitter")
        check_number("desired_speed_ratio", desired_speed_ratio, 1.0, low_open=True, hint="IDM desired speed / task speed")
        for name, value in (("hidas_dv", hidas_dv), ("hidas_b_f", hidas_b_f)):
            check_number(name, value, 0.0, low_open=True)
        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        self.density_range = (float(density_range[0]), float(density_range[1]))
        self.speed_range = (float(speed_range[0]), float(speed_range[1]))
        self.horizon = int(horizon)
        self.ego_speed_range = (float(ego_speed_range[0]), float(ego_speed_range[1]))
        self.ego_start = float(ego_start)
        self.w_speed = float(w_speed)
        self.speed_error_clip = float(speed_error_clip)
        self.w_gap = float(w_gap)
        self.gap_error_clip = float(gap_error_clip)
        self.w_rear = float(w_rear)
        self.collision_penalty = float(collision_penalty)
        self.accel_cost = float(accel_cost)
        self.lane_change_cost = float(lane_change_cost)
        self.step_floor = (
            self.w_speed * self.speed_error_clip + self.w_gap * self.gap_error_clip + max(accel_cost, lane_change_cost)
        )
        self.desired_speed_ratio = float(desired_speed_ratio)
        self.jam_gap = float(jam_gap)
        self.hidas = HidasParams(dv=hidas_dv, b_f=hidas_b_f, g_min=hidas_g_min, c=hidas_c)
        hidas_should_yield(10.0, 20.0, 20.0, dv=hidas_dv, b_f=hidas_b_f, g_min=hidas_g_min, c=hidas_c)  # validates
        self.spawn_jitter = float(spawn_jitter)
        self.speed_jitter = float(speed_jitter)
        self.normalize_obs = bool(normalize_obs)
        # the calibration must exist over the whole task box (densest, fastest corner is the hardest)
        calibrate_idm(self.density_range[1], self.speed_range[1], desired_speed_ratio=desired_speed_ratio, jam_gap=jam_gap)
        self._network, self._lane_candidates, self._lane_frames = make_merge_network()
        self._t = 0
        self._merged = False
        self._failed = False
        self._merge_event: dict[str, float] | None = None
        self._init_task()
        super().__init__(
            config={"simulation_frequency": int(simulation_frequency), "policy_frequency": int(policy_frequency)},
            render_mode=render_mode,
        )

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "observation": None,
                "action": None,
                "simulation_frequency": 10,
                "policy_frequency": 2,
                "neighbour_vehicles_connected_lanes": True,
                "screen_width": 800,
                "screen_height": 200,
                "centering_position": [0.4, 0.6],
                "scaling": 4.0,
            }
        )
        return config

    # -- task protocol ----------------------------------------------------------------------------
    def _sample_task(self, rng: np.random.Generator) -> Task:
        return {"density": float(rng.uniform(*self.density_range)), "speed": float(rng.uniform(*self.speed_range))}

    def _validate_task(self, task: Task) -> None:
        super()._validate_task(task)
        calibrate_idm(
            float(task["density"]), float(task["speed"]), desired_speed_ratio=self.desired_speed_ratio, jam_gap=self.jam_gap
        )

    @property
    def task_idm(self) -> IDMParams:
        """The calibrated IDM parameters of the task in force."""
        return calibrate_idm(
            self._task["density"], self._task["speed"], desired_speed_ratio=self.desired_speed_ratio, jam_gap=self.jam_gap
        )

    # -- spaces -----------------------------------------------------------------------------------
    def define_spaces(self) -> None:
        self.observation_type = None  # type: ignore[assignment]
        self.action_type = None  # type: ignore[assignment]
        if self.normalize_obs:
            ego_low = [0.0, -1.0, 0.0, -1.5]
            ego_high = [5.0, 4.0, 1.5, 1.5]
            other_low = [0.0, -2.5, -4.0, -2.0, -1.5]
            other_high = [1.0, 2.5, 4.0, 2.0, 1.5]
        else:
            ego_low = [0.0, -4.0, 0.0, -45.0]
            ego_high = [500.0, 16.0, 45.0, 45.0]
            other_low = [0.0, -250.0, -16.0, -60.0, -45.0]
            other_high = [1.0, 250.0, 16.0, 60.0, 45.0]
        low = np.array(ego_low + other_low * 4, dtype=np.float32)
        high = np.array(ego_high + other_high * 4, dtype=np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self.action_space = spaces.Discrete(5)

    # -- scene ------------------------------------------------------------------------------------
    def _reset(self) -> None:
        rng = self.np_random
        road = MergeRoad(self._network, rng, self._lane_candidates, self._lane_frames)
        road.record_history = self.config["show_trajectories"]
        road.idm = self.task_idm
        road.hidas = self.hidas
        road.task_speed = float(self._task["speed"])
        road.spacing = 1000.0 / float(self._task["density"])
        obstacle = Obstacle(road, [END_OF_LANE, LANE_WIDTH])
        road.objects.append(obstacle)
        road.obstacle = obstacle
        approach = self._network.get_lane(("j", "k", 0))
        ego = MergeEgoVehicle(
            road, approach.position(self.ego_start - RAMP_START, 0.0), 0.0, float(rng.uniform(*self.ego_speed_range))
        )
        road.ego = ego
        self.road = road
        self.vehicle = ego
        # main-lane traffic: a jittered platoon at the task spacing, random phase with respect to the ego
        s, j = road.spacing, self.spawn_jitter
        xs = [self.ego_start + s * float(rng.uniform(0.0, 1.0))]
        while xs[-1] < self.ego_start + self.WINDOW_FRONT:
            xs.append(xs[-1] + s * float(rng.uniform(1 - j, 1 + j)))
        while xs[0] > self.ego_start - self.WINDOW_BACK:
            xs.insert(0, xs[0] - s * float(rng.uniform(1 - j, 1 + j)))
        vs = road.task_speed * rng.uniform(1 - self.speed_jitter, 1 + self.speed_jitter, size=len(xs))
        road.set_traffic(np.array(xs), vs)
        road.phantom_x = xs[-1] + s
        self._t = 0
        self._merged = False
        self._failed = False
        self._merge_event = None

    def place_vehicles(
        self,
        ego_x: float,
        ego_speed: float,
        traffic_x: list[float] | np.ndarray,
        traffic_speed: list[float] | np.ndarray,
        *,
        ego_lane: LaneIndex = MERGE_LANE,
        mode: int = CRUISE,
    ) -> np.ndarray:
        """
        Scripted scenes (tests, figures): put the ego on ``ego_lane`` at ``ego_x`` and replace the traffic.

        Call after ``reset()``; returns the new observation. Traffic ahead of the last vehicle is
        led by the phantom leader one task spacing ahead.

        :param ego_x: ego x [m]
        :param ego_speed: ego speed [m/s]
        :param traffic_x: main-lane vehicle x positions [m]
        :param traffic_speed: their speeds [m/s]
        :param ego_lane: lane index of the ego
        :param mode: ego longitudinal mode (0 accelerate, 1 decelerate, 2 cruise)
        :return: the observation
        """
        road = self.road
        assert isinstance(road, MergeRoad)
        lane = self._network.get_lane(ego_lane)
        longitudinal, _ = lane.local_coordinates(np.array([ego_x, 0.0]))
        ego = MergeEgoVehicle(road, lane.position(longitudinal, 0.0), lane.heading_at(longitudinal), float(ego_speed))
        ego.mode = mode
        road.ego = ego
        self.vehicle = ego
        road.set_traffic(np.asarray(traffic_x, dtype=np.float64), np.asarray(traffic_speed, dtype=np.float64))
        self._merged = ego.lane_index in MAIN_LANES
        return self._observe()

    # -- gymnasium API ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:  # type: ignore[override]
        super(AbstractEnv, self).reset(seed=seed, options=options)
        self._apply_pending_task()
        if options and "config" in options:
            self.configure(options["config"])
        self.update_metadata()
        self.time = self.steps = 0
        self.done = False
        self._reset()
        obs = self._observe()
        info = {"cost": 0.0, "crashed": False, "merged": False, "merge_step": False, "ego_speed": float(self.vehicle.speed)}
        if self.render_mode == "human":
            self.render()
        return obs, info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        refuse_non_finite_action(self, action)
        action = int(action)
        if not 0 <= action < 5:
            raise ValueError(f"action must be in 0..4, got {action}")
        road = self.road
        ego = self.vehicle
        assert isinstance(road, MergeRoad) and isinstance(ego, MergeEgoVehicle)
        frames = int(self.config["simulation_frequency"] // self.config["policy_frequency"])
        dt = 1.0 / self.config["simulation_frequency"]
        ego.command(action)
        self._merge_event = None
        for _ in range(frames):
            road.act()
            road.step(dt)
            self.steps += 1
            if ego.lane_index in RAMP_LANES and ego.position[0] >= END_OF_LANE - (ego.LENGTH + Obstacle.LENGTH) / 2:
                ego.crashed = True  # ran out of merge lane
            if not self._merged and ego.lane_index in MAIN_LANES:
                self._merged = True
                self._merge_event = self._merge_measures()
            if ego.crashed:
                break
        self.time += 1.0 / self.config["policy_frequency"]
        self._t += 1
        self._failed = not ego.crashed and not self._merged and self._t >= self.horizon
        road.maintain_window(self.WINDOW_BACK, self.WINDOW_FRONT, self.spawn_jitter)
        road.sync()

        obs = self._observe()
        rewards = self._rewards(action)
        reward = float(sum(rewards.values()))
        terminated = bool(ego.crashed or self._failed)
        truncated = not terminated and self._t >= self.horizon
        info: dict[str, Any] = {
            "cost": 1.0 if terminated else 0.0,
            "crashed": bool(ego.crashed),
            "failed_to_merge": self._failed,
            "merged": self._merged,
            "merge_step": self._merge_event is not None,
            "ego_speed": float(ego.speed),
            "action": action,
            "rewards": rewards,
        }
        if self._merge_event is not None:
            info.update(self._merge_event)
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, truncated, info

    def _merge_measures(self) -> dict[str, float]:
        """At the merge frame: the rear vehicle's IDM deceleration for the ego and the paper's b_min."""
        road, ego = self.road, self.vehicle
        assert isinstance(road, MergeRoad)
        ego_x, ego_v = float(ego.position[0]), float(ego.speed * math.cos(ego.heading))
        front, rear = road.neighbours_x(ego_x)
        b_min = -math.inf
        rear_acc = 0.0
        if front is not None:
            b_min = max(b_min, min_braking(float(road.x[front]), float(road.v[front]), ego_x, ego_v))
        if rear is not None:
            rear_x, rear_v = float(road.x[rear]), float(road.v[rear])
            b_min = max(b_min, min_braking(ego_x, ego_v, rear_x, rear_v))
            rear_acc = float(idm_acceleration(rear_v, ego_x - rear_x, ego_v, road.idm))
        return {"rear_deceleration": max(-rear_acc, 0.0), "b_min": b_min}

    def _observe(self) -> np.ndarray:
        road, ego = self.road, self.vehicle
        assert isinstance(road, MergeRoad)
        ex, ey = float(ego.position[0]), float(ego.position[1])
        cos_h, sin_h = math.cos(ego.heading), math.sin(ego.heading)
        evx, evy = ego.speed * cos_h, ego.speed * sin_h
        d_eol = max(END_OF_LANE - ex, 0.0) if ego.lane_index in RAMP_LANES else 0.0
        features = [d_eol, ey, evx, evy]
        dx = road.x - ex
        order = np.argsort(np.abs(dx))[:4]
        for i in order.tolist():
            features += [1.0, float(dx[i]), -ey, float(road.v[i]) - evx, -evy]
        features += [0.0] * (24 - len(features))
        obs = np.array(features, dtype=np.float32)
        if self.normalize_obs:
            obs *= _OBS_SCALE
        return np.clip(obs, self.observation_space.low, self.observation_space.high)  # type: ignore[attr-defined]

    # -- reward -----------------------------------------------------------------------------------
    def _rewards(self, action: Any) -> dict[str, float]:
        """Reward components of the last step (no side effects: reads the state and the step's merge event)."""
        road, ego = self.road, self.vehicle
        assert isinstance(road, MergeRoad)
        speed_error = min(abs(ego.speed * math.cos(ego.heading) - float(self._task["speed"])), self.speed_error_clip)
        front, _ = road.neighbours_x(float(ego.position[0]))
        if front is None:
            gap_error = self.gap_error_clip
        else:
            gap = float(road.x[front] - ego.position[0])
            gap_error = min(abs(gap - 1000.0 / float(self._task["density"])), self.gap_error_clip)
        rear = self._merge_event["rear_deceleration"] if self._merge_event is not None else 0.0
        failed = bool(ego.crashed) or self._failed
        action = int(action)
        cost = self.accel_cost if action in (ACCELERATE, DECELERATE) else self.lane_change_cost if action >= LANE_LEFT else 0.0
        return {
            "speed": -self.w_speed * speed_error,
            "gap": -self.w_gap * gap_error,
            "rear_deceleration": -self.w_rear * rear,
            "collision": -(self.collision_penalty + self.step_floor * max(self.horizon - self._t, 0)) if failed else 0.0,
            "action": -cost,
        }

    def _reward(self, action: Any) -> float:
        return float(sum(self._rewards(action).values()))

    def _is_terminated(self) -> bool:
        return bool(self.vehicle.crashed or self._failed)

    def _is_truncated(self) -> bool:
        return not self._is_terminated() and self._t >= self.horizon
