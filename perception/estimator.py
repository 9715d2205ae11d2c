"""The estimator interface: sensor messages in, named state values out.

An estimator is any object with

- ``reset(start_fix)``: start again from the start fix (x [m], y [m], yaw [rad], world frame);
- ``update(messages, t) -> Mapping[str, value]``: the :class:`perception.rig.SensorMessage`
  samples taken since the last call, in time order, and the control time ``t`` [s]; it returns
  values under the names of :data:`ESTIMATE_FIELDS` (a float each, ``"pose"`` three), and must
  return ``"pose"``: the dead-reckoned (x, y, yaw) the on-board course tracker follows;
- optionally ``readout_request(sensor) -> (t [s], points) | None``: for a sensor whose spec
  says ``readout_window``, the body-frame points [m] its next sample at time ``t`` must show (a
  tracker-driven windowed readout); the simulation asks after each ``update``.

It is built once per environment by a factory given the :class:`perception.rig.Rig`
(``gym.make(..., estimator=FACTORY)``). The built-in one is :class:`perception.RoverEstimator`.

A field an estimator does not return is unknown: it reads 0 in the observation vector (and its
quality field, if it does not return one, 0), NaN in ``info["estimate"]`` and "–" in every
report; leave a value out rather than return NaN. The environment and ``rover replay`` check
what comes back (:func:`check_estimate`): an unknown name, a value that is not a real finite
number (text such as ``"1.5"`` is not one; a slip ratio's standard deviation may be inf), a
quality outside [0, 1], a flag other than 0 or 1, or a pose that is not three numbers is an error
naming the estimator, the name and the step.

The rig an estimator is given (:func:`perception.rig.read_only`) is its own copy with every array
read-only: an estimator cannot change the sensors that feed it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from perception.models.drive_geometry import AXLES, WHEELS
from perception.rig import SensorMessage

#: The state fields of the observation an estimator fills (the tracker's fields are the
#: environment's): body twist, wheel rates, slip ratios, axle roll, height and steering, body
#: roll and pitch, and three qualities in [0, 1].
STATE_ESTIMATES: tuple[str, ...] = (
    "v_x",
    "v_y",
    "omega",
    *(f"wheel_rate_{w}" for w in WHEELS),
    *(f"slip_{w}" for w in WHEELS),
    *(f"axle_roll_{a}" for a in AXLES),
    *(f"axle_height_{a}" for a in AXLES),
    *(f"steering_{a}" for a in AXLES),
    "roll",
    "pitch",
    "odometry_quality",
    "kinematics_quality",
    "attitude_quality",
)

#: What else an estimator may report (into ``info["estimate"]``, never the observation): the
#: height change since the start [m], the wheels' angles [rad] and slip angles [rad], the slip
#: ratios' standard deviation (inf: unknown), whether each slip is measured (1/0) and a slip
#: event (1/0), and the slip filter's quality; what the wheels feel of the soil: each wheel's
#: motor torque [N m], sinkage [m] (and its quality), drawbar pull [N], load [N], its drawbar
#: pull over load at its slip on the soil's identified pull curve [-], the slips of that
#: curve's largest DP/W and largest tractive efficiency [-], and the identification's quality.
EXTRA_ESTIMATES: tuple[str, ...] = (
    "height",
    *(f"wheel_angle_{w}" for w in WHEELS),
    *(f"slip_angle_{w}" for w in WHEELS),
    *(f"slip_std_{w}" for w in WHEELS),
    *(f"slip_valid_{w}" for w in WHEELS),
    *(f"slip_event_{w}" for w in WHEELS),
    "slip_quality",
    *(f"wheel_torque_{w}" for w in WHEELS),
    *(f"sinkage_{w}" for w in WHEELS),
    "sinkage_quality",
    *(f"drawbar_pull_{w}" for w in WHEELS),
    *(f"load_{w}" for w in WHEELS),
    *(f"pull_ratio_{w}" for w in WHEELS),
    "slip_best_pull",
    "slip_best_efficiency",
    "soil_quality",
)

#: Every name an estimator may return: ``"pose"`` (required) and the state and extra estimates.
ESTIMATE_FIELDS: tuple[str, ...] = ("pose", *STATE_ESTIMATES, *EXTRA_ESTIMATES)
_KNOWN = frozenset(ESTIMATE_FIELDS)
#: Fields that are qualities: in [0, 1].
QUALITY_FIELDS: frozenset[str] = frozenset(
    (
        "odometry_quality",
        "kinematics_quality",
        "attitude_quality",
        "slip_quality",
        "sinkage_quality",
        "soil_quality",
    )
)
#: Fields that are flags: 0 or 1.
FLAG_FIELDS: frozenset[str] = frozenset(
    (*(f"slip_valid_{w}" for w in WHEELS), *(f"slip_event_{w}" for w in WHEELS))
)


@runtime_checkable
class Estimator(Protocol):
    """What the environment needs of an estimator (see the module docstring)."""

    def reset(self, start_fix: Sequence[float]) -> None:
        """Start again from the start fix (x [m], y [m], yaw [rad], world frame)."""
        ...

    def update(self, messages: Sequence[SensorMessage], t: float) -> Mapping[str, Any]:
        """The state after the messages since the last call, at control time ``t`` [s]."""
        ...


class EstimatorError(RuntimeError):
    """An estimator raised, or returned something that is not an estimate; the message says which."""


def estimator_name(estimator: object) -> str:
    """How an estimator is named in messages: its class's module and name."""
    cls = type(estimator)
    return f"{cls.__module__}.{cls.__qualname__}"


