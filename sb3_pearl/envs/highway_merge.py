"""``HighwayMergeMeta-v0``: the paper's Highway-Merge task family (Section V-A-2) on highway-env.

The ego vehicle starts on an on-ramp and must merge into a **single** main lane before the
merge lane ends (an :class:`~highway_env.vehicle.objects.Obstacle` closes it; failing to merge
is a crash). Main-lane traffic follows IDM, calibrated per task so that the traffic really
drives at the task speed with the task density; while the ego is on the ramp, the main-lane
vehicle right behind it follows Hidas' merging model (:func:`hidas_should_yield`).

- Task ``{"density": veh/km, "speed": m/s}``: density ``U[30, 50]`` veh/km, speed
  ``U[50, 70]`` mph stored in **m/s** (``speed_range`` is in m/s too; :data:`MPH` converts).
- Observation (24, float32): ego ``[D_EOL, y, vx, vy]`` then the 4 main-lane vehicles nearest to
  the ego (by longitudinal distance, nearest first, the rear ones included)
  ``[presence, dx, dy, dvx, dvy]``, zero-padded. Lengths are divided by :data:`OBS_LENGTH_SCALE`
  (100 m), ``y``/``dy`` by the lane width (4 m), speeds by :data:`OBS_SPEED_SCALE` (30 m/s), then
  clipped to the observation box (``normalize_obs=False`` gives metres and m/s).
- Actions ``Discrete(5)``: 0 accelerate (+1.5 m/s^2), 1 decelerate (-1.5 m/s^2), 2 cruise (IDM,
  with the task's calibrated parameters), 3 left lane change, 4 right lane change. The
  longitudinal mode persists across simulation frames and policy steps until another of 0-2 is
  chosen (a lane change keeps it); the speed never goes negative. The ramp lanes are
  ``forbidden``, so a merge cannot be undone and "right" is a no-op on this road.
- Reward (the paper's equation, weights in the constructor, see ``docs/highway_merge.md``)::

      r = -w_speed * min(|vx - v_task|, speed_error_clip)
          - w_gap * min(|dx_front - 1000 / density|, gap_error_clip)
          - w_rear * rear_deceleration            (only on the merge step)
          - (collision_penalty + step_floor * steps_skipped)   (on a crash / failure to merge)
          - action_cost(a)

  ``step_floor`` is the largest per-step penalty, so crashing early is never better than driving on.
- ``info``: ``cost`` (1.0 on a crash or a failure to merge), ``crashed``, ``merged`` (the ego has
  merged by now), ``merge_step`` (it merged during this step), ``ego_speed`` (m/s), ``rewards``
  (components); on the merge step also ``rear_deceleration`` (m/s^2, >= 0) and ``b_min``
  (the paper's minimum braking, m/s^2).
- Time: 10 Hz simulation, 2 Hz policy, 60 steps (30 s). The env ends the episode itself: at the
  horizon, an ego still on the ramp has failed to merge (terminated, cost 1), otherwise the episode
  is truncated. Registered with the same ``max_episode_steps`` (for code that reads the spec).

Speed: main-lane vehicles are :class:`HidasIDMVehicle` objects (rendering, collisions and the
Hidas decision use them) whose longitudinal dynamics are integrated as numpy arrays by
:class:`MergeRoad` (they drive on one straight lane: no steering, leaders from the x-sorted
order); only the ego is checked for collisions; traffic exists only in a window around the ego.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.lane import AbstractLane, LineType, SineLane, StraightLane
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task

MPH = 0.44704
"""One mile per hour in m/s."""

OBS_LENGTH_SCALE = 100.0
OBS_SPEED_SCALE = 30.0
LANE_WIDTH = StraightLane.DEFAULT_WIDTH

# Road geometry [m]: main lane on y = 0, ramp approach on y = 10.5, merge lane on y = 4.
RAMP_START = 0.0
APPROACH_LENGTH = 100.0
CONVERGE_LENGTH = 80.0
MERGE_LENGTH = 150.0
MERGE_START = RAMP_START + APPROACH_LENGTH + CONVERGE_LENGTH  # node "b"
END_OF_LANE = MERGE_START + MERGE_LENGTH  # node "c": the obstacle closes the merge lane here
MAIN_START = -400.0
MAIN_END = END_OF_LANE + 2000.0
RAMP_AMPLITUDE = 3.25
SPEED_LIMIT = 45.0  # [m/s] ~100 mph: above every calibrated desired speed (1.3 * 70 mph = 40.7 m/s)

MAIN_LANES: tuple[LaneIndex, ...] = (("a", "b", 0), ("b", "c", 0), ("c", "d", 0))
RAMP_LANES: tuple[LaneIndex, ...] = (("j", "k", 0), ("k", "b", 0), ("b", "c", 1))
MERGE_LANE: LaneIndex = ("b", "c", 1)

EGO_COLOR = (50, 200, 0)
YIELDING_COLOR = (200, 200, 0)

ACCELERATE, DECELERATE, CRUISE, LANE_LEFT, LANE_RIGHT = range(5)
ACTION_NAMES = ("ACCELERATE", "DECELERATE", "CRUISE", "LANE_LEFT", "LANE_RIGHT")


# ---------------------------------------------------------------------------------------------
# Hidas' merging model and IDM
# ---------------------------------------------------------------------------------------------
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
    much faster leader *brake* its follower); :class:`HidasIDMVehicle` carries the same fix.

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


# ---------------------------------------------------------------------------------------------
# Vehicles
# ---------------------------------------------------------------------------------------------
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

    Its longitudinal state is integrated by :class:`MergeRoad` (vectorised over the lane); this
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
        """IDM desired gap with Treiber's floor on the dynamic part (see :func:`idm_acceleration`)."""
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


