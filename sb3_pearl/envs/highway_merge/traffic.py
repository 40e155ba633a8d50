"""IDM car following of the main-lane traffic and its per-task calibration.

Main-lane traffic follows IDM (Treiber et al. 2000) with parameters calibrated per task so that it
really drives at the task speed with the task density (:func:`calibrate_idm`); the vectorised
:func:`idm_acceleration` is what :class:`~sb3_pearl.envs.highway_merge.road.MergeRoad` integrates.
``docs/highway_merge.md`` ("Traffic and tasks") has the calibration table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle


@dataclass(frozen=True)
class IDMParams:
    """
    IDM parameters of the main-lane traffic of one task (the conventions of highway-env's ``IDMVehicle``).

    :param desired_speed: IDM desired speed v0 [m/s]
    :param time_wanted: desired time headway T [s]
    :param distance_wanted: jam distance d0, centre to centre (vehicle length + jam gap) [m]
    :param acc_max: comfortable acceleration a [m/s^2]
    :param comfort_dec: comfortable deceleration b [m/s^2] (positive)
    :param delta: velocity exponent
    :param acc_limit: the command is clipped to +-acc_limit [m/s^2] (``IDMVehicle.ACC_MAX``)
    """

    desired_speed: float
    time_wanted: float
    distance_wanted: float
    acc_max: float = IDMVehicle.COMFORT_ACC_MAX
    comfort_dec: float = -IDMVehicle.COMFORT_ACC_MIN
    delta: float = IDMVehicle.DELTA
    acc_limit: float = IDMVehicle.ACC_MAX


def idm_acceleration(speed: Any, gap: Any, leader_speed: Any, params: IDMParams) -> Any:
    """
    IDM acceleration (Treiber et al. 2000), for floats or numpy arrays, clipped to ``+-acc_limit``.

    Same formula as ``IDMVehicle.acceleration`` on a straight lane (``gap`` is the centre-to-centre
    distance, ``distance_wanted`` includes a vehicle length) except that the dynamic part of the
    desired gap is floored at 0 as in Treiber's IDM (highway-env lets it go negative, which makes a
    much faster leader *brake* its follower);
    :class:`~sb3_pearl.envs.highway_merge.hidas.HidasIDMVehicle` carries the same fix.

    :param speed: follower speed(s) [m/s], >= 0
    :param gap: centre-to-centre distance(s) to the leader [m]; ``inf`` for none
    :param leader_speed: leader speed(s) [m/s]
    :param params: IDM parameters
    :return: acceleration(s) [m/s^2]
    """
    p = params
    if isinstance(speed, np.ndarray):
        dynamic = speed * (p.time_wanted + (speed - leader_speed) / (2.0 * math.sqrt(p.acc_max * p.comfort_dec)))
        np.maximum(dynamic, 0.0, out=dynamic)
        dynamic += p.distance_wanted
        dynamic /= np.maximum(gap, 1e-2)
        dynamic *= dynamic
        acc = (speed / p.desired_speed) ** p.delta
        acc += dynamic
        acc *= -p.acc_max
        acc += p.acc_max
        return np.clip(acc, -p.acc_limit, p.acc_limit, out=acc)
    free = 1.0 - (speed / p.desired_speed) ** p.delta
    dynamic = speed * p.time_wanted + speed * (speed - leader_speed) / (2.0 * math.sqrt(p.acc_max * p.comfort_dec))
    desired_gap = p.distance_wanted + max(dynamic, 0.0)
    acc = p.acc_max * (free - (desired_gap / max(gap, 1e-2)) ** 2)
    return min(max(acc, -p.acc_limit), p.acc_limit)


def calibrate_idm(
    density: float,
    speed: float,
    *,
    desired_speed_ratio: float = 1.3,
    jam_gap: float = 2.0,
    vehicle_length: float = Vehicle.LENGTH,
) -> IDMParams:
    """
    IDM parameters whose equilibrium is the task: speed ``speed`` at spacing ``1000 / density``.

    Default IDM (T = 1.5 s, d0 = 10 m) cannot carry 30-50 veh/km at 50-70 mph on one lane (its
    equilibrium speed at these spacings is 7-15 m/s). Here v0 = ``desired_speed_ratio * speed``,
    d0 = vehicle length + ``jam_gap`` (Hidas' g_min), and the headway T solves the homogeneous
    equilibrium ``1 - (v/v0)^delta = (s*(v) / s)^2`` with ``s*(v) = d0 + v T``:
    ``T = (s sqrt(1 - (v/v0)^delta) - d0) / v``.

    :param density: traffic density [veh/km]
    :param speed: traffic speed [m/s]
    :param desired_speed_ratio: v0 / speed (> 1)
    :param jam_gap: bumper-to-bumper jam gap [m]
    :param vehicle_length: vehicle length [m]
    :return: the calibrated IDM parameters
    """
    if density <= 0 or speed <= 0:
        raise ValueError(f"calibrate_idm: density and speed must be > 0, got {density}, {speed}")
    if desired_speed_ratio <= 1:
        raise ValueError(f"calibrate_idm: desired_speed_ratio must be > 1, got {desired_speed_ratio}")
    spacing = 1000.0 / density
    d0 = vehicle_length + jam_gap
    delta = IDMVehicle.DELTA
    headway = (spacing * math.sqrt(1.0 - desired_speed_ratio ** (-delta)) - d0) / speed
    if headway <= 0:
        raise ValueError(
            f"calibrate_idm: no IDM equilibrium at {density} veh/km ({spacing:.1f} m spacing) and {speed} m/s "
            f"with a {d0} m jam distance; lower the density or the jam gap"
        )
    return IDMParams(desired_speed=desired_speed_ratio * speed, time_wanted=headway, distance_wanted=d0, delta=delta)
