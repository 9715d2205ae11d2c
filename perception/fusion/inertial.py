"""Roll and pitch from an IMU, and dead reckoning that uses them.

:class:`AttitudeFilter` is a complementary filter with an integral term (Mahony's): the attitude
is propagated with the gyro's rates less their bias and pulled toward the accelerometer's
gravity direction with a time constant, while the specific force is close to 1 g; the same
pull, integrated, learns the gyro's x and y biases. The z bias is not seen by gravity: it comes
from a standstill (:meth:`AttitudeFilter.calibrate`) and is refined by the slip filter.
Frames: body x forward, y left, z up; the world z up; roll, pitch and yaw are the Z-Y-X Euler
angles of the body in the world (pitch positive nose down).
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: Gravity [m/s^2].
G = 9.81


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` [rad] (Rodrigues)."""
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * K + (1.0 - math.cos(a)) * (K @ K)


def tilt_from_gravity(f_body: np.ndarray) -> tuple[float, float]:
    """(roll, pitch) [rad] of a body at rest whose accelerometer reads ``f_body`` [m/s^2]."""
    fx, fy, fz = (float(v) for v in f_body)
    return math.atan2(fy, fz), math.atan2(-fx, math.hypot(fy, fz))


class AttitudeFilter:
    """Roll and pitch of the body from gyro and accelerometer samples.

    Args:
        R_body_imu: (3, 3) rotation of the IMU's mount frame in the body frame (its calibration).
        time_constant: How fast the attitude follows the accelerometer's gravity [s].
        accel_gate: The accelerometer corrects only while | |f| - g | is below this [m/s^2].
        bias_time: How fast the gyro's x and y biases are learnt from that pull [s].
    """

    def __init__(
        self, R_body_imu=None, time_constant: float = 2.0, accel_gate: float = 0.5, bias_time: float = 10.0
    ) -> None:
        R = np.eye(3) if R_body_imu is None else np.asarray(R_body_imu, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise ValueError("R_body_imu: give a (3, 3) rotation matrix")
        if not (time_constant > 0 and accel_gate > 0 and bias_time > 0):
            raise ValueError(
                f"time_constant={time_constant!r}, accel_gate={accel_gate!r}, bias_time={bias_time!r}: "
                "all must be > 0"
            )
        self.bias_time = float(bias_time)
        self.R_body_imu = R
        self.time_constant = float(time_constant)
        self.accel_gate = float(accel_gate)
        self.reset()

    def reset(self) -> None:
        """Level, no bias, no rate."""
        self.R = np.eye(3)  # body -> world (its yaw is arbitrary; only the tilt is used)
        self.bias = np.zeros(3)  # gyro bias, body frame [rad/s]
        self.rate = np.zeros(3)  # the last bias-corrected body rate [rad/s]

    def calibrate(self, gyro_mean, accel_mean) -> None:
        """At a standstill: the mean gyro z reading is its z bias, the mean specific force the tilt.

        The x and y means are not taken as biases: a body that has just come to rest on its
        suspension still rolls and pitches by more than a MEMS gyro's bias; the filter learns
        those two from gravity instead.

        Args:
            gyro_mean: (3,) mean rate, IMU frame [rad/s].
            accel_mean: (3,) mean specific force, IMU frame [m/s^2].
        """
        g = self.R_body_imu @ np.asarray(gyro_mean, dtype=np.float64)
        f = self.R_body_imu @ np.asarray(accel_mean, dtype=np.float64)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(f)) and np.linalg.norm(f) > 0.5 * G):
            raise ValueError("calibrate: give finite means taken at rest (|f| near 9.81 m/s^2)")
        self.bias = np.array([0.0, 0.0, g[2]])
        roll, pitch = tilt_from_gravity(f)
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        self.R = np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])

    def update(self, gyro, accel, dt: float, accel_body=None) -> None:
        """One sample: ``gyro`` [rad/s] and ``accel`` [m/s^2] in the IMU frame, over ``dt`` [s].

        ``accel_body``: the body's own acceleration [m/s^2, body frame] if known (for example
        omega x v in a steady turn, from the odometry), taken out of the specific force before
        it is read as gravity.
        """
        w = self.R_body_imu @ np.asarray(gyro, dtype=np.float64) - self.bias
        f = self.R_body_imu @ np.asarray(accel, dtype=np.float64)
        if accel_body is not None:
            f = f - np.asarray(accel_body, dtype=np.float64)
        self.rate = w
        self.R = self.R @ _exp_so3(w * dt)
        n = float(np.linalg.norm(f))
        if abs(n - G) < self.accel_gate:
            up_pred = self.R[2]  # the world's up in the body frame
            err = np.cross(up_pred, f / n)  # small rotation (body frame) taking predicted to measured
            self.R = self.R @ _exp_so3(-err * min(1.0, dt / self.time_constant))
            # the integral term: a lasting pull is a gyro bias (x and y; err has no part along up)
            step = err * dt / (self.time_constant * self.bias_time)
            self.bias[:2] += step[:2]
        # keep it a rotation (one Newton step of the polar decomposition; the drift is ~1e-16)
        self.R = 1.5 * self.R - 0.5 * self.R @ self.R.T @ self.R

    @property
    def roll(self) -> float:
        """Roll [rad]."""
        return math.atan2(self.R[2, 1], self.R[2, 2])

    @property
    def pitch(self) -> float:
        """Pitch [rad] (positive nose down)."""
        return -math.asin(max(-1.0, min(1.0, self.R[2, 0])))

    def heading_rate(self, yaw_rate_body: float) -> float:
        """The world heading's rate [rad/s] for a body-z rate ``yaw_rate_body`` (and the last x-y rates).

        Z-Y-X kinematics: psi_dot = (sin(roll) w_y + cos(roll) w_z) / cos(pitch).
        """
        r, p = self.roll, self.pitch
        return (math.sin(r) * self.rate[1] + math.cos(r) * yaw_rate_body) / max(math.cos(p), 1e-3)


