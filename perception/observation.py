"""The observation vector of the rover environments, declared once: name, unit, bounds, source.

A controller acts on this vector; the environment fills it (from perception, or from the
simulator for ablations) and everything else reads it by field name, never by position. The
module depends on numpy only, so that controllers need neither the simulator nor gymnasium.

Sources (with ``obs_source="estimated"``):

- ``slip filter``: the fusion of the downward camera's visual odometry and the fisheye's wheel
  rates (:class:`perception.SlipEstimator`);
- ``fisheye``: the fisheye kinematics (:class:`perception.KinematicStateEstimator`);
- ``IMU``: the attitude filter on the IMU's gyro and accelerometer (:class:`perception.AttitudeFilter`);
  0 with quality 0 on a rover without one;
- ``odometry`` / ``fisheye`` quality: the estimators' own confidence;
- ``tracker``: the on-board course tracker fed with the dead-reckoned pose and the course known
  before the mission;
- ``action``: the previous action sent.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from perception.models.drive_geometry import AXLES, WHEELS


@dataclass(frozen=True)
class ObsField:
    """One entry of the observation vector.

    Attributes:
        name: Field name (unique).
        unit: SI unit (``1`` for dimensionless).
        low: Lower bound; observations are clipped to [low, high].
        high: Upper bound.
        source: What fills it with ``obs_source="estimated"`` (see the module docstring).
        description: Meaning, with the frame.
    """

    name: str
    unit: str
    low: float
    high: float
    source: str
    description: str


def _f(name, unit, low, high, source, description) -> ObsField:
    return ObsField(name, unit, float(low), float(high), source, description)


#: The state and task fields, in order; the previous action follows (:func:`observation_fields`).
#: Bounds are generous finite limits far outside anything physical, reached only by a blow-up.
STATE_FIELDS: tuple[ObsField, ...] = (
    _f("v_x", "m/s", -20, 20, "slip filter", "body forward velocity (body frame, x forward)"),
    _f("v_y", "m/s", -20, 20, "slip filter", "body lateral velocity (body frame, y left)"),
    _f(
        "omega",
        "rad/s",
        -20,
        20,
        "slip filter",
        "yaw rate about body z, counter-clockwise + (fused with the gyro's where there is an IMU)",
    ),
    *(_f(f"wheel_rate_{w}", "rad/s", -100, 100, "slip filter", f"{w} wheel spin rate") for w in WHEELS),
    *(
        _f(f"slip_{w}", "1", -1, 1, "slip filter", f"{w} longitudinal slip ratio (+ spinning, - skidding)")
        for w in WHEELS
    ),
    *(
        _f(f"axle_roll_{a}", "rad", -math.pi, math.pi, "fisheye", f"axle roll psi_{a} about body x")
        for a in AXLES
    ),
    *(
        _f(
            f"axle_height_{a}",
            "m",
            -1,
            1,
            "fisheye",
            f"axle-body distance d_{a} (roll centre below the body origin)",
        )
        for a in AXLES
    ),
    *(
        _f(f"steering_{a}", "rad", -math.pi / 2, math.pi / 2, "fisheye", f"axle steering lambda_{a}, left +")
        for a in AXLES
    ),
    _f("roll", "rad", -math.pi, math.pi, "IMU", "body roll against gravity, left side up +"),
    _f("pitch", "rad", -math.pi / 2, math.pi / 2, "IMU", "body pitch against gravity, nose down +"),
    _f(
        "odometry_quality",
        "1",
        0,
        1,
        "odometry",
        "confidence of the last visual-odometry estimate (0: invalid)",
    ),
    _f(
        "kinematics_quality",
        "1",
        0,
        1,
        "fisheye",
        "share of the fisheye's 10 joint states measured in its last frame",
    ),
    _f(
        "attitude_quality",
        "1",
        0,
        1,
        "IMU",
        "share of the last period's IMU samples in range (0: no IMU, roll and pitch unknown)",
    ),
    _f("waypoint_distance", "m", 0, 1000, "tracker", "distance to the next waypoint"),
    _f(
        "waypoint_bearing",
        "rad",
        -math.pi,
        math.pi,
        "tracker",
        "direction of the next waypoint from body x, left +",
    ),
    _f("cross_track", "m", -1000, 1000, "tracker", "offset from the current course segment, left +"),
    _f("heading_error", "rad", -math.pi, math.pi, "tracker", "segment heading minus body heading"),
)

#: Names of :data:`STATE_FIELDS`, in order.
OBS_FIELDS: tuple[str, ...] = tuple(f.name for f in STATE_FIELDS)

#: Names of the previous-action fields per action mode.
ACTION_FIELDS: dict[str, tuple[str, ...]] = {
    "drive": ("prev_speed", "prev_steer_F", "prev_steer_R"),
    "wheels": tuple(f"prev_wheel_{w}" for w in WHEELS) + ("prev_steer_F", "prev_steer_R"),
}


def observation_fields(action_mode: str) -> tuple[ObsField, ...]:
    """Every field of the observation for ``action_mode`` (``"drive"`` or ``"wheels"``), in order."""
    if action_mode not in ACTION_FIELDS:
        raise ValueError(f"action_mode={action_mode!r}: use one of {sorted(ACTION_FIELDS)}")
    prev = tuple(
        _f(n, "1", -1, 1, "action", "the previous action, clipped to [-1, 1]")
        for n in ACTION_FIELDS[action_mode]
    )
    return STATE_FIELDS + prev


def field_index(fields: Sequence[str] | Sequence[ObsField], name: str) -> int:
    """Position of field ``name`` in the observation whose fields (or names) are ``fields``.

    Raises:
        KeyError: There is no such field; the message lists the known ones.
    """
    names = [f.name if isinstance(f, ObsField) else f for f in fields]
    try:
        return names.index(name)
    except ValueError:
        raise KeyError(f"the observation has no field {name!r}; its fields are {names}") from None


def bounds(fields: Sequence[ObsField]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 arrays of ``fields``."""
    return (
        np.array([f.low for f in fields], dtype=np.float32),
        np.array([f.high for f in fields], dtype=np.float32),
    )


