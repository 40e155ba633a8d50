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

Modules:

- :mod:`~sb3_pearl.envs.highway_merge.env`: :class:`HighwayMergeMetaEnv` (the registered env) and the observation scale;
- :mod:`~sb3_pearl.envs.highway_merge.traffic`: IDM of the main-lane traffic and its per-task calibration;
- :mod:`~sb3_pearl.envs.highway_merge.hidas`: Hidas' merging rule, :class:`HidasIDMVehicle` and ``B_min``;
- :mod:`~sb3_pearl.envs.highway_merge.geometry`: road dimensions, lane indices, :class:`LaneFrame`, the network;
- :mod:`~sb3_pearl.envs.highway_merge.road`: :class:`MergeRoad`, the road that integrates the main-lane traffic;
- :mod:`~sb3_pearl.envs.highway_merge.ego`: :class:`MergeEgoVehicle`;
- :mod:`~sb3_pearl.envs.highway_merge.actions`: the action ids.

``docs/highway_merge.md`` has the design choices, the calibration table and the speed measurements.
"""

from sb3_pearl.envs.highway_merge.actions import ACCELERATE, ACTION_NAMES, CRUISE, DECELERATE, LANE_LEFT, LANE_RIGHT
from sb3_pearl.envs.highway_merge.ego import EGO_COLOR, MergeEgoVehicle
from sb3_pearl.envs.highway_merge.env import MPH, OBS_LENGTH_SCALE, OBS_SPEED_SCALE, HighwayMergeMetaEnv
from sb3_pearl.envs.highway_merge.geometry import (
    APPROACH_LENGTH,
    CONVERGE_LENGTH,
    END_OF_LANE,
    LANE_WIDTH,
    MAIN_END,
    MAIN_LANES,
    MAIN_START,
    MERGE_LANE,
    MERGE_LENGTH,
    MERGE_START,
    RAMP_AMPLITUDE,
    RAMP_LANES,
    RAMP_START,
    SPEED_LIMIT,
    LaneFrame,
    make_merge_network,
)
from sb3_pearl.envs.highway_merge.hidas import YIELDING_COLOR, HidasIDMVehicle, HidasParams, hidas_should_yield, min_braking
from sb3_pearl.envs.highway_merge.road import MergeRoad, measure_main_lane_traffic
from sb3_pearl.envs.highway_merge.traffic import IDMParams, calibrate_idm, idm_acceleration

__all__ = [
    "ACCELERATE",
    "ACTION_NAMES",
    "APPROACH_LENGTH",
    "CONVERGE_LENGTH",
    "CRUISE",
    "DECELERATE",
    "EGO_COLOR",
    "END_OF_LANE",
    "LANE_LEFT",
    "LANE_RIGHT",
    "LANE_WIDTH",
    "MAIN_END",
    "MAIN_LANES",
    "MAIN_START",
    "MERGE_LANE",
    "MERGE_LENGTH",
    "MERGE_START",
    "MPH",
    "OBS_LENGTH_SCALE",
    "OBS_SPEED_SCALE",
    "RAMP_AMPLITUDE",
    "RAMP_LANES",
    "RAMP_START",
    "SPEED_LIMIT",
    "YIELDING_COLOR",
    "HidasIDMVehicle",
    "HidasParams",
    "HighwayMergeMetaEnv",
    "IDMParams",
    "LaneFrame",
    "MergeEgoVehicle",
    "MergeRoad",
    "calibrate_idm",
    "hidas_should_yield",
    "idm_acceleration",
    "make_merge_network",
    "measure_main_lane_traffic",
    "min_braking",
]
