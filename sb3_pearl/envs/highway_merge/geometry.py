"""Road geometry of the merge: dimensions, lane indices, the road network and :class:`LaneFrame`.

::

     x [m]:  -400 ............ 0 ....... 100 ....... 180 ................ 330 ............ 2330
     main lane (y = 0)   a ====================== b ==================== c ================ d
     merge lane (y = 4)                            b -------------------- c [Obstacle]
     converge (sine)                   k ~~~~~~~ b
     ramp approach (y = 10.5)   j ---- k

One main lane (``a-b-c-d``) and a ramp (``j-k``, ``k-b``, then lane 1 of road ``b-c``, the merge
lane, closed at :data:`END_OF_LANE` by an :class:`~highway_env.vehicle.objects.Obstacle`).
"""

from __future__ import annotations

import math

import numpy as np
from highway_env.road.lane import AbstractLane, LineType, SineLane, StraightLane
from highway_env.road.road import LaneIndex, RoadNetwork

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


def make_merge_network() -> tuple[RoadNetwork, dict[LaneIndex, list[LaneIndex]], dict[LaneIndex, LaneFrame]]:
    """One main lane (a-b-c-d) and a ramp (j-k-b) whose last part is lane 1 of road b-c."""
    net = RoadNetwork()
    c, s, n = LineType.CONTINUOUS_LINE, LineType.STRIPED, LineType.NONE
    net.add_lane("a", "b", StraightLane([MAIN_START, 0.0], [MERGE_START, 0.0], line_types=[c, c], speed_limit=SPEED_LIMIT))
    net.add_lane("b", "c", StraightLane([MERGE_START, 0.0], [END_OF_LANE, 0.0], line_types=[c, s], speed_limit=SPEED_LIMIT))
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
