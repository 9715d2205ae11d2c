"""Exact ground truth read from the simulator, in the frames and units of docs/environment.md."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.rover_estimator import STATE_KEYS

#: ``info["ground_truth"]``'s keys: the pose and the state under the estimator's names.
#: What the wheels feel of the ground, per wheel (``info["ground_truth"]``, after the state),
#: and the drive motors' torques.
SOIL_TRUTH_KEYS: tuple[str, ...] = (
    "wheel_torque",
    "sinkage",
    "drawbar_pull",
    "load",
)
#: The soil's steady-state figures per wheel (``info["soil"]``, in a scenario with soil): NaN
#: for a wheel on rigid ground, so kept out of ``info["ground_truth"]`` (Gymnasium's checker
#: compares NaN as unequal).
SOIL_CURVE_KEYS: tuple[str, ...] = ("pull_ratio", "slip_best_pull", "slip_best_efficiency")
GROUND_TRUTH_KEYS: tuple[str, ...] = ("pose", *STATE_KEYS, *SOIL_TRUTH_KEYS)


@dataclass(frozen=True)
class GroundTruth:
    """The rover's true state at one instant. Wheel order FL, FR, RL, RR; axle order F, R.

    Attributes:
        t: Simulation time since the episode start [s].
        pose: (x, y, z, qx, qy, qz, qw): body centre and orientation, world frame [m].
        twist: (v_x, v_y, omega): body velocity and yaw rate in the body frame [m/s, rad/s].
        wheel_rate: Wheel spin rates relative to their knuckles [rad/s].
        wheel_angle: Unwrapped wheel angles [rad].
        slip_ratio: Longitudinal slip ratio per wheel, in [-1, 1].
        slip_angle: Slip angle per wheel [rad].
        axle_roll: Axle roll psi_F, psi_R relative to the body, about body x [rad].
        axle_height: Axle-body distance d_F, d_R: depth of the axle roll centre below the body
            origin along body -z [m].
        steering: Axle steering lambda_F, lambda_R [rad] (the virtual centre-wheel angle that
            the two measured wheel angles of the axle imply, averaged).
        tilt: (roll, pitch) of the body against gravity [rad], Z-Y-X Euler angles of ``pose``
            (roll about body x, left side up +; pitch about body y, nose down +). A property.
        wheel_steer: Measured steering angle of each wheel [rad].
        wheel_v_long: Ground velocity of each wheel centre along its heading [m/s].
        wheel_v_lat: Ground velocity of each wheel centre across its heading, left + [m/s].
        wheel_torque: Torque applied by each drive motor in the last physics step [N m].
        friction: Friction coefficient applied to each wheel (from the map under it); on
            deformable soil, tan(phi) of the soil (its shear strength per unit normal stress).
        normal_force: Total contact normal force on each wheel [N] (on soil: the soil's).
        contact_point: World position of each wheel's deepest contact (NaN if none) [m] (on
            soil: the rim's lowest point).
        sinkage: Depth of each rim's lowest point below the original surface [m] (0 on rigid
            ground).
        drawbar_pull: The ground's force on each wheel along its heading [N] (on soil: the
            soil's drawbar pull; on rigid ground: the contact's friction along the heading).
        load: The ground's force on each wheel along the ground's normal [N].
        pull_ratio: On soil, the soil's steady-state DP/W at the wheel's slip and load (virgin
            soil, :class:`rover_env.sim.terramechanics.PullCurves`) [-]; NaN on rigid ground,
            off the ground, or braking harder than a slip of -0.5.
        slip_best_pull: On soil, the slip of the largest steady-state DP/W at the wheel's load
            [-]; NaN elsewhere.
        slip_best_efficiency: On soil, the slip of the largest tractive efficiency there [-];
            NaN elsewhere.
    """

    t: float
    pose: np.ndarray
    twist: np.ndarray
    wheel_rate: np.ndarray
    wheel_angle: np.ndarray
    slip_ratio: np.ndarray
    slip_angle: np.ndarray
    axle_roll: np.ndarray
    axle_height: np.ndarray
    steering: np.ndarray
    wheel_steer: np.ndarray
    wheel_v_long: np.ndarray
    wheel_v_lat: np.ndarray
    wheel_torque: np.ndarray
    friction: np.ndarray
    normal_force: np.ndarray
    contact_point: np.ndarray
    sinkage: np.ndarray
    drawbar_pull: np.ndarray
    load: np.ndarray
    pull_ratio: np.ndarray
    slip_best_pull: np.ndarray
    slip_best_efficiency: np.ndarray

    @property
    def tilt(self) -> np.ndarray:
        """(roll, pitch) of the body against gravity [rad] (Z-Y-X Euler angles of ``pose``)."""
        qx, qy, qz, qw = (float(v) for v in self.pose[3:7])
        roll = math.atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
        pitch = math.asin(max(-1.0, min(1.0, 2.0 * (qw * qy - qz * qx))))
        return np.array([roll, pitch])

    @property
    def in_contact(self) -> np.ndarray:
        """Whether each wheel touches the ground."""
        return self.normal_force > 0.0

    def as_dict(self) -> dict[str, np.ndarray]:
        """The public ``info["ground_truth"]`` dict: exactly :data:`GROUND_TRUTH_KEYS`."""
        return {k: np.array(getattr(self, k), dtype=np.float64) for k in GROUND_TRUTH_KEYS}

    def soil_dict(self) -> dict[str, np.ndarray]:
        """The soil's steady-state figures per wheel (``info["soil"]``): :data:`SOIL_CURVE_KEYS`."""
        return {k: np.array(getattr(self, k), dtype=np.float64) for k in SOIL_CURVE_KEYS}

    def contact_dict(self) -> dict[str, np.ndarray]:
        """Per-wheel friction and contact (``info["wheel_contact"]``)."""
        return {
            "friction": self.friction.copy(),
            "normal_force": self.normal_force.copy(),
            "in_contact": self.in_contact.astype(np.float64),
            "contact_point": self.contact_point.copy(),
        }
