"""Errors of the estimator in the loop against the simulator's truth: per field, slip, and path.

:class:`EstimateLog` records, at every control step of an ``obs_source="estimated"`` episode,
the state fields and slip events the estimator returned (by name; NaN where it returned none),
the truth of the same fields and the dead-reckoned and true planar poses. From it:

- :func:`field_errors`: per observation field, MAE and 95th percentile of |estimate - truth|;
- :func:`slip_metrics`: per-wheel slip-ratio MAE while |s_true| > 0.1 and otherwise, and
  slip-event detection (precision, recall, F1, onset latency in camera frames);
- :func:`perception.odometry.trajectory.path_segment_errors` on the logged poses (the odometry paper's
  path-segment error).

The first second of each episode (the filters' start-up) is left out of every figure. Each
figure scores only what the estimator returned: a field it never returned has no error (NaN,
"–" in the reports), never the error of a zero; slip events it never flagged are not scored.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from perception.fusion.slip import SlipConfig, slip_events
from perception.models.drive_geometry import AXLES, WHEELS
from perception.observation import OBS_FIELDS
from perception.odometry.trajectory import path_segment_errors
from rover_env.sim.simulation import quat_to_yaw

#: Observation fields with a ground truth, and the (ground-truth key, index) of each.
_TRUTH_OF: dict[str, tuple[str, int]] = {
    **{n: ("twist", i) for i, n in enumerate(("v_x", "v_y", "omega"))},
    **{f"wheel_rate_{w}": ("wheel_rate", i) for i, w in enumerate(WHEELS)},
    **{f"slip_{w}": ("slip_ratio", i) for i, w in enumerate(WHEELS)},
    **{f"axle_roll_{a}": ("axle_roll", i) for i, a in enumerate(AXLES)},
    **{f"axle_height_{a}": ("axle_height", i) for i, a in enumerate(AXLES)},
    **{f"steering_{a}": ("steering", i) for i, a in enumerate(AXLES)},
    "roll": ("tilt", 0),
    "pitch": ("tilt", 1),
}
#: Observation fields with a ground truth: twist, wheel rates, slip, axle roll and height, steering,
#: body roll and pitch (read as 0 without an IMU, so their error is then the true tilt).
FIELDS: tuple[str, ...] = tuple(n for n in OBS_FIELDS if n in _TRUTH_OF)
#: (ground-truth key, index) of each of :data:`FIELDS`.
TRUTH: tuple[tuple[str, int], ...] = tuple(_TRUTH_OF[n] for n in FIELDS)
#: The columns of the slip ratios (FL, FR, RL, RR) in :meth:`EstimateLog.arrays`' ``est`` and ``tru``.
SLIP_COLUMNS: list[int] = [FIELDS.index(f"slip_{w}") for w in WHEELS]


def columns(*names: str) -> list[int]:
    """The columns of the fields ``names`` (of :data:`FIELDS`) in ``est`` and ``tru``."""
    return [FIELDS.index(n) for n in names]


EVENT_FRAMES = 2  # frames in a row with |s| >= SLIP_EVENT that make a true event (SlipConfig.event_hold)
EVENT_SPEED = SlipConfig().event_min_speed  # [m/s] no event on a slower wheel
#: |s| of the hysteresis band's floor: true slip that rises above this but makes no true event
#: (it peaks below the threshold, 0.2, or stays above it for one frame) is neither an event nor,
#: when the estimator calls one there, a false alarm.
BAND_FLOOR = 0.15
START_UP = 1.0  # [s] left out at the start of an episode


class EstimateLog:
    """Per-step rows of an estimated-observation episode.

    Args:
        radius: Wheel radius [m] (tread speeds from wheel rates).
    """

    def __init__(self, radius: float) -> None:
        self.radius = radius
        self.est: list[np.ndarray] = []  # estimated fields (FIELDS; NaN: not returned)
        self.events: list[list[float]] = []  # per-wheel slip events flagged (1/0; NaN: not returned)
        self.tru: list[list[float]] = []  # true values of the same fields (TRUTH)
        self.speed: list[np.ndarray] = []  # per-wheel tread or body speed [m/s]
        self.t: list[float] = []  # time [s]
        self.est_pose: list[tuple[float, float, float]] = []  # (x, y, yaw) [m, m, rad]
        self.true_pose: list[tuple[float, float, float]] = []
        self.est_z: list[float] = []  # the body origin's height [m]

    def add(self, info: dict, values: Mapping[str, Any]) -> None:
        """Record one step from ``info`` of ``env.step`` and the estimator's ``values`` by name.

        ``values``: what the estimator returned at the step (``env.unwrapped.estimate_values``).
        """
        gt = info["ground_truth"]
        self.est.append(np.array([values.get(n, math.nan) for n in FIELDS], dtype=np.float64))
        self.events.append([values.get(f"slip_event_{w}", math.nan) for w in WHEELS])
        self.tru.append([gt[k][i] for k, i in TRUTH])
        self.speed.append(np.maximum(np.abs(gt["wheel_rate"] * self.radius), abs(gt["twist"][0])))
        self.t.append(info["t"])
        for poses, p in ((self.est_pose, info["estimate"]["pose"]), (self.true_pose, gt["pose"])):
            poses.append((p[0], p[1], quat_to_yaw(p[3:7])))
        self.est_z.append(float(info["estimate"]["pose"][2]))  # the body origin's height [m], as the truth's

    def arrays(self, frame: float) -> dict:
        """The rows as arrays, with the fisheye's frame period ``frame`` [s] and the wheel radius."""
        names = ("est", "events", "tru", "speed", "t", "est_pose", "true_pose", "est_z")
        return {k: np.array(getattr(self, k), dtype=float) for k in names} | {
            "frame": frame,
            "radius": self.radius,
        }


