"""The rover's kinematic geometry as the fisheye estimator needs it (no simulator).

Frames (REP-103): body x forward, y left, z up. Per axle a in (F, R): the roll centre at
(x_a, 0, -d_a) in the body frame (d_a: depth below the body origin, the axle-body distance), the
axle frame rotated by the roll psi_a about body x. Each wheel's kingpin lies at (0, +-track/2, 0)
in its axle frame; its knuckle frame is rotated by the wheel steering angle delta about the axle's
z. Wheel order FL, FR, RL, RR; marker names as in the kinematics paper: A1, A2 on the front axle
plate, B1, B2 on the front tie-rod ends, C1, C2 and D1, D2 on the rear (index 1 on the left).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from perception.models.calib_io import CalibrationError, as_array, check_rigid, read_mapping, write_mapping
from perception.models.drive_geometry import (
    AXLES,
    WHEELS,
    ackermann_arms,
    wheel_steering_angles,
)
from perception.models.validation import real_number

PLATE = {"F": ("A1", "A2"), "R": ("C1", "C2")}
ROD = {"F": ("B1", "B2"), "R": ("D1", "D2")}
MARKERS = ("A1", "A2", "B1", "B2", "C1", "C2", "D1", "D2")


def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` [rad] about x."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` [rad] about y."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` [rad] about z."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RoverKinematicModel:
    """Geometry of the axles, markers and wheels [m], and the fisheye's pose on the body.

    Attributes:
        axle_x: Roll centres at x = +axle_x (front) and -axle_x (rear), body frame.
        nominal_depth: Axle-body distance d at rest (roll centre below the body origin).
        track: Lateral distance between wheel centres.
        wheel_radius: Tread radius.
        wheel_width: Tread width.
        plate_offset: Plate markers' distance from the roll axis along x, toward the body centre
            (their plane, paper eq. 2, is x = +-(axle_x - plate_offset)).
        plate_marker_y: |y| of the plate markers in the axle frame.
        arm_tip: Front-left tie-rod end in its knuckle frame (x, y, z); the others mirror it.
        marker_size: Edge of the magenta squares.
        correction_marker_arc: Angular width of the white tread marker [rad].
        ackermann_center_x: x of the turn-centre line each axle's tie rod is designed for.
        T_body_cam: Fisheye optical frame in the body frame.
        rest_sag: How far the body's weight compresses each axle's travel spring at rest [m]
            (its share of the weight over the spring's stiffness; 0: unknown). Tilted, the
            springs carry the weight's component along body z only, so both axles hang deeper
            by ``rest_sag (1 - cos(roll) cos(pitch))``.
        pitch_sag: How far the front axle's depth at rest grows per unit sine of the body's
            nose-up pitch [m], the rear's shrinking as much: the weight's component along body
            x, acting at the body's height over the ground, moves load between the axles
            (0: unknown). See :meth:`rest_depths`.
        beam_length: Length of each axle's beam along its y axis, centred on the roll axis [m]
            (0: unknown). beam_section: The larger of its x and z extents [m]. Seen from the
            fisheye, a beam may hide a rear wheel's contact with the ground (:meth:`beam_parts`).
        mass: The rover's mass [kg] (0: unknown).
        joint_limits: (axle roll [rad], axle travel about ``nominal_depth`` [m], axle steering
            [rad]) ranges +-, or None (unknown). With them the fisheye's odometry leaves out the
            image of the wheels, markers and arms over the whole range
            (:func:`perception.models.rover_parts.kinematics_roi`).
    """

    axle_x: float
    nominal_depth: float
    track: float
    wheel_radius: float
    wheel_width: float
    plate_offset: float
    plate_marker_y: float
    arm_tip: tuple[float, float, float]
    marker_size: float
    correction_marker_arc: float
    ackermann_center_x: float = 0.0
    T_body_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    rest_sag: float = 0.0
    pitch_sag: float = 0.0
    beam_length: float = 0.0
    beam_section: float = 0.0
    mass: float = 0.0
    joint_limits: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        for name in ("axle_x", "nominal_depth", "track", "wheel_radius", "wheel_width", "marker_size"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise CalibrationError(f"{name}: {v!r} must be a positive length in metres")
        for name in ("rest_sag", "pitch_sag", "beam_length", "beam_section", "mass"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise CalibrationError(f"{name}: {v!r} must be a length >= 0 in metres")
        for name in ("plate_offset", "plate_marker_y", "ackermann_center_x"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise CalibrationError(f"{name}: {v!r} must be a finite length in metres")
        arc = self.correction_marker_arc
        if not (isinstance(arc, (int, float)) and 0.0 < arc < math.pi):
            raise CalibrationError(
                f"correction_marker_arc: {arc!r}; the tread marker's angular width is in (0, pi) rad"
            )
        object.__setattr__(self, "arm_tip", tuple(float(v) for v in as_array(self.arm_tip, (3,), "arm_tip")))
        object.__setattr__(self, "T_body_cam", check_rigid(self.T_body_cam, "T_body_cam"))
        if self.joint_limits is not None:
            lim = tuple(float(v) for v in as_array(self.joint_limits, (3,), "joint_limits"))
            if not all(math.isfinite(v) and v > 0 for v in lim):
                raise CalibrationError(
                    f"joint_limits: {self.joint_limits!r}; give the roll [rad], travel [m] and steering "
                    "[rad] ranges, each > 0, or None"
                )
            object.__setattr__(self, "joint_limits", lim)

    def rest_depths(self, roll: float, pitch: float) -> np.ndarray:
        """The axle depths (d_F, d_R) of the rover at rest on its wheels, its body tilted [m].

        Args:
            roll: Body roll against gravity [rad] (left side up +).
            pitch: Body pitch against gravity [rad] (nose down +).

        With ``rest_sag`` and ``pitch_sag`` 0 both are ``nominal_depth``, the level rest.
        """
        if not (math.isfinite(roll) and math.isfinite(pitch)):
            raise ValueError(f"roll={roll!r}, pitch={pitch!r}: the tilt must be finite [rad]")
        common = self.nominal_depth + self.rest_sag * (1.0 - math.cos(roll) * math.cos(pitch))
        shift = -self.pitch_sag * math.sin(pitch)
        return np.array([common + shift, common - shift])

    # ------------------------------------------------------------------ forward kinematics
    def axle_sign(self, axle: str) -> float:
        """+1 for the front axle, -1 for the rear."""
        return 1.0 if axle == "F" else -1.0

    def roll_centre(self, axle: str, depth: float) -> np.ndarray:
        """Roll centre of ``axle`` at axle-body distance ``depth`` (body frame)."""
        return np.array([self.axle_sign(axle) * self.axle_x, 0.0, -depth])

    def axle_pose(self, axle: str, psi: float, depth: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t): axle frame -> body frame."""
        return rot_x(psi), self.roll_centre(axle, depth)

    def plate_marker_local(self, name: str) -> np.ndarray:
        """Plate marker centre in its axle frame."""
        axle = "F" if name[0] == "A" else "R"
        side = 1.0 if name[1] == "1" else -1.0
        return np.array([-self.axle_sign(axle) * self.plate_offset, side * self.plate_marker_y, 0.0])

    def kingpin_local(self, wheel: str) -> np.ndarray:
        """Kingpin (wheel centre) in its axle frame."""
        return np.array([0.0, (1.0 if wheel[1] == "L" else -1.0) * self.track / 2.0, 0.0])

    def tip_knuckle(self, wheel: str) -> np.ndarray:
        """Tie-rod end of ``wheel`` in its knuckle frame (front tips behind the kingpin, rear in front)."""
        x, y, z = self.arm_tip
        sx = 1.0 if wheel[0] == "F" else -1.0
        sy = 1.0 if wheel[1] == "L" else -1.0
        return np.array([sx * x, sy * y, z])

    def marker_positions(self, psi, depth, delta) -> dict[str, np.ndarray]:
        """Body-frame centres of the 8 magenta markers.

        Args:
            psi: (psi_F, psi_R) axle roll [rad].
            depth: (d_F, d_R) axle-body distance [m].
            delta: (4,) wheel steering angles FL, FR, RL, RR [rad].
        """
        out = {}
        for i, axle in enumerate(AXLES):
            R, t = self.axle_pose(axle, psi[i], depth[i])
            for name in PLATE[axle]:
                out[name] = R @ self.plate_marker_local(name) + t
            for name, wheel in zip(ROD[axle], (axle + "L", axle + "R"), strict=True):
                k = WHEELS.index(wheel)
                local = self.kingpin_local(wheel) + rot_z(delta[k]) @ self.tip_knuckle(wheel)
                out[name] = R @ local + t
        return out

    def marker_normals(self, psi, delta) -> dict[str, np.ndarray]:
        """Body-frame unit normals of the 8 marker faces.

        Plate markers lie flat on the beam's inner face; tie-rod markers face the fisheye at zero
        roll and steering and turn with their knuckle.
        """
        out = {}
        for i, axle in enumerate(AXLES):
            R = rot_x(psi[i])
            for name in PLATE[axle]:
                out[name] = R @ np.array([-self.axle_sign(axle), 0.0, 0.0])
            for name, wheel in zip(ROD[axle], (axle + "L", axle + "R"), strict=True):
                out[name] = R @ rot_z(delta[WHEELS.index(wheel)]) @ self._rod_normals[name]
        return out

    @functools.cached_property
    def _rod_normals(self) -> dict[str, np.ndarray]:
        """Tie-rod marker normals at zero roll and steering (they face the fisheye)."""
        nominal = self.marker_positions((0.0, 0.0), (self.nominal_depth,) * 2, np.zeros(4))
        cam = self.T_body_cam[:3, 3]
        out = {}
        for axle in AXLES:
            for name in ROD[axle]:
                n = cam - nominal[name]
                out[name] = n / np.linalg.norm(n)
        return out

    def wheel_frames(self, psi, depth, delta) -> list[tuple[np.ndarray, np.ndarray]]:
        """(R, centre) of each wheel's knuckle frame in the body frame (axle along its y)."""
        out = []
        for k, wheel in enumerate(WHEELS):
            i = AXLES.index(wheel[0])
            R, t = self.axle_pose(wheel[0], psi[i], depth[i])
            out.append((R @ rot_z(delta[k]), R @ self.kingpin_local(wheel) + t))
        return out

    def occluders(self, wheel: str, R: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parts in front of a wheel's tread seen from the fisheye: its steering arm and tie-rod marker.

        Args:
            wheel: FL, FR, RL or RR.
            R: The wheel's knuckle frame in the body frame (rotation).
            c: Its centre (the kingpin), body frame.

        Returns:
            (n, 3) body-frame points along the arm and at the marker, and (n,) radii [m] of the
            spheres around them that cover the parts.
        """
        pts, radii = self._occluder_parts[wheel]
        return pts @ np.asarray(R).T + c, radii

    @functools.cached_property
    def _occluder_parts(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per wheel: knuckle-frame points along the steering arm and at the tie-rod marker, radii."""
        out = {}
        for wheel in WHEELS:
            tip = self.tip_knuckle(wheel)
            s = np.linspace(0.0, 1.0, 7)[:, None]
            arm = s * np.array([tip[0], tip[1], 0.0]) + np.array([0.0, 0.0, tip[2]])
            out[wheel] = (np.vstack([arm, tip]), np.r_[np.full(len(arm), 0.012), 0.75 * self.marker_size])
        return out

    def beam_parts(self, psi, depth) -> tuple[np.ndarray, np.ndarray]:
        """Both axle beams as chains of spheres: (n, 3) body-frame centres and (n,) radii [m].

        None of either (empty arrays) while ``beam_length`` is unknown (0).
        """
        if self.beam_length <= 0.0:
            return np.zeros((0, 3)), np.zeros(0)
        n = max(2, int(math.ceil(self.beam_length / (0.5 * max(self.beam_section, 1e-3)))) + 1)
        local = np.column_stack([np.zeros(n), np.linspace(-0.5, 0.5, n) * self.beam_length, np.zeros(n)])
        pts = [local @ R.T + t for R, t in (self.axle_pose(a, psi[i], depth[i]) for i, a in enumerate(AXLES))]
        return np.vstack(pts), np.full(2 * n, math.sqrt(0.5) * self.beam_section)

    def ackermann_arms(self) -> tuple[np.ndarray, np.ndarray]:
        """(arm to the turn-centre line, y) of each wheel, order FL, FR, RL, RR."""
        return ackermann_arms(self.axle_x, self.track, self.ackermann_center_x)

    def wheel_angles(self, lam_front: float, lam_rear: float) -> np.ndarray:
        """Per-wheel steering angles for axle commands (the tie rods' Ackermann mapping) [rad]."""
        return wheel_steering_angles(self.ackermann_arms(), lam_front, lam_rear)

    # ------------------------------------------------------------------ YAML
    _KEYS = frozenset(
        {
            "axle_x",
            "nominal_depth",
            "track",
            "wheel_radius",
            "wheel_width",
            "plate_offset",
            "plate_marker_y",
            "arm_tip",
            "marker_size",
            "correction_marker_arc",
            "ackermann_center_x",
            "T_body_cam",
        }
    )

    # 0 when absent (files written before them)
    _OPTIONAL = ("rest_sag", "pitch_sag", "beam_length", "beam_section", "mass")

    @classmethod
    def load(cls, path: str | Path) -> RoverKinematicModel:
        """Read a model written by :meth:`save` (the sags and joint limits optional; no unknown keys)."""
        d = read_mapping(path, set(cls._KEYS), set(cls._OPTIONAL) | {"joint_limits"})
        try:
            kw: dict = {k: real_number(k, d[k]) for k in cls._KEYS - {"arm_tip", "T_body_cam"}}
            kw.update({k: real_number(k, d[k]) for k in cls._OPTIONAL if k in d})
            if d.get("joint_limits") is not None:
                kw["joint_limits"] = tuple(as_array(d["joint_limits"], (3,), "joint_limits"))
            return cls(
                arm_tip=tuple(as_array(d["arm_tip"], (3,), "arm_tip")),
                T_body_cam=as_array(d["T_body_cam"], (4, 4), "T_body_cam"),
                **kw,
            )
        except (CalibrationError, TypeError, ValueError) as exc:
            raise CalibrationError(f"{path}: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        """Write every field to YAML."""
        data = {k: getattr(self, k) for k in sorted(self._KEYS | set(self._OPTIONAL))}
        data["arm_tip"] = list(self.arm_tip)
        if self.joint_limits is not None:
            data["joint_limits"] = list(self.joint_limits)
        return write_mapping(path, data)
