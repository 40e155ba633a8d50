"""The merge road: highway-env's ``Road`` whose main-lane traffic is integrated as numpy arrays.

Main-lane vehicles are :class:`~sb3_pearl.envs.highway_merge.hidas.HidasIDMVehicle` objects
(rendering, collisions and the Hidas decision use them) whose longitudinal dynamics are integrated
as numpy arrays by :class:`MergeRoad` (they drive on one straight lane: no steering, leaders from
the x-sorted order); only the ego is checked for collisions; traffic exists only in a window around
the ego. :func:`measure_main_lane_traffic` measures that traffic alone (calibration checks).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

from sb3_pearl.envs.highway_merge.actions import CRUISE
from sb3_pearl.envs.highway_merge.geometry import MAIN_LANES, LaneFrame
from sb3_pearl.envs.highway_merge.hidas import YIELDING_COLOR, HidasIDMVehicle, HidasParams
from sb3_pearl.envs.highway_merge.traffic import IDMParams, idm_acceleration

if TYPE_CHECKING:
    from sb3_pearl.envs.highway_merge.ego import MergeEgoVehicle
    from sb3_pearl.envs.highway_merge.env import HighwayMergeMetaEnv


class MergeRoad(Road):
    """
    The merge road: highway-env's ``Road`` whose main-lane traffic is integrated as arrays.

    Main-lane vehicles are sorted by x (they never overtake on one lane); each follows the next
    one, the head follows a phantom leader that drives at the task speed one spacing ahead.
    ``act()`` computes all commands from one snapshot, ``step(dt)`` integrates them and checks the
    ego (only) for collisions; :meth:`sync` writes the arrays into the vehicle objects (done on
    the vehicles involved in a collision check or a Hidas decision at once, on all of them once per
    policy step, which is enough for rendering).

    :param network: the road network
    :param np_random: random generator (spawn jitter)
    :param lane_candidates: lane index -> lanes the ego can be on next (itself first)
    :param lane_frames: lane index -> :class:`LaneFrame`
    """

    def __init__(
        self,
        network: RoadNetwork,
        np_random: np.random.Generator,
        lane_candidates: dict[LaneIndex, list[LaneIndex]],
        lane_frames: dict[LaneIndex, LaneFrame],
    ) -> None:
        super().__init__(network=network, np_random=np_random, neighbour_vehicles_connected_lanes=True)
        self._lane_candidates = lane_candidates
        self.lane_frames = lane_frames
        self.ego: MergeEgoVehicle | None = None
        self.traffic: list[HidasIDMVehicle] = []
        self.x = np.zeros(0)
        self.v = np.zeros(0)
        self.acc = np.zeros(0)
        self.ego_acc: float | None = None
        self.phantom_x = 0.0
        self.idm = IDMParams(desired_speed=30.0, time_wanted=1.0, distance_wanted=7.0)
        self.hidas = HidasParams()
        self.task_speed = 30.0
        self.spacing = 30.0
        self.obstacle: Obstacle | None = None
        self.follower: HidasIDMVehicle | None = None
        self._collision_radius = 0.0

    def lane_candidates(self, lane_index: LaneIndex) -> list[LaneIndex]:
        return self._lane_candidates[lane_index]

    # -- traffic bookkeeping --------------------------------------------------------------------
    def set_traffic(self, xs: np.ndarray, vs: np.ndarray) -> None:
        """Replace the traffic by vehicles at ``xs`` with speeds ``vs``; the phantom leads one spacing ahead."""
        order = np.argsort(xs)
        self.x = np.asarray(xs, dtype=np.float64)[order].copy()
        self.v = np.asarray(vs, dtype=np.float64)[order].copy()
        self.traffic = [self._make_vehicle(x, v) for x, v in zip(self.x.tolist(), self.v.tolist())]
        self.phantom_x = (float(self.x[-1]) if len(self.x) else 0.0) + self.spacing
        self._keep_phantom_ahead_of_ego()
        self._refresh_vehicles()

    def _keep_phantom_ahead_of_ego(self) -> None:
        """Downstream traffic stays at least a spacing ahead of an ego that drives ahead of all traffic on the main lane."""
        ego = self.ego
        if ego is not None and ego.lane_index in MAIN_LANES:
            ego_x = float(ego.position[0])
            if not len(self.x) or self.x[-1] < ego_x:
                self.phantom_x = max(self.phantom_x, ego_x + self.spacing)

    def _make_vehicle(self, x: float, v: float) -> HidasIDMVehicle:
        return HidasIDMVehicle(self, [x, 0.0], v, self.idm, self.hidas)

    def _refresh_vehicles(self) -> None:
        self.vehicles = ([self.ego] if self.ego is not None else []) + list(self.traffic)
        self.acc = np.zeros_like(self.x)
        self.follower = None

    def sync(self, index: int | None = None) -> None:
        """
        Write the array state into the vehicle objects.

        :param index: one vehicle, or all of them (``None``)
        """
        if index is not None:
            vehicle = self.traffic[index]
            vehicle.position[0] = float(self.x[index])
            vehicle.speed = float(self.v[index])
            return
        for vehicle, x, v, a in zip(self.traffic, self.x.tolist(), self.v.tolist(), self.acc.tolist()):
            vehicle.position[0] = x
            vehicle.speed = v
            vehicle.action["acceleration"] = a
            if vehicle is not self.follower:
                vehicle.yielding = False
            vehicle.color = YIELDING_COLOR if vehicle.yielding else None

    def neighbours_x(self, x: float) -> tuple[int | None, int | None]:
        """Indices of the main-lane vehicles right ahead of and right behind position ``x``."""
        k = int(self.x.searchsorted(x))
        front = k if k < len(self.x) else None
        rear = k - 1 if k >= 1 else None
        return front, rear

    def maintain_window(self, back: float, front: float, jitter: float) -> None:
        """
        Keep traffic in ``[ego_x - back, ego_x + front]``: spawn at the ends at the task spacing
        (x ``U[1 - jitter, 1 + jitter]``), drop vehicles that left the window by more than a spacing.
        """
        assert self.ego is not None
        ego_x = float(self.ego.position[0])
        s = self.spacing
        changed = False
        # behind: drop, then spawn upstream of the tail at the tail's speed
        while len(self.x) and self.x[0] < ego_x - back - s and self.traffic[0] is not self.follower:
            self.x, self.v = self.x[1:], self.v[1:]
            self.traffic.pop(0)
            changed = True
        while len(self.x) and self.x[0] - s >= ego_x - back:
            x_new = float(self.x[0] - s * self.np_random.uniform(1 - jitter, 1 + jitter))
            self.x = np.concatenate(([x_new], self.x))
            self.v = np.concatenate(([self.v[0]], self.v))
            self.traffic.insert(0, self._make_vehicle(x_new, float(self.v[0])))
            changed = True
        # ahead: drop (the phantom takes the dropped head's place), then spawn at the phantom
        while len(self.x) > 1 and self.x[-1] > ego_x + front + s:
            self.phantom_x = float(self.x[-1])
            self.x, self.v = self.x[:-1], self.v[:-1]
            self.traffic.pop()
            changed = True
        self._keep_phantom_ahead_of_ego()
        while self.phantom_x < ego_x + front:
            self.x = np.append(self.x, self.phantom_x)
            self.v = np.append(self.v, self.task_speed)
            self.traffic.append(self._make_vehicle(self.phantom_x, self.task_speed))
            self.phantom_x += s * self.np_random.uniform(1 - jitter, 1 + jitter)
            changed = True
        if changed:
            follower = self.follower
            self._refresh_vehicles()
            self.follower = follower if follower in self.traffic else None

    # -- dynamics -------------------------------------------------------------------------------
    def act(self) -> None:
        """Commands of every vehicle from the current snapshot (the ego's cruise command included)."""
        x, v = self.x, self.v
        n = len(x)
        gap = np.empty(n)
        lead_v = np.empty(n)
        if n:
            gap[:-1] = x[1:] - x[:-1]
            lead_v[:-1] = v[1:]
            gap[-1] = self.phantom_x - x[-1]
            lead_v[-1] = self.task_speed
        ego = self.ego
        follower_idx = None
        self.ego_acc = None
        if ego is not None and not ego.crashed:
            ego_x = float(ego.position[0])
            ego_vx = ego.speed * math.cos(ego.heading)
            front, rear = self.neighbours_x(ego_x)
            if rear is not None:
                if ego.lane_index in MAIN_LANES:  # the ego is a real leader
                    gap[rear] = ego_x - x[rear]
                    lead_v[rear] = ego_vx
                else:
                    follower_idx = rear
            acc = idm_acceleration(v, gap, lead_v, self.idm)
            if follower_idx is not None:
                self.sync(follower_idx)
                follower = self.traffic[follower_idx]
                if self.follower is not None and self.follower is not follower:
                    self.follower.yielding = False
                acc[follower_idx] = follower.merge_acceleration(float(acc[follower_idx]), ego)
                self.follower = follower
            elif self.follower is not None:
                self.follower.yielding = False
                self.follower = None
            if ego.mode == CRUISE:
                self.ego_acc = self._ego_cruise(ego, ego_x, ego_vx, front)
        else:
            acc = idm_acceleration(v, gap, lead_v, self.idm)
        self.acc = acc

    def _ego_cruise(self, ego: MergeEgoVehicle, ego_x: float, ego_vx: float, front: int | None) -> float:
        """IDM for the ego with the task's parameters: its leader on its lane and, while changing lane, on the target lane."""
        on_main = ego.lane_index in MAIN_LANES
        speed = ego.speed
        acc = idm_acceleration(speed, math.inf, 0.0, self.idm)
        if (on_main or ego.target_lane_index in MAIN_LANES) and front is not None:
            acc = min(acc, idm_acceleration(speed, float(self.x[front]) - ego_x, float(self.v[front]), self.idm))
        if not on_main and self.obstacle is not None:
            acc = min(acc, idm_acceleration(speed, float(self.obstacle.position[0]) - ego_x, 0.0, self.idm))
        return acc

    def step(self, dt: float) -> None:
        """Integrate one frame (positions with the old speeds, as ``Vehicle.step``) and check the ego's collisions."""
        ego = self.ego
        if ego is not None:
            ego.control(self.ego_acc, dt)
            ego.step(dt)
        self.x = self.x + self.v * dt
        self.v = np.maximum(self.v + self.acc * dt, 0.0)
        self.phantom_x += self.task_speed * dt
        n = len(self.x)
        if n > 1 and float((self.x[1:] - self.x[:-1]).min()) < Vehicle.LENGTH:
            self._no_overlap()
        if ego is not None:
            self._ego_collisions(ego, dt)

    def _no_overlap(self) -> None:
        """
        Keep main-lane vehicles at least a car length apart (bumper contact), matching the leader's speed.

        NPC-NPC collisions are not checked; explicit Euler with IDM's clipped braking can let a jam
        (behind an ego stopped on the main lane) compress a few decimetres past contact. Applied from
        the head backwards: ``x_i <= min_{j >= i} (x_j - (j - i) L)``.
        """
        offsets = np.arange(len(self.x)) * Vehicle.LENGTH
        clamped = np.minimum.accumulate((self.x - offsets)[::-1])[::-1] + offsets
        moved = clamped < self.x
        moved[-1] = False
        self.x = clamped
        self.v[:-1] = np.where(moved[:-1], np.minimum(self.v[:-1], self.v[1:]), self.v[:-1])

    def _ego_collisions(self, ego: MergeEgoVehicle, dt: float) -> None:
        """The ego against nearby traffic and objects, behind highway-env's own spherical pre-check (``_is_colliding``)."""
        ego_x, ego_y = float(ego.position[0]), float(ego.position[1])
        radius = ego.diagonal + ego.speed * dt  # (ego.diagonal + other.diagonal) / 2 + ego.speed * dt, equal diagonals
        if abs(ego_y) < radius:
            lo = int(self.x.searchsorted(ego_x - radius))
            hi = int(self.x.searchsorted(ego_x + radius))
            for i in range(lo, hi):
                self.sync(i)
                ego.handle_collisions(self.traffic[i], dt)
        for obj in self.objects:
            if abs(float(obj.position[0]) - ego_x) < radius + obj.diagonal:
                ego.handle_collisions(obj, dt)


def measure_main_lane_traffic(
    env: HighwayMergeMetaEnv, idm: IDMParams | None = None, seed: int = 0, seconds: float = 60.0, warmup: float = 30.0
) -> tuple[float, float]:
    """
    Mean speed and spacing of the main-lane traffic alone (no ego), for calibration checks.

    :param env: the env, with the task to measure already set
    :param idm: IDM parameters to use instead of the task's calibrated ones (e.g. highway-env's defaults)
    :param seed: reset seed
    :param seconds: simulated time
    :param warmup: seconds left out of the averages
    :return: mean speed [m/s] and mean spacing (centre to centre) [m]
    """
    env.reset(seed=seed)
    road = env.road
    assert isinstance(road, MergeRoad)
    if idm is not None:
        road.idm = idm
    road.ego = None
    dt = 1.0 / env.config["simulation_frequency"]
    speeds, spacings = [], []
    for frame in range(round(seconds / dt)):
        road.act()
        road.step(dt)
        if frame >= round(warmup / dt):
            speeds.append(road.v.mean())
            spacings.append(np.diff(road.x).mean())
    return float(np.mean(speeds)), float(np.mean(spacings))