def tilted_step(pose, z: float, twist, roll: float, pitch: float, heading_rate: float, dt: float):
    """Dead-reckoning step on tilted ground: (x, y, yaw) and height after ``dt`` [s].

    The body velocity (v_x, v_y) of ``twist`` lies in its own x-y plane; it is turned into the
    world by yaw (at the interval's middle), pitch and roll. Returns ((x, y, yaw), z) [m, rad].
    """
    x, y, yaw = (float(v) for v in pose)
    vx, vy = float(twist[0]), float(twist[1])
    psi = yaw + 0.5 * heading_rate * dt
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(psi), math.sin(psi)
    # the first two columns of Rz(psi) Ry(pitch) Rx(roll)
    dx = cy * cp * vx + (cy * sp * sr - sy * cr) * vy
    dy = sy * cp * vx + (sy * sp * sr + cy * cr) * vy
    dz = -sp * vx + cp * sr * vy
    return np.array([x + dx * dt, y + dy * dt, yaw + heading_rate * dt]), z + dz * dt


# ---------------------------------------------------------------------------------------- logs
IMU_CSV_COLUMNS = ("t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")


class ImuLog:
    """IMU samples of a log: times [s], gyro [rad/s] and accelerometer [m/s^2] (IMU frame).

    Attributes:
        t: (n,) sample times [s], strictly increasing.
        gyro: (n, 3) angular rates [rad/s].
        accel: (n, 3) specific forces [m/s^2].
        dropped: Rows left out for non-finite readings (their count).
    """

    def __init__(self, t, gyro, accel, dropped: int = 0) -> None:
        self.t = np.asarray(t, dtype=np.float64)
        self.gyro = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
        self.accel = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
        self.dropped = int(dropped)