def field_errors(runs: list[dict]) -> dict[str, tuple[float, float]]:
    """Per field of :data:`FIELDS`: (MAE, 95th percentile) of |estimate - truth| over ``runs``.

    Over the steps where the estimator returned the field; (NaN, NaN) where it never did.
    """
    err = np.vstack([np.abs(r["est"] - r["tru"])[r["t"] >= START_UP] for r in runs])
    out = {}
    for j, name in enumerate(FIELDS):
        col = err[:, j][np.isfinite(err[:, j])] if len(err) else np.zeros(0)
        out[name] = (float(col.mean()), float(np.percentile(col, 95))) if col.size else (math.nan, math.nan)
    return out


def _mean_known(values) -> float:
    """The mean of the finite ``values``; NaN if none is (nothing was estimated)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else math.nan


def _runs_of(on: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index ranges of the True runs of ``on``."""
    d = np.diff(np.r_[0, on.astype(int), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def slip_metrics(runs: list[dict], wheels=(0, 1, 2, 3)) -> dict:
    """Slip-ratio accuracy and slip-event detection over ``runs`` (:meth:`EstimateLog.arrays`).

    ``wheels``: the wheels scored (0-3: FL, FR, RL, RR), all by default.

    MAE of the four wheels' slip ratios while |s_true| > 0.1 and otherwise, over steps where the
    wheel's tread or ground speed is at least 5 cm/s and the estimator returned the slip (NaN:
    it never did). Events: the estimator's own (``slip_event_<wheel>``; a run in which it never
    returned one is not scored, and every count is then NaN) against the truth labelled by the
    same rule
    (:func:`perception.fusion.slip.slip_events`: |s| >= 0.2 for two frames in a row on a wheel at 0.15 m/s
    or more, ending below 0.1); an estimated event matches a true one it overlaps or that ended
    at most ``EVENT_FRAMES`` fisheye frames before it starts (the detector needs that long to
    confirm; F1 is NaN when neither side has one). The scoring has a hysteresis band: an
    estimated event that matches no true one but meets, in the same way, a true excursion to
    ``BAND_FLOOR`` or more that made no true event (its |s| peaked below 0.2, or stayed above
    0.2 for a single frame) is neither a match nor a false alarm (``in_band`` counts them).
    Latency runs from the truth's first frame at 0.2 and is counted in fisheye frames.
    """
    err_slip, err_calm, tp, fp, fn, band, lat = [], [], 0, 0, 0, 0, []
    scored = True  # every run's events were returned
    for rr in runs:
        step_s = float(np.median(np.diff(rr["t"]))) if len(rr["t"]) > 1 else rr["frame"]
        grace = max(1, round(EVENT_FRAMES * rr["frame"] / step_s))  # steps a detection may trail by
        keep = rr["t"] >= START_UP
        s_est, s_true = rr["est"][keep][:, SLIP_COLUMNS], rr["tru"][keep][:, SLIP_COLUMNS]
        moving = rr["speed"][keep] >= 0.05
        big = np.abs(s_true) > 0.1
        err = np.abs(s_est - s_true)
        known = np.isfinite(err)
        known[:, [w for w in range(4) if w not in wheels]] = False
        err_slip.extend(err[moving & big & known].tolist())
        err_calm.extend(err[moving & ~big & known].tolist())
        flagged = np.asarray(rr["events"], dtype=np.float64).reshape(-1, 4)[keep]
        if not len(flagged):  # a run over before its start-up ended: nothing to score
            continue
        if not np.isfinite(flagged).any():  # the estimator flags no events: not scored
            scored = False
            continue
        ev_est = np.nan_to_num(flagged, nan=0.0) > 0.5  # not returned at a step: no event claimed
        ev_true = slip_events(s_true, min_frames=EVENT_FRAMES, speed=rr["speed"][keep], min_speed=EVENT_SPEED)
        s_abs = np.abs(s_true)
        for w in wheels:
            e_runs, t_runs = _runs_of(ev_est[:, w]), _runs_of(ev_true[:, w])
            matched = set()
            for a0, a1 in t_runs:
                hit = [k for k, (b0, b1) in enumerate(e_runs) if b0 < a1 + grace and a0 < b1]
                if hit:
                    tp += 1
                    matched.update(hit)
                    lat.append(max(0, e_runs[hit[0]][0] - (a0 - (EVENT_FRAMES - 1))))
                else:
                    fn += 1
            # true excursions above the band's floor that made no true event
            near = [(a0, a1) for a0, a1 in _runs_of(s_abs[:, w] >= BAND_FLOOR) if not ev_true[a0:a1, w].any()]
            for k, (b0, b1) in enumerate(e_runs):
                if k not in matched:
                    if any(b0 < a1 + grace and a0 < b1 for a0, a1 in near):
                        band += 1
                    else:
                        fp += 1
    if not scored:  # every count, and so every event figure, unknown
        tp = fp = fn = band = math.nan  # type: ignore[assignment]
        lat = []
    prec = tp / (tp + fp) if tp + fp else math.nan  # no estimated event: precision is undefined
    rec = tp / (tp + fn) if tp + fn else math.nan  # no true event: recall is undefined
    # no event on either side: detection is not scored
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else math.nan
    # latencies are counted in control steps; a fisheye frame spans frame / (step time) of them
    step = float(np.median(np.diff(runs[0]["t"]))) if runs and len(runs[0]["t"]) > 1 else math.nan
    lat_frames = np.array(lat) * step / runs[0]["frame"] if lat else np.zeros(0)
    return dict(
        mae_slip=float(np.mean(err_slip)) if err_slip else math.nan,
        n_slip=len(err_slip),
        mae_calm=float(np.mean(err_calm)) if err_calm else math.nan,
        events=tp + fn,
        matched=tp,
        false=fp,
        in_band=band,
        missed=fn,
        precision=prec,
        recall=rec,
        f1=f1,
        latency_median=float(np.median(lat_frames)) if len(lat_frames) else math.nan,
        latency_max=float(lat_frames.max()) if len(lat_frames) else math.nan,
        within_2=float(np.mean(lat_frames <= 2 + 1e-9)) if len(lat_frames) else math.nan,
    )


_UNIT_OF = {
    "v_x": "m/s", "v_y": "m/s", "omega": "rad/s", "wheel_rate": "rad/s", "slip": "-",
    "axle_roll": "rad", "axle_height": "m", "steering": "rad",
}  # fmt: skip


def estimator_unit(key: str) -> str:
    """The unit of an :func:`estimator_summary` key ("-": a ratio; "count"; "frames"; "%")."""
    if key.startswith(("mae_", "p95_")):
        return _UNIT_OF.get(key[4:], "-")
    if key.startswith("segment_"):
        return "%"
    if key.startswith("position_error"):
        return "m"
    if key.startswith("slip_events"):
        return "count"
    if key == "slip_latency_max":
        return "frames"
    return "-"


def estimator_summary(run: dict, segment_lengths=(2.0, 5.0, 10.0)) -> dict[str, float]:
    """One episode's estimator errors as flat ``name: value`` pairs (for tables and JSON).

    Keys: ``mae_<field>`` and ``p95_<field>`` for the twist, and the mean over wheels or axles of
    the wheel rates, slip ratios, axle roll and height and steering; the slip metrics
    (``slip_mae_slipping``, ``slip_mae_otherwise``, ``slip_f1``, ...); the dead-reckoned
    position's final and mean error [m]; and ``segment_<L>m_percent``, the mean path-segment
    error as a share of the length.
    """
    errs = field_errors([run])
    out: dict[str, float] = {}
    groups = {
        "v_x": ["v_x"],
        "v_y": ["v_y"],
        "omega": ["omega"],
        "wheel_rate": [f for f in FIELDS if f.startswith("wheel_rate")],
        "slip": [f for f in FIELDS if f.startswith("slip_")],
        "axle_roll": ["axle_roll_F", "axle_roll_R"],
        "axle_height": ["axle_height_F", "axle_height_R"],
        "steering": ["steering_F", "steering_R"],
    }
    for g, names in groups.items():  # a group's mean over the fields estimated (NaN: none was)
        out[f"mae_{g}"] = _mean_known([errs[n][0] for n in names])
        out[f"p95_{g}"] = _mean_known([errs[n][1] for n in names])
    s = slip_metrics([run])

    def count(v: float) -> float:
        return float(v) if math.isnan(v) else int(v)

    out.update(
        slip_mae_slipping=s["mae_slip"],
        slip_mae_otherwise=s["mae_calm"],
        slip_events=count(s["events"]),
        slip_events_matched=count(s["matched"]),
        slip_events_false=count(s["false"]),
        slip_events_missed=count(s["missed"]),
        slip_events_in_band=count(s["in_band"]),
        slip_precision=s["precision"],
        slip_recall=s["recall"],
        slip_f1=s["f1"],
        slip_latency_max=s["latency_max"],
    )
    d = np.linalg.norm(run["est_pose"][:, :2] - run["true_pose"][:, :2], axis=1)
    out["position_error_final"] = float(d[-1]) if len(d) else math.nan
    out["position_error_mean"] = float(d.mean()) if len(d) else math.nan
    for e in path_segment_errors(run["true_pose"], run["est_pose"], segment_lengths):
        out[f"segment_{e.length:g}m_percent"] = e.mean_percent
    return out


__all__ = [
    "FIELDS",
    "TRUTH",
    "EstimateLog",
    "estimator_summary",
    "field_errors",
    "slip_metrics",
]
