"""The waypoint-course driving task: the on-board tracker, progress and task features."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rover_env.config.scenario import CourseConfig


def wrap_angle(a: float) -> float:
    """Wrap an angle to [-pi, pi) [rad]."""
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class CourseFeatures:
    """Task features in the body frame.

    Attributes:
        distance: Distance to the next waypoint [m].
        bearing: Direction of the next waypoint from the body x axis, left + [rad].
        cross_track: Signed distance from the current course segment, left of it + [m].
        heading_error: Segment heading minus body heading, wrapped [rad].
        progress: Arc length travelled along the course [m].
    """

    distance: float
    bearing: float
    cross_track: float
    heading_error: float
    progress: float


class WaypointCourse:
    """A polyline from the start position through the scenario's waypoints.

    The current segment ends at the next waypoint; it is reached when the body centre comes
    within ``tolerance`` of it, and the last one only once the body centre has also passed it
    (its projection on the last segment reaches the goal). Progress is the arc length of the
    projection onto the current segment (clamped to it) plus the length of the completed
    segments.
    """

    def __init__(self, course: CourseConfig) -> None:
        self.cfg = course
        self.index = 0
        self.points = np.zeros((1, 2))
        self._cum = np.zeros(1)
        self._pts: list[tuple[float, float]] = [(0.0, 0.0)]
        self._seg_len: list[float] = []
        self._cum_list: list[float] = [0.0]

    def reset(self, start_xy: np.ndarray) -> None:
        """Start a new episode from ``start_xy`` (world, [m])."""
        self.points = np.vstack(
            [np.asarray(start_xy, dtype=float)[None, :2], np.asarray(self.cfg.waypoints, dtype=float)]
        )
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])
        # plain-float copies for the per-step features
        self._pts = [(float(px), float(py)) for px, py in self.points]
        self._seg_len = seg.tolist()
        self._cum_list = self._cum.tolist()
        self.index = 0

    @property
    def num_waypoints(self) -> int:
        """Number of waypoints of the course."""
        return len(self.cfg.waypoints)

    @property
    def finished(self) -> bool:
        """True once the last waypoint has been reached."""
        return self.index >= self.num_waypoints

    @property
    def length(self) -> float:
        """Course length from the start through all waypoints [m]."""
        return float(self._cum[-1])

    def update(self, xy: np.ndarray) -> bool:
        """Advance past every waypoint within tolerance of ``xy``; True if one was reached."""
        reached = False
        x, y = float(xy[0]), float(xy[1])
        while not self.finished and math.dist(self._pts[self.index + 1], (x, y)) <= self.cfg.tolerance:
            if self.index + 1 == self.num_waypoints and not self._passed_goal(x, y):
                break
            self.index += 1
            reached = True
        return reached

    def _passed_goal(self, x: float, y: float) -> bool:
        """Whether (x, y) lies on or beyond the line through the goal square to the last segment."""
        (ax, ay), (bx, by) = self._pts[-2], self._pts[-1]
        tx, ty = bx - ax, by - ay
        return (x - bx) * tx + (y - by) * ty >= 0.0

    def features(self, xy: np.ndarray, yaw: float, clamp_finished: bool = True) -> CourseFeatures:
        """Task features of a body at ``xy`` [m] heading ``yaw`` [rad] (world frame).

        Args:
            xy: Position [m].
            yaw: Heading [rad].
            clamp_finished: Once the course is finished, report the whole course length as the
                progress (else the arc length of ``xy``'s projection onto the last segment).
        """
        k = min(self.index, self.num_waypoints - 1)
        ax, ay = self._pts[k]
        bx, by = self._pts[k + 1]
        x, y = float(xy[0]), float(xy[1])
        length = self._seg_len[k]
        if length > 1e-9:
            tx, ty = (bx - ax) / length, (by - ay) / length
        else:
            tx, ty = math.cos(yaw), math.sin(yaw)
        rx, ry = x - ax, y - ay
        along = min(length, max(0.0, rx * tx + ry * ty))
        cross = tx * ry - ty * rx
        dist = math.hypot(bx - x, by - y)
        bearing = wrap_angle(math.atan2(by - y, bx - x) - yaw)
        heading_err = wrap_angle(math.atan2(ty, tx) - yaw)
        progress = self.length if (self.finished and clamp_finished) else self._cum_list[k] + along
        return CourseFeatures(dist, bearing, cross, heading_err, progress)