def state_values(
    state: Mapping[str, Sequence[float] | np.ndarray],
    quality: Sequence[float],
    task: Mapping[str, float],
) -> dict[str, float]:
    """The state and task fields by name, from state arrays, quality and task features.

    Args:
        state: Arrays under the ground-truth keys ``twist`` (v_x, v_y, omega), ``wheel_rate``
            (4), ``slip_ratio`` (4), ``axle_roll`` (2), ``axle_height`` (2), ``steering`` (2),
            ``tilt`` (roll, pitch).
        quality: (odometry, kinematics, attitude) quality in [0, 1].
        task: ``waypoint_distance``, ``waypoint_bearing``, ``cross_track``, ``heading_error``.
    """
    out: dict[str, float] = {}
    for name, v in zip(("v_x", "v_y", "omega"), state["twist"], strict=True):
        out[name] = float(v)
    for key, prefix, labels in (
        ("wheel_rate", "wheel_rate_", WHEELS),
        ("slip_ratio", "slip_", WHEELS),
        ("axle_roll", "axle_roll_", AXLES),
        ("axle_height", "axle_height_", AXLES),
        ("steering", "steering_", AXLES),
    ):
        for label, v in zip(labels, state[key], strict=True):
            out[prefix + label] = float(v)
    out["roll"], out["pitch"] = (float(v) for v in state["tilt"])
    out["odometry_quality"], out["kinematics_quality"], out["attitude_quality"] = (float(q) for q in quality)
    for name in ("waypoint_distance", "waypoint_bearing", "cross_track", "heading_error"):
        out[name] = float(task[name])
    return out


def assemble(
    fields: Sequence[ObsField], values: Mapping[str, float], prev_action: Sequence[float] | np.ndarray
) -> np.ndarray:
    """The float32 observation: ``values`` by field name then ``prev_action``, NaN as 0, clipped.

    Args:
        fields: :func:`observation_fields` of the action mode.
        values: Every state and task field by name (:func:`state_values`).
        prev_action: The previous action (as many values as the action fields).
    """
    n_state = len(fields) - len(prev_action)
    vec = np.array(
        [values[f.name] for f in fields[:n_state]] + [float(a) for a in prev_action], dtype=np.float64
    )
    low, high = bounds(fields)
    return np.clip(np.nan_to_num(vec, nan=0.0).astype(np.float32), low, high)


def markdown_table(fields: Sequence[ObsField]) -> str:
    """The observation table as Markdown (index, name, unit, bounds, source, meaning)."""
    rows = ["| index | field | unit | bounds | source (estimated) | meaning |", "|---:|---|---|---|---|---|"]
    for i, f in enumerate(fields):
        rows.append(
            f"| {i} | `{f.name}` | {f.unit} | [{f.low:g}, {f.high:g}] | {f.source} | {f.description} |"
        )
    return "\n".join(rows)