class LaneFrame:
    """
    Float-math view of a highway-env ``StraightLane`` / ``SineLane`` (its numpy methods cost microseconds per call).

    :param lane: the lane
    """

    def __init__(self, lane: AbstractLane) -> None:
        if not isinstance(lane, StraightLane):
            raise TypeError(f"LaneFrame supports StraightLane and SineLane, got {type(lane).__name__}")
        self.lane = lane
        self.sx, self.sy = float(lane.start[0]), float(lane.start[1])
        self.dx, self.dy = float(lane.direction[0]), float(lane.direction[1])
        self.heading = float(lane.heading)
        self.length = float(lane.length)
        self.sine = isinstance(lane, SineLane)
        self.amplitude = float(lane.amplitude) if isinstance(lane, SineLane) else 0.0
        self.pulsation = float(lane.pulsation) if isinstance(lane, SineLane) else 0.0
        self.phase = float(lane.phase) if isinstance(lane, SineLane) else 0.0

    def local(self, x: float, y: float) -> tuple[float, float]:
        """``lane.local_coordinates((x, y))``."""
        ex, ey = x - self.sx, y - self.sy
        s = ex * self.dx + ey * self.dy
        r = -ex * self.dy + ey * self.dx
        if self.sine:
            r -= self.amplitude * math.sin(self.pulsation * s + self.phase)
        return s, r

    def heading_at(self, s: float) -> float:
        """``lane.heading_at(s)``."""
        if self.sine:
            return self.heading + math.atan(self.amplitude * self.pulsation * math.cos(self.pulsation * s + self.phase))
        return self.heading

    def distance_with_heading(self, x: float, y: float, heading: float) -> float:
        """``lane.distance_with_heading((x, y), heading)``."""
        s, r = self.local(x, y)
        return abs(r) + max(s - self.length, 0.0) + max(-s, 0.0) + abs(_wrap_to_pi(heading - self.heading_at(s)))


def _wrap_to_pi(angle: float) -> float:
    return ((angle + math.pi) % (2 * math.pi)) - math.pi


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

    :param road: the road (a :class:`MergeRoad`)
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


