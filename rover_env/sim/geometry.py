"""The rover's geometry, mass properties and joint parameters, and the fiducials on it.

Frames (REP-103): body x forward, y left, z up, origin at the body centre. Every link frame below
is the URDF link frame (origin at the joint that moves it). Wheel order is always FL, FR, RL, RR;
axle order F, R.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from perception.models.drive_geometry import (
    AXLES,
    WHEELS,
    DriveGeometry,
    ackermann_arms,
    wheel_steering_angles,
)
from perception.models.validation import ConfigError, check_range

GRAVITY = 9.81  # [m/s^2]

__all__ = ["AXLES", "WHEELS", "Fiducial", "RoverGeometry"]


@dataclass(frozen=True)
class Fiducial:
    """A visual marker on the rover.

    Attributes:
        name: Marker name: A1, A2 (front axle plate), B1, B2 (front tie-rod ends), C1, C2 (rear
            axle plate), D1, D2 (rear tie-rod ends); W_FL ... W_RR for the white correction
            marker on each wheel tread. Index 1 is on the left (+y) side, 2 on the right.
        link: Name of the link the marker is fixed to.
        position: Marker centre in the link frame [m].
        normal: Unit normal of the marker face in the link frame (points out of the face).
        size: Edge length of the square marker [m] (for the wheel marker: tread arc length).
        rgba: Marker colour, components in [0, 1].
    """

    name: str
    link: str
    position: tuple[float, float, float]
    normal: tuple[float, float, float]
    size: float
    rgba: tuple[float, float, float, float]


MARKER_THICKNESS = 0.002  # [m] magenta plates are boxes this thick, centred on their position
MAGENTA = (1.0, 0.0, 1.0, 1.0)
WHITE = (1.0, 1.0, 1.0, 1.0)


@dataclass(frozen=True)
class RoverGeometry:
    """Geometry, masses and joint parameters of the four-wheel double-Ackermann rover.

    Kinematic chain per axle: body -(prismatic z: travel d)- carriage -(revolute x: roll psi)-
    axle -(revolute z: steering)- knuckle -(revolute y: wheel)- wheel. The steering (kingpin)
    axis passes through the wheel centre, so steering does not move the wheel centre.

    All lengths [m], masses [kg], angles [rad], stiffness [N/m] or [N m/rad], damping
    [N s/m] or [N m s/rad], torques [N m], rates [rad/s].
    """

    body_size: tuple[float, float, float] = (0.90, 0.50, 0.15)  # length, width, height [m]
    body_mass: float = 30.0  # [kg]
    axle_x: float = 0.40  # front axle at +axle_x, rear at -axle_x (body frame) [m]
    axle_z: float = -0.15  # axle roll centre height in the body frame [m]
    track: float = 0.60  # lateral distance between wheel centres [m]
    wheel_radius: float = 0.115  # [m]
    wheel_width: float = 0.08  # [m]
    wheel_mass: float = 1.5  # [kg]
    axle_beam_size: tuple[float, float, float] = (0.06, 0.44, 0.05)  # x, y, z extent [m]
    axle_mass: float = 2.0  # [kg]
    carriage_mass: float = 0.5  # [kg]
    knuckle_mass: float = 0.4  # [kg]

    roll_limit: float = math.radians(20.0)  # passive axle roll range +/- [rad]
    roll_stiffness: float = 60.0  # [N m/rad]
    roll_damping: float = 4.0  # [N m s/rad]
    travel_limit: float = 0.05  # passive vertical axle travel range +/- [m]
    travel_stiffness: float = 8000.0  # [N/m]
    travel_damping: float = 300.0  # [N s/m]

    steer_limit: float = math.radians(30.0)  # axle steering command range +/- [rad]
    steer_max_torque: float = 30.0  # [N m]
    steer_max_rate: float = 2.0  # [rad/s]
    ackermann_center_x: float = 0.0  # x of the turn centre line the tie rods are designed for [m]
    steering_arm_length: float = 0.12  # kingpin to tie-rod end, horizontal [m]
    tie_rod_drop: float = 0.045  # tie-rod plane below the roll axis, clear of the beam [m]

    wheel_max_torque: float = 8.0  # drive motor torque limit [N m]
    wheel_max_rate: float = 20.0  # drive motor speed limit [rad/s]

    fiducial_size: float = 0.035  # edge of the magenta squares [m]
    plate_marker_y: float = 0.15  # |y| of the axle-plate markers A, C in the axle frame [m]
    correction_marker_arc: float = math.radians(16.0)  # angular width of the white marker [rad]
    # Fisheye optical centre, on a short mount 4.5 cm under the body: a camera right at the body's
    # underside would lose markers raised by roll and travel behind the body's bottom plane.
    fisheye_origin: tuple[float, float, float] = (0.0, 0.0, -0.12)  # tie-rod markers face it [m]
    # Downward camera on a mast: a vertical post at x = mast_x and a boom forward to the camera,
    # whose optical centre is at mast_camera_position (body frame), 0.8 m above flat ground.
    mast_x: float = 0.40  # [m]
    mast_thickness: float = 0.04  # square section of post and boom [m]
    mast_camera_position: tuple[float, float, float] = (0.95, 0.0, 0.535)  # [m]

    inertia_scale: float = field(default=1.0, repr=False)  # multiplies link inertias (tests)

    def __post_init__(self) -> None:
        for i, v in enumerate(self.body_size):
            check_range(f"body_size[{i}]", v, 0.05, 5.0)
        check_range("mast_thickness", self.mast_thickness, 0.005, 0.2)
        check_range(
            "mast_camera_position[2]", self.mast_camera_position[2], self.body_size[2] / 2 + 0.05, 3.0
        )
        if not self.body_size[0] / 2 < self.mast_camera_position[0] <= 3.0:
            raise ConfigError(
                f"mast_camera_position[0]: {self.mast_camera_position[0]!r} m; the downward camera must "
                f"look at the ground ahead of the body (x > {self.body_size[0] / 2:g} m, at most 3 m)"
            )
        fx, fy, fz = self.fisheye_origin
        if not (abs(fx) < self.body_size[0] / 2 and abs(fy) < self.body_size[1] / 2):
            raise ConfigError(
                f"fisheye_origin: ({fx:g}, {fy:g}) m is not under the body; keep it inside its footprint"
            )
        if not (self.axle_z < fz < -self.body_size[2] / 2):
            raise ConfigError(
                f"fisheye_origin[2]: {fz!r} m; the fisheye hangs under the body, between its bottom "
                f"({-self.body_size[2] / 2:g} m) and the axle roll centres ({self.axle_z:g} m)"
            )
        for name in (
            "body_mass",
            "wheel_mass",
            "axle_mass",
            "carriage_mass",
            "knuckle_mass",
            "wheel_radius",
            "wheel_width",
            "roll_stiffness",
            "travel_stiffness",
            "steer_max_torque",
            "steer_max_rate",
            "wheel_max_torque",
            "wheel_max_rate",
            "fiducial_size",
            "steering_arm_length",
            "tie_rod_drop",
            "inertia_scale",
        ):
            check_range(name, getattr(self, name), 0.0, None, lo_open=True)
        for name in ("roll_damping", "travel_damping"):
            check_range(name, getattr(self, name), 0.0, None)
        check_range("axle_x", self.axle_x, 0.05, 5.0)
        check_range("track", self.track, 0.1, 5.0)
        check_range("roll_limit", self.roll_limit, 0.0, math.radians(60), lo_open=True)
        check_range("travel_limit", self.travel_limit, 0.0, 0.5, lo_open=True)
        check_range("steer_limit", self.steer_limit, 0.0, math.radians(60), lo_open=True)
        check_range("correction_marker_arc", self.correction_marker_arc, 0.0, 1.0, lo_open=True)
        if self.track / 2 - self.wheel_width / 2 <= self.axle_beam_size[1] / 2:
            raise ConfigError(
                "axle_beam_size[1]: the axle beam reaches into the wheels; "
                "make it shorter than track - wheel_width"
            )
        if self.plate_marker_y >= self.axle_beam_size[1] / 2:
            raise ConfigError("plate_marker_y: must lie on the axle beam (< axle_beam_size[1]/2)")
        if abs(self.ackermann_center_x) >= self.axle_x:
            raise ConfigError("ackermann_center_x: must lie between the axles")
        arm = self.axle_x - abs(self.ackermann_center_x)
        if self.track / 2 * math.tan(self.steer_limit) >= arm:
            raise ConfigError(
                "steer_limit: the inner wheel would pass 90 degrees; lower steer_limit or track"
            )

    # ------------------------------------------------------------------ derived quantities
    @property
    def wheelbase(self) -> float:
        """Distance between front and rear axle [m]."""
        return 2.0 * self.axle_x

    @property
    def total_mass(self) -> float:
        """The rover's mass: body, wheels, axles, carriages and knuckles [kg]."""
        return (
            self.body_mass
            + 4 * (self.wheel_mass + self.knuckle_mass)
            + 2 * (self.axle_mass + self.carriage_mass)
        )

    @property
    def sprung_mass(self) -> float:
        """Mass carried by the two travel springs (body only) [kg]."""
        return self.body_mass

    def axle_origin(self, axle: str) -> np.ndarray:
        """Roll/travel joint origin of axle ``'F'`` or ``'R'`` in the body frame [m]."""
        x = self.axle_x if axle == "F" else -self.axle_x
        return np.array([x, 0.0, self.axle_z])

    def wheel_offset(self, wheel: str) -> np.ndarray:
        """Wheel centre (kingpin) of ``wheel`` in its axle frame [m]."""
        side = 1.0 if wheel[1] == "L" else -1.0
        return np.array([0.0, side * self.track / 2.0, 0.0])

    def wheel_position_body(self, wheel: str) -> np.ndarray:
        """Nominal wheel centre in the body frame at zero roll and travel [m]."""
        return self.axle_origin(wheel[0]) + self.wheel_offset(wheel)

    def wheel_positions_body(self) -> np.ndarray:
        """Nominal wheel centres, shape (4, 3), order FL, FR, RL, RR [m]."""
        return np.stack([self.wheel_position_body(w) for w in WHEELS])

    @property
    def drive(self) -> DriveGeometry:
        """The drive geometry controllers use (wheel layout, radius, steering limit)."""
        return DriveGeometry(
            axle_x=self.axle_x,
            track=self.track,
            wheel_radius=self.wheel_radius,
            steer_limit=self.steer_limit,
            ackermann_center_x=self.ackermann_center_x,
        )

    def ackermann_angles(self, steer_front: float, steer_rear: float) -> np.ndarray:
        """Per-wheel steering angles for the axle commands, order FL, FR, RL, RR [rad].

        See :func:`perception.models.drive_geometry.wheel_steering_angles`.
        """
        return wheel_steering_angles(
            ackermann_arms(self.axle_x, self.track, self.ackermann_center_x), steer_front, steer_rear
        )

    def turning_radius(self, steer: float) -> float:
        """Radius of the body-centre path for equal-and-opposite axle steering ``steer`` [m].

        With lambda_F = steer and lambda_R = -steer the turn centre lies on the body's lateral
        line at y = axle_x / tan(steer) (for ``ackermann_center_x`` = 0). Infinite for zero.
        """
        if steer == 0.0:
            return math.inf
        return abs(self.axle_x / math.tan(steer))

    # ------------------------------------------------------------------ fiducials
    def _face_camera(self, p_body: np.ndarray) -> tuple[float, float, float]:
        n = np.asarray(self.fisheye_origin) - p_body
        n = n / np.linalg.norm(n)
        return (float(n[0]), float(n[1]), float(n[2]))

    def steering_arm_tip(self, wheel: str) -> np.ndarray:
        """Tie-rod end (steering arm tip) of ``wheel`` in its knuckle frame [m].

        The arms point inward toward the Ackermann turn-centre line (classic Ackermann
        trapezoid), so the tie rod of the front axle lies behind it and that of the rear
        axle in front of it. They sit ``tie_rod_drop`` below the roll axis, so that the tips
        pass under the axle beam at full lock, and are long enough that the inner wheel at
        full lock does not hide the tip from the fisheye.
        """
        sign_x = -1.0 if wheel[0] == "F" else 1.0
        sign_y = -1.0 if wheel[1] == "L" else 1.0
        arm = abs(self.axle_x - self.ackermann_center_x)
        beta = math.atan2(self.track / 2.0, arm)
        length = self.steering_arm_length
        return np.array(
            [sign_x * length * math.cos(beta), sign_y * length * math.sin(beta), -self.tie_rod_drop]
        )

    def fiducials(self) -> tuple[Fiducial, ...]:
        """All markers with their link and position in the link frame.

        Plate markers A (front), C (rear) lie flat on the inner face of the axle beam at the
        height of the roll axis, so they stay in the axle's vertical plane (the kinematics
        paper's eq. 2). Tie-rod markers B (front), D (rear) sit on the steering-arm tips, in the
        plane parallel to the axle's plane through the roll centre and ``tie_rod_drop`` below it
        (eqs. 3-4 with r_o moved down by that distance); their faces point to the nominal
        fisheye origin.
        The white correction marker of each wheel is centred on the tread at wheel angle 0,
        i.e. at +z of the wheel frame when the wheel angle is zero.
        """
        out: list[Fiducial] = []

        def magenta(name: str, link: str, p_link: np.ndarray, normal) -> Fiducial:
            pos = (float(p_link[0]), float(p_link[1]), float(p_link[2]))
            return Fiducial(name, link, pos, normal, self.fiducial_size, MAGENTA)

        for axle, plate, rod in (("F", "A", "B"), ("R", "C", "D")):
            inner = -1.0 if axle == "F" else 1.0
            for idx, side in ((1, 1.0), (2, -1.0)):
                p_axle = np.array(
                    [inner * (self.axle_beam_size[0] / 2 + MARKER_THICKNESS), side * self.plate_marker_y, 0.0]
                )
                out.append(magenta(f"{plate}{idx}", f"axle_{axle}", p_axle, (inner, 0.0, 0.0)))
            for idx, wheel_side in ((1, "L"), (2, "R")):
                wheel = axle + wheel_side
                tip = self.steering_arm_tip(wheel)
                normal = self._face_camera(self.wheel_position_body(wheel) + tip)
                out.append(magenta(f"{rod}{idx}", f"knuckle_{wheel}", tip, normal))
        arc = self.correction_marker_arc * self.wheel_radius
        for w in WHEELS:
            out.append(
                Fiducial(f"W_{w}", f"wheel_{w}", (0.0, 0.0, self.wheel_radius), (0.0, 0.0, 1.0), arc, WHITE)
            )
        return tuple(out)

    def marker_face_centre(self, f: Fiducial) -> np.ndarray:
        """Centre of the visible face of magenta marker ``f`` in its link frame [m]."""
        return np.asarray(f.position) + 0.5 * MARKER_THICKNESS * np.asarray(f.normal)

    def kinematic_model(self, T_body_fisheye: np.ndarray):
        """The geometry the fisheye estimator needs: a :class:`~perception.models.rover.RoverKinematicModel`.

        Marker positions are the centres of their visible faces.
        """
        from perception.models.rover import RoverKinematicModel

        a1 = self.marker_face_centre(self.fiducial("A1"))  # front-left plate marker, axle frame
        b1 = self.marker_face_centre(self.fiducial("B1"))  # front-left tie-rod end, knuckle frame
        return RoverKinematicModel(
            axle_x=self.axle_x,
            nominal_depth=-self.axle_z,
            track=self.track,
            wheel_radius=self.wheel_radius,
            wheel_width=self.wheel_width,
            plate_offset=float(-a1[0]),
            plate_marker_y=float(a1[1]),
            arm_tip=(float(b1[0]), float(b1[1]), float(b1[2])),
            marker_size=self.fiducial_size,
            correction_marker_arc=self.correction_marker_arc,
            ackermann_center_x=self.ackermann_center_x,
            T_body_cam=T_body_fisheye,
            # the body's weight over the travel springs, and its load moved between the axles by
            # a pitch (the weight along body x at the body's height over the ground)
            rest_sag=self.sprung_mass * GRAVITY / (2.0 * self.travel_stiffness),
            pitch_sag=self.sprung_mass
            * GRAVITY
            * (-self.axle_z + self.wheel_radius)
            / (2.0 * self.axle_x * self.travel_stiffness),
            joint_limits=(self.roll_limit, self.travel_limit, self.steer_limit),
            beam_length=self.axle_beam_size[1],
            beam_section=max(self.axle_beam_size[0], self.axle_beam_size[2]),
            mass=self.total_mass,
        )

    def fiducial(self, name: str) -> Fiducial:
        """The fiducial called ``name`` (see :meth:`fiducials`)."""
        for f in self.fiducials():
            if f.name == name:
                return f
        raise KeyError(f"no fiducial named {name!r}")
