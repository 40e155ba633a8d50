"""Hidas' (2005) merging model: the main-lane vehicle right behind a merger decides whether to yield.

While the ego is on the ramp, the main-lane vehicle right behind it (the *follower*) follows
:func:`hidas_should_yield`; :class:`HidasIDMVehicle` is the main-lane vehicle that carries the rule.
:func:`min_braking` is the paper's ``B_min`` measure of a merge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from highway_env.road.road import Road
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from sb3_pearl.envs.highway_merge.traffic import IDMParams, idm_acceleration

YIELDING_COLOR = (200, 200, 0)
"""Colour of a follower while it yields (the paper's figure)."""


def hidas_should_yield(
    g_f: float,
    v_f: float,
    v_s: float,
    *,
    dv: float = 2.7,
    b_f: float = 1.5,
    g_min: float = 2.0,
    c: float = 0.9,
) -> bool:
    """
    Hidas' (2005) courtesy-yielding rule: does the follower slow down for a merging vehicle?

    With ``Dt = dv / b_f``, the gap the follower would leave by slowing down is
    ``g_f_sld = g_f - (v_f Dt - b_f Dt^2 / 2) + v_s Dt`` and the gap it accepts is
    ``g_f_min = g_min + c (v_f - v_s)`` if ``v_f > v_s`` else ``g_min``. It yields iff
    ``g_f_sld > g_f_min``.

    :param g_f: clear gap from the follower's front bumper to the merger's rear bumper [m]
    :param v_f: follower speed [m/s]
    :param v_s: merger (subject) speed [m/s]
    :param dv: largest speed decrease the follower accepts [m/s] (paper: 2.7)
    :param b_f: deceleration the follower accepts [m/s^2] (paper: 1.5)
    :param g_min: minimum safe constant gap [m] (paper: 2.0)
    :param c: acceptable-gap parameter [s] (paper: 0.9)
    :return: whether the follower yields
    """
    if b_f <= 0 or dv <= 0:
        raise ValueError(f"hidas_should_yield: dv and b_f must be > 0, got dv={dv}, b_f={b_f}")
    dt = dv / b_f
    g_sld = g_f - (v_f * dt - b_f * dt * dt / 2.0) + v_s * dt
    g_accept = g_min + c * (v_f - v_s) if v_f > v_s else g_min
    return bool(g_sld > g_accept)


def min_braking(leader_x: float, leader_v: float, follower_x: float, follower_v: float) -> float:
    """
    The paper's ``B_min(veh_0, veh_1) = (v_1^2 - v_0^2) / (2 (x_0 - x_1))``: the constant deceleration
    the follower (1) needs to match the leader's (0) speed before closing the centre distance.

    :param leader_x: leader longitudinal position [m]
    :param leader_v: leader speed [m/s]
    :param follower_x: follower longitudinal position [m]
    :param follower_v: follower speed [m/s]
    :return: the braking [m/s^2] (negative: none needed)
    """
    return (follower_v**2 - leader_v**2) / (2.0 * max(leader_x - follower_x, 1e-6))


@dataclass(frozen=True)
class HidasParams:
    """Hidas' merging-model parameters (the paper's values, calibrated from video data by Hidas 2005)."""

    dv: float = 2.7
    b_f: float = 1.5
    g_min: float = 2.0
    c: float = 0.9


class HidasIDMVehicle(IDMVehicle):
    """
    A main-lane vehicle: IDM with per-task parameters, and Hidas' courtesy yielding to a merger.

    Its longitudinal state is integrated by :class:`~sb3_pearl.envs.highway_merge.road.MergeRoad`
    (vectorised over the lane); this
    object holds the synced state for rendering and collisions, and decides the merge response in
    :meth:`merge_acceleration` when it is the vehicle right behind a merging ego.

    :param road: the road
    :param position: world position [m]
    :param speed: initial speed [m/s]
    :param idm: the task's IDM parameters
    :param hidas: Hidas' parameters
    """

    def __init__(self, road: Road, position: Any, speed: float, idm: IDMParams, hidas: HidasParams) -> None:
        super().__init__(road, position, heading=0.0, speed=speed, target_speed=idm.desired_speed, enable_lane_change=False)
        self.idm = idm
        self.hidas = hidas
        self.TIME_WANTED = idm.time_wanted
        self.DISTANCE_WANTED = idm.distance_wanted
        self.COMFORT_ACC_MAX = idm.acc_max
        self.COMFORT_ACC_MIN = -idm.comfort_dec
        self.DELTA = idm.delta
        self.yielding = False

    def desired_gap(self, ego_vehicle: Vehicle, front_vehicle: Vehicle = None, projected: bool = True) -> float:
        """
        IDM desired gap with Treiber's floor on the dynamic part
        (see :func:`~sb3_pearl.envs.highway_merge.traffic.idm_acceleration`).
        """
        dv = (
            np.dot(ego_vehicle.velocity - front_vehicle.velocity, ego_vehicle.direction)
            if projected
            else ego_vehicle.speed - front_vehicle.speed
        )
        ab = -self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN
        dynamic = ego_vehicle.speed * self.TIME_WANTED + ego_vehicle.speed * dv / (2 * np.sqrt(ab))
        return float(self.DISTANCE_WANTED + max(dynamic, 0.0))

    def merge_acceleration(self, idm_acc: float, merger: Vehicle) -> float:
        """
        Acceleration of this vehicle while ``merger`` is on the ramp right ahead of it.

        It yields iff :func:`hidas_should_yield` says so: it then follows the merger as a leader
        with its braking for the merger capped at ``b_f``, and never brakes less than its IDM
        command for its real leader (``idm_acc``). Otherwise it ignores the merger.

        :param idm_acc: its IDM acceleration for its real leader [m/s^2]
        :param merger: the merging vehicle (the ego on the ramp)
        :return: its acceleration [m/s^2]
        """
        h = self.hidas
        gap = float(merger.position[0] - self.position[0])
        v_s = merger.speed * math.cos(merger.heading)
        g_f = gap - (self.LENGTH + merger.LENGTH) / 2.0
        self.yielding = hidas_should_yield(g_f, self.speed, v_s, dv=h.dv, b_f=h.b_f, g_min=h.g_min, c=h.c)
        if not self.yielding:
            return idm_acc
        acc_merger = idm_acceleration(self.speed, gap, v_s, self.idm)
        return min(idm_acc, max(acc_merger, -h.b_f))