def _as_number(value: object) -> float:
    """``value`` as a float; TypeError for text, bytes, bools and complex numbers (Python converts some)."""
    if isinstance(value, str | bytes | bool | np.bool_ | complex | np.complexfloating):
        raise TypeError(f"{type(value).__name__}")
    return float(value)  # type: ignore[arg-type]


def check_estimate(values: object, who: str, step: int) -> dict[str, Any]:
    """``values`` as an estimate, checked: known names, real finite numbers in range, a pose of three.

    Args:
        values: What an estimator's ``update`` returned.
        who: The estimator (:func:`estimator_name`), for the message.
        step: The control step, for the message (0: the reset).

    Returns:
        The values as floats (``"pose"``: a (3,) float array).

    Raises:
        EstimatorError: Not a mapping, an unknown name (the known ones are listed), a value that
            is not a real finite number (text, a bool, an object whose conversion fails), a
            quality outside [0, 1], a flag other than 0 or 1, a negative spread, or a pose
            missing or not three finite numbers.
    """
    where = f"estimator {who}, step {step}"
    if not isinstance(values, Mapping):
        raise EstimatorError(
            f"{where}: update() returned {type(values).__name__}, not a mapping of names to values"
        )
    unknown = sorted(set(values) - _KNOWN, key=str)
    if unknown:
        raise EstimatorError(
            f"{where}: unknown key {unknown[0]!r}; the known ones are 'pose' and "
            f"perception.estimator.STATE_ESTIMATES / EXTRA_ESTIMATES"
        )
    if "pose" not in values:
        raise EstimatorError(f"{where}: no 'pose' (x, y, yaw) [m, m, rad]; the course tracker follows it")
    out: dict[str, Any] = {}
    for key, v in values.items():
        if key == "pose":
            try:
                if isinstance(v, str | bytes):
                    raise TypeError(type(v).__name__)
                pose = np.array([_as_number(x) for x in v], dtype=np.float64)
            except Exception:  # noqa: BLE001 - whatever the user's object raises: not a pose
                pose = np.full(0, math.nan)
            if pose.shape != (3,) or not np.all(np.isfinite(pose)):
                raise EstimatorError(f"{where}: 'pose' is {v!r}; give three finite numbers (x, y, yaw)")
            out["pose"] = pose
            continue
        try:
            f = _as_number(v)
        except TypeError as exc:
            raise EstimatorError(f"{where}: {key!r} is {v!r} ({exc}), not a number; return a float") from None
        except Exception as exc:  # noqa: BLE001 - the user's object: any error of its conversion
            raise EstimatorError(
                f"{where}: {key!r} is {v!r}, not a number ({type(exc).__name__}: {exc})"
            ) from None
        spread = key.startswith("slip_std_") and f == math.inf  # an unknown spread
        if not (math.isfinite(f) or spread):
            raise EstimatorError(
                f"{where}: {key!r} is {v!r}; give a finite number (leave an unknown value out)"
            )
        if key in QUALITY_FIELDS and not 0.0 <= f <= 1.0:
            raise EstimatorError(f"{where}: {key!r} is {v!r}; a quality is in [0, 1]")
        if key in FLAG_FIELDS and f not in (0.0, 1.0):
            raise EstimatorError(f"{where}: {key!r} is {v!r}; a flag is 1.0 (yes) or 0.0 (no)")
        if key.startswith("slip_std_") and f < 0.0:
            raise EstimatorError(f"{where}: {key!r} is {v!r}; a standard deviation is >= 0 (inf: unknown)")
        out[key] = f
    return out


def _pick(values: Mapping[str, Any], names: Sequence[str], default: float = math.nan) -> np.ndarray:
    return np.array([values.get(n, default) for n in names], dtype=np.float64)


def state_arrays(values: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """An estimate's state under the ground truth's grouped keys (NaN where it is unknown).

    ``twist`` (v_x, v_y, omega), ``wheel_rate``, ``wheel_angle``, ``slip_ratio``,
    ``slip_angle`` (FL, FR, RL, RR), ``axle_roll``, ``axle_height``, ``steering`` (F, R) and
    ``tilt`` (roll, pitch).
    """
    return {
        "twist": _pick(values, ("v_x", "v_y", "omega")),
        "wheel_rate": _pick(values, [f"wheel_rate_{w}" for w in WHEELS]),
        "wheel_angle": _pick(values, [f"wheel_angle_{w}" for w in WHEELS]),
        "slip_ratio": _pick(values, [f"slip_{w}" for w in WHEELS]),
        "slip_angle": _pick(values, [f"slip_angle_{w}" for w in WHEELS]),
        "axle_roll": _pick(values, [f"axle_roll_{a}" for a in AXLES]),
        "axle_height": _pick(values, [f"axle_height_{a}" for a in AXLES]),
        "steering": _pick(values, [f"steering_{a}" for a in AXLES]),
        "tilt": _pick(values, ("roll", "pitch")),
    }


def qualities(values: Mapping[str, Any]) -> tuple[float, float, float]:
    """(odometry, kinematics, attitude) quality of an estimate; 0 where it gives none."""
    return tuple(float(values.get(f"{k}_quality", 0.0)) for k in ("odometry", "kinematics", "attitude"))  # type: ignore[return-value]