# ---------------------------------------------------------------------------------------------
# Road with vectorised main-lane traffic
# ---------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------
# Environment
# ---------------------------------------------------------------------------------------------
class HighwayMergeMetaEnv(MetaTaskEnv, AbstractEnv):
    """
    Ramp merge into one main lane; the task is the traffic (density, speed). See the module docstring.

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
    :param desired_speed_ratio: IDM desired speed / task speed (calibration, :func:`calibrate_idm`)
    :param jam_gap: IDM jam gap [m] (calibration)
    :param hidas_dv: Hidas' maximum speed decrease [m/s]
    :param hidas_b_f: Hidas' acceptable deceleration [m/s^2]
    :param hidas_g_min: Hidas' minimum gap [m]
    :param hidas_c: Hidas' acceptable-gap parameter [s]
    :param spawn_jitter: relative jitter of the spacing of spawned vehicles
    :param speed_jitter: relative jitter of the initial traffic speeds
    :param normalize_obs: scale the observation (see the module docstring)
    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"``
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 4}
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
        for name, (low, high) in (("density_range", density_range), ("speed_range", speed_range)):
            if not 0 < low <= high:
                raise ValueError(f"{name} must satisfy 0 < low <= high, got {(low, high)}")
        if not 0 <= ego_speed_range[0] <= ego_speed_range[1]:
            raise ValueError(f"ego_speed_range must satisfy 0 <= low <= high, got {ego_speed_range}")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if policy_frequency <= 0 or simulation_frequency <= 0 or simulation_frequency % policy_frequency:
            raise ValueError(
                f"policy_frequency ({policy_frequency}) must be > 0 and divide simulation_frequency ({simulation_frequency})"
            )
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
            spawn_jitter=spawn_jitter,
            speed_jitter=speed_jitter,
        )
        for name, value in weights.items():
            if value < 0:
                raise ValueError(f"{name} must be >= 0, got {value}")
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
        self._network, self._lane_candidates, self._lane_frames = self._make_network()
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
    @staticmethod
    def _make_network() -> tuple[RoadNetwork, dict[LaneIndex, list[LaneIndex]], dict[LaneIndex, LaneFrame]]:
        """One main lane (a-b-c-d) and a ramp (j-k-b) whose last part is lane 1 of road b-c."""
        net = RoadNetwork()
        c, s, n = LineType.CONTINUOUS_LINE, LineType.STRIPED, LineType.NONE
        net.add_lane("a", "b", StraightLane([MAIN_START, 0.0], [MERGE_START, 0.0], line_types=[c, c], speed_limit=SPEED_LIMIT))
        net.add_lane(
            "b", "c", StraightLane([MERGE_START, 0.0], [END_OF_LANE, 0.0], line_types=[c, s], speed_limit=SPEED_LIMIT)
        )
        net.add_lane("c", "d", StraightLane([END_OF_LANE, 0.0], [MAIN_END, 0.0], line_types=[c, c], speed_limit=SPEED_LIMIT))
        y_merge = LANE_WIDTH
        y_approach = y_merge + 2 * RAMP_AMPLITUDE
        approach = StraightLane(
            [RAMP_START, y_approach],
            [RAMP_START + APPROACH_LENGTH, y_approach],
            line_types=[c, c],
            forbidden=True,
            speed_limit=SPEED_LIMIT,
        )
        converge = SineLane(
            [RAMP_START + APPROACH_LENGTH, y_merge + RAMP_AMPLITUDE],
            [MERGE_START, y_merge + RAMP_AMPLITUDE],
            RAMP_AMPLITUDE,
            np.pi / CONVERGE_LENGTH,
            np.pi / 2,
            line_types=[c, c],
            forbidden=True,
            speed_limit=SPEED_LIMIT,
        )
        merge = StraightLane(
            [MERGE_START, y_merge], [END_OF_LANE, y_merge], line_types=[n, c], forbidden=True, speed_limit=SPEED_LIMIT
        )
        net.add_lane("j", "k", approach)
        net.add_lane("k", "b", converge)
        net.add_lane("b", "c", merge)
        candidates: dict[LaneIndex, list[LaneIndex]] = {}
        frames: dict[LaneIndex, LaneFrame] = {}
        for _from, tos in net.graph.items():
            for _to, lanes in tos.items():
                for i, lane in enumerate(lanes):
                    frames[(_from, _to, i)] = LaneFrame(lane)
                    indices = [(_from, _to, j) for j in range(len(lanes)) if j != i]
                    for nxt, nxt_lanes in net.graph.get(_to, {}).items():
                        indices += [(_to, nxt, j) for j in range(len(nxt_lanes))]
                    candidates[(_from, _to, i)] = [(_from, _to, i)] + indices
        return net, candidates, frames

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


_OBS_SCALE = np.array(
    [1 / OBS_LENGTH_SCALE, 1 / LANE_WIDTH, 1 / OBS_SPEED_SCALE, 1 / OBS_SPEED_SCALE]
    + [1.0, 1 / OBS_LENGTH_SCALE, 1 / LANE_WIDTH, 1 / OBS_SPEED_SCALE, 1 / OBS_SPEED_SCALE] * 4,
    dtype=np.float32,
)