def read_imu_csv(path) -> ImuLog:
    """Read an IMU CSV with the header ``t, gyro_x, gyro_y, gyro_z, accel_x, accel_y, accel_z``.

    Units: s, rad/s, m/s^2; the times on the images' clock (t = 0 at the first image). Other
    columns are ignored. Rows with a non-finite reading are left out and counted (a warning).

    Raises:
        FileNotFoundError: No such file.
        ValueError: Missing columns (named), a non-number, a non-finite or non-increasing time
            (the row is named), or no rows.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such IMU CSV")
    with open(
        p, newline="", encoding="utf-8-sig", errors="replace"
    ) as fh:  # -sig: a BOM (Excel) is no header
        reader = csv.reader(fh)
        header = [h.strip() for h in next(reader, [])]
        missing = [c for c in IMU_CSV_COLUMNS if c not in header]
        if missing:
            raise ValueError(
                f"{p}: missing columns {missing}; the header must hold {', '.join(IMU_CSV_COLUMNS)} "
                "(s, rad/s, m/s^2)"
            )
        idx = [header.index(c) for c in IMU_CSV_COLUMNS]
        rows = []
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            try:
                rows.append([float(row[i]) for i in idx])
            except (ValueError, IndexError):
                raise ValueError(
                    f"{p}, line {line_no}: {row!r} is not {len(IMU_CSV_COLUMNS)} numbers"
                ) from None
    if not rows:
        raise ValueError(f"{p}: no samples")
    a = np.array(rows)
    t = a[:, 0]
    bad_t = np.flatnonzero(~np.isfinite(t))
    if len(bad_t):
        raise ValueError(f"{p}, line {bad_t[0] + 2}: time {float(t[bad_t[0]])!r} is not a finite number")
    back = np.flatnonzero(np.diff(t) <= 0)
    if len(back):
        k = back[0] + 1
        raise ValueError(
            f"{p}, line {k + 2}: t = {float(t[k])!r} s does not increase after {float(t[k - 1])!r} s; "
            "give the samples in time order, each once"
        )
    ok = np.all(np.isfinite(a[:, 1:]), axis=1)
    if not ok.all():
        log.warning("%s: %d rows with non-finite readings left out", p, int((~ok).sum()))
    return ImuLog(t[ok], a[ok, 1:4], a[ok, 4:7], dropped=int((~ok).sum()))


#: Widest full-scale range of MEMS gyros (parts of +-4000 deg/s exist) [rad/s]: a reading beyond
#: it is not in rad/s.
GYRO_RANGE_MAX = math.radians(4000.0)
#: Widest standstill gyro bias of the data sheets (the MPU-6050's zero-rate output, +-20 deg/s)
#: [rad/s].
GYRO_BIAS_MAX = math.radians(20.0)
#: How far the standstill accelerometer's norm may be from gravity [m/s^2]: MEMS zero-g offsets
#: and scale errors stay within 0.25 g. While driving (no standstill given) the median norm
#: over the log may be 0.3 g from it.
ACCEL_STILL_TOL = 0.25 * G
ACCEL_DRIVE_TOL = 0.3 * G


def _accel_hint(norm: float) -> str:
    """The likely unit of an accelerometer whose gravity reads ``norm``."""
    for scale, unit in ((1.0 / G, "g"), (1000.0, "mm/s^2"), (1000.0 / G, "mg"), (100.0, "cm/s^2")):
        if abs(norm / scale - G) < 0.3 * G:
            return f"; it looks like {unit}: multiply by {1 / scale:g} for m/s^2"
    if norm < 0.3 * G:
        return (
            "; gravity is missing: give the specific force (what the part reads), not a linear acceleration"
        )
    return ""


def check_imu_units(imu: ImuLog, name: str, still: float = 0.0) -> None:
    """Refuse IMU samples whose numbers are not rad/s and m/s^2, suggesting the likely unit.

    Checks: no gyro reading beyond the widest MEMS range (:data:`GYRO_RANGE_MAX`); over the
    standstill of ``still`` seconds at the start (if > 0), a mean gyro rate within the widest
    data-sheet bias (:data:`GYRO_BIAS_MAX`) and an accelerometer norm within
    :data:`ACCEL_STILL_TOL` of gravity; without a standstill, a median accelerometer norm
    within :data:`ACCEL_DRIVE_TOL` of it. An accelerometer that reads exactly zero throughout
    (not recorded) passes with a warning.

    Args:
        imu: The samples (gyro [rad/s], accel [m/s^2] expected).
        name: The file or topic, for the messages.
        still: Seconds of standstill at the start of the log (0: none known).

    Raises:
        ValueError: A check failed; the message names ``name``, the number and the likely unit.
    """
    if not len(imu.t):
        raise ValueError(f"{name}: no IMU samples")
    peak = float(np.abs(imu.gyro).max())
    if peak > GYRO_RANGE_MAX:
        hint = "; it looks like deg/s: multiply by pi/180" if peak * math.pi / 180 <= GYRO_RANGE_MAX else ""
        raise ValueError(
            f"{name}: a gyro reading of {peak:.4g} is beyond any gyro's range ({GYRO_RANGE_MAX:.1f} rad/s = "
            f"4000 deg/s){hint}; give rad/s"
        )
    norms = np.linalg.norm(imu.accel, axis=1)
    recorded = bool(np.any(imu.accel != 0))
    if not recorded:
        log.warning(
            "%s: the accelerometer reads exactly zero throughout (not recorded?); only the gyro is used", name
        )
    if still > 0:
        m = imu.t <= imu.t[0] + still
        bias = imu.gyro[m].mean(axis=0)
        b = float(np.linalg.norm(bias))
        if b > GYRO_BIAS_MAX:
            deg = b * math.pi / 180 <= GYRO_BIAS_MAX
            hint = "it looks like deg/s (multiply by pi/180)" if deg else "check the units (rad/s)"
            raise ValueError(
                f"{name}: over the first {still:g} s (the standstill) the gyro reads {b:.4g} rad/s, beyond "
                f"any data sheet's bias ({GYRO_BIAS_MAX:.2f} rad/s = 20 deg/s): {hint}, and that the rover "
                "stands still then"
            )
        f = float(np.linalg.norm(imu.accel[m].mean(axis=0)))
        if recorded and abs(f - G) > ACCEL_STILL_TOL:
            raise ValueError(
                f"{name}: at the standstill the accelerometer reads {f:.4g}, not gravity ({G} m/s^2 within "
                f"{ACCEL_STILL_TOL:.1f}){_accel_hint(f)}"
            )
    elif recorded:
        f = float(np.median(norms))
        if abs(f - G) > ACCEL_DRIVE_TOL:
            raise ValueError(
                f"{name}: the accelerometer's median norm is {f:.4g}, not gravity ({G} m/s^2 within "
                f"{ACCEL_DRIVE_TOL:.1f}){_accel_hint(f)}"
            )


def check_gyro_against_odometry(gyro_z, omega, name: str) -> None:
    """Refuse a gyro whose yaw rate is not the odometry's in scale (units, axis or mount).

    Fits gyro_z = s * omega + b over the pairs where both are known (omega spread over
    0.05 rad/s, at least 10 pairs), or takes s as the median ratio gyro_z / omega where the
    odometry turns faster than 0.05 rad/s (a steady turn); with neither there is nothing to
    check. The scale s must lie in [0.5, 2]: a gyro in deg/s reads 57 times the odometry's
    rate, one about another axis near 0, one mounted upside down -1.

    Args:
        gyro_z: (n,) the gyro's body-z rate per pair, bias not removed [rad/s].
        omega: (n,) the odometry's yaw rate per pair (NaN where invalid) [rad/s].
        name: The IMU file or topic, for the message.

    Raises:
        ValueError: The scale is outside [0.5, 2]; the message gives it and the likely cause.
    """
    g, w = np.asarray(gyro_z, dtype=np.float64), np.asarray(omega, dtype=np.float64)
    ok = np.isfinite(g) & np.isfinite(w)
    if ok.sum() >= 10 and float(np.std(w[ok])) >= 0.05:
        s = float(np.polyfit(w[ok], g[ok], 1)[0])
    else:  # a steady turn: the ratio of the rates where the odometry turns
        turn = ok & (np.abs(w) > 0.05)
        if turn.sum() < 5:
            return
        s = float(np.median(g[turn] / w[turn]))
    if 0.5 <= s <= 2.0:
        return
    if abs(s * math.pi / 180 - 1) < 0.3:
        cause = "it looks like deg/s: multiply the gyro by pi/180"
    elif abs(s + 1) < 0.3:
        cause = "the IMU's z axis points down: give its mount with --imu-rpy (e.g. 180 0 0)"
    elif abs(s) < 0.5:
        cause = "the yaw is about another of the IMU's axes: give its mount with --imu-rpy"
    else:
        cause = "check the gyro's units (rad/s) and the mount (--imu-rpy)"
    raise ValueError(f"{name}: the gyro's yaw rate is {s:.3g} times the odometry's; {cause}")
