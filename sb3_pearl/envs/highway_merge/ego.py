"""The ego vehicle of the merge: persistent longitudinal modes, highway-env's lane controllers in float math."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from highway_env.road.lane import AbstractLane
from highway_env.road.road import LaneIndex, Road
from highway_env.vehicle.controller import ControlledVehicle

from sb3_pearl.envs.highway_merge.actions import ACCELERATE, ACTION_NAMES, CRUISE, DECELERATE
from sb3_pearl.envs.highway_merge.geometry import MERGE_LANE, LaneFrame, _wrap_to_pi
from sb3_pearl.envs.highway_merge.road import MergeRoad

EGO_COLOR = (50, 200, 0)
"""Colour of the ego (green)."""


def _not_zero(value: float, eps: float = 1e-2) -> float:
    if abs(value) > eps:
        return value
    return eps if value >= 0 else -eps


class MergeEgoVehicle(ControlledVehicle):
    """
    The ego: a longitudinal mode that persists (+1.5, -1.5 m/s^2 or IDM cruise), highway-env's lane
    keeping / lane change controllers, speed kept >= 0.

    ``steering_control``, ``step`` and ``on_state_update`` are highway-env's formulas in float math
    (``tests/test_envs_highway.py`` checks them against the originals).

    :param road: the road (a :class:`~sb3_pearl.envs.highway_merge.road.MergeRoad`)
    :param position: world position [m]
    :param heading: heading [rad]
    :param speed: initial speed [m/s]
    :param acceleration: magnitude of the accelerate / decelerate modes [m/s^2]
    """

    lane_index: LaneIndex
    target_lane_index: LaneIndex
    impact: np.ndarray | None

    def __init__(self, road: Road, position: Any, heading: float = 0.0, speed: float = 0.0, acceleration: float = 1.5) -> None:
        super().__init__(road, position, heading, speed)
        self.speed = float(speed)
        self.heading = float(heading)
        self.mode = CRUISE
        self.mode_acceleration = float(acceleration)
        self.color = EGO_COLOR
        self.frames: dict[LaneIndex, LaneFrame] = road.lane_frames if isinstance(road, MergeRoad) else {}

    def command(self, action: int) -> None:
        """
        Apply a policy action: set the longitudinal mode or the target lane.

        :param action: 0 accelerate, 1 decelerate, 2 cruise, 3 left, 4 right
        """
        if action in (ACCELERATE, DECELERATE, CRUISE):
            self.mode = action
        else:
            ControlledVehicle.act(self, ACTION_NAMES[action])  # highway-env's lane-change target logic
            self.target_lane_index = (self.target_lane_index[0], self.target_lane_index[1], int(self.target_lane_index[2]))

    def follow_road(self) -> None:
        """highway-env's lane following (next lane at the end of this one), but the closed merge lane never leads on."""
        if self.target_lane_index == MERGE_LANE:
            return
        frame = self.frames[self.target_lane_index]
        s, _ = frame.local(float(self.position[0]), float(self.position[1]))
        if s > frame.length - AbstractLane.VEHICLE_LENGTH / 2:
            super().follow_road()

    def control(self, idm_acc: float | None, dt: float) -> None:
        """
        Set this frame's steering and acceleration.

        :param idm_acc: the cruise (IDM) acceleration, used in cruise mode
        :param dt: the simulation step, to keep the speed >= 0
        """
        self.follow_road()
        if self.mode == ACCELERATE:
            acc = self.mode_acceleration
        elif self.mode == DECELERATE:
            acc = -self.mode_acceleration
        else:
            acc = 0.0 if idm_acc is None else idm_acc
        acc = max(acc, -self.speed / dt)  # never a negative speed
        self.action = {"steering": self.steering_control(self.target_lane_index), "acceleration": acc}

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        """``ControlledVehicle.steering_control`` in float math."""
        frame = self.frames[target_lane_index]
        speed = self.speed
        s, r = frame.local(float(self.position[0]), float(self.position[1]))
        future_heading = frame.heading_at(s + speed * self.TAU_PURSUIT)
        lateral_speed_command = -self.KP_LATERAL * r
        heading_command = math.asin(min(max(lateral_speed_command / _not_zero(speed), -1.0), 1.0))
        heading_ref = future_heading + min(max(heading_command, -math.pi / 4), math.pi / 4)
        heading_rate_command = self.KP_HEADING * _wrap_to_pi(heading_ref - self.heading)
        slip_angle = math.asin(min(max(self.LENGTH / 2 / _not_zero(speed) * heading_rate_command, -1.0), 1.0))
        steering = math.atan(2 * math.tan(slip_angle))
        return min(max(steering, -self.MAX_STEERING_ANGLE), self.MAX_STEERING_ANGLE)

    def step(self, dt: float) -> None:
        """``Vehicle.step`` (kinematic bicycle, crash handling, speed limits) in float math."""
        self.clip_actions()
        beta = math.atan(0.5 * math.tan(self.action["steering"]))
        angle = self.heading + beta
        self.position[0] += self.speed * math.cos(angle) * dt
        self.position[1] += self.speed * math.sin(angle) * dt
        if self.impact is not None:
            self.position += self.impact
            self.crashed = True
            self.impact = None
        self.heading += self.speed * math.sin(beta) / (self.LENGTH / 2) * dt
        self.speed += self.action["acceleration"] * dt
        self.on_state_update()

    def on_state_update(self) -> None:
        """Closest lane among the current lanes and their successors (not all lanes: a hot spot)."""
        if not self.road:
            return
        x, y = float(self.position[0]), float(self.position[1])
        if self.lane_index == self.target_lane_index:  # lane keeping: only the end of the lane can change it
            frame = self.frames[self.lane_index]
            s, _ = frame.local(x, y)
            if 0.0 <= s < frame.length:
                return
        best, best_dist = self.lane_index, math.inf
        for index in self.road.lane_candidates(self.lane_index):  # type: ignore[attr-defined,has-type]
            dist = self.frames[index].distance_with_heading(x, y, self.heading)
            if dist < best_dist:
                best, best_dist = index, dist
        self.lane_index = best
        self.lane = self.road.network.get_lane(best)
        if self.road.record_history:
            self.history.appendleft(self.create_from(self))
