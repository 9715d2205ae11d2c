"""The simulated rover in one PyBullet client: actuation, passive suspension, ground truth."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pybullet as pb

from perception.wheel_kinematics import slip_angle, slip_ratio
from rover_env.geometry import AXLES, WHEELS, RoverGeometry
from rover_env.ground_truth import GroundTruth
from rover_env.textures import tread_texture, write_cached
from rover_env.urdf import urdf_file

if TYPE_CHECKING:
    from pybullet_utils.bullet_client import BulletClient

    from rover_env.terrain import Terrain

GRAVITY = 9.81  # [m/s^2]


def ackermann_wheel_speeds(
    geom: RoverGeometry, speed: float, steer_front: float, steer_rear: float
) -> np.ndarray:
    """Ground speed of each wheel centre for a body-centre speed and axle steering commands.

    The instantaneous centre of rotation (ICR) is where the normals of the two axles' virtual
    centre wheels meet; each wheel's speed is proportional to its distance from it, so no
    wheel is dragged. Parallel axle angles (straight or crab driving) give equal speeds.

    Args:
        geom: Rover geometry.
        speed: Signed speed of the body centre [m/s].
        steer_front: lambda_F [rad].
        steer_rear: lambda_R [rad].

    Returns:
        (4,) wheel-centre speeds [m/s], order FL, FR, RL, RR, with the sign of ``speed``.
    """
    tf, tr = math.tan(steer_front), math.tan(steer_rear)
    if abs(tf - tr) < 1e-9:
        return np.full(4, speed)
    yc = geom.wheelbase / (tf - tr)
    xc = geom.axle_x - yc * tf
    icr = np.array([xc, yc])
    r_body = math.hypot(xc, yc)
    r_wheels = np.linalg.norm(geom.wheel_positions_body()[:, :2] - icr, axis=1)
    return speed * r_wheels / r_body


class Rover:
    """The rover's multibody, its motors and passive springs.

    Args:
        client: The environment's own BulletClient.
        geometry: Geometry and joint parameters.
    """

    def __init__(self, client: BulletClient, geometry: RoverGeometry) -> None:
        self.client = client
        self.geom = geometry
        self.body_id = client.loadURDF(
            str(urdf_file(geometry)),
            basePosition=[0, 0, 1],
            flags=pb.URDF_USE_INERTIA_FROM_FILE,
        )
        self.joint: dict[str, int] = {}
        self.link: dict[str, int] = {"body": -1}
        for j in range(client.getNumJoints(self.body_id)):
            info = client.getJointInfo(self.body_id, j)
            self.joint[info[1].decode()] = j
            self.link[info[12].decode()] = j
        self.wheel_joints = [self.joint[f"wheel_{w}"] for w in WHEELS]
        self.steer_joints = [self.joint[f"steer_{w}"] for w in WHEELS]
        self.wheel_links = [self.link[f"wheel_{w}"] for w in WHEELS]
        self.knuckle_links = [self.link[f"knuckle_{w}"] for w in WHEELS]
        self.passive_joints = [self.joint[f"{k}_{a}"] for a in AXLES for k in ("travel", "roll")]
        g = geometry
        per_axle_load = g.sprung_mass * GRAVITY / 2.0
        # per passive joint (travel_F, roll_F, travel_R, roll_R): stiffness, damping, preload
        self._k = np.array([g.travel_stiffness, g.roll_stiffness] * 2)
        self._c = np.array([g.travel_damping, g.roll_damping] * 2)
        self._preload = np.array([-per_axle_load, 0.0] * 2)
        for link in [-1, *range(client.getNumJoints(self.body_id))]:
            client.changeDynamics(
                self.body_id,
                link,
                linearDamping=0.0,
                angularDamping=0.0,
                jointDamping=0.0,
                restitution=0.0,
                rollingFriction=0.0,
                spinningFriction=0.0,
            )
        client.setJointMotorControlArray(
            self.body_id,
            self.passive_joints,
            pb.VELOCITY_CONTROL,
            targetVelocities=[0.0] * 4,
            forces=[0.0] * 4,
        )
        tex = write_cached(
            f"tread:v1:{g.correction_marker_arc:.6f}",
            lambda: tread_texture(marker_arc=g.correction_marker_arc),
        )
        self._tread_tex = client.loadTexture(str(tex))
        for link in self.wheel_links:
            client.changeVisualShape(
                self.body_id, link, textureUniqueId=self._tread_tex, rgbaColor=[1, 1, 1, 1]
            )
        self._mu = [-1.0] * 4
        self.wheel_rate_cmd = np.zeros(4)
        self.steer_cmd = np.zeros(2)

    # ------------------------------------------------------------------ state
    def reset_pose(self, position, quat_xyzw) -> None:
        """Place the rover at rest at ``position`` [m] with ``quat_xyzw``, all joints at zero."""
        c = self.client
        c.resetBasePositionAndOrientation(self.body_id, list(position), list(quat_xyzw))
        c.resetBaseVelocity(self.body_id, [0, 0, 0], [0, 0, 0])
        for j in self.joint.values():
            c.resetJointState(self.body_id, j, 0.0, 0.0)
        self._mu = [-1.0] * 4
        self.command(np.zeros(4), 0.0, 0.0)

    def command(self, wheel_rates: np.ndarray, steer_front: float, steer_rear: float) -> None:
        """Set motor targets, held until the next command.

        Args:
            wheel_rates: (4,) wheel spin-rate targets [rad/s], clipped to the motor limit.
            steer_front: lambda_F [rad], clipped to the steering limit.
            steer_rear: lambda_R [rad], clipped to the steering limit.
        """
        g = self.geom
        rates = np.clip(np.asarray(wheel_rates, dtype=np.float64), -g.wheel_max_rate, g.wheel_max_rate)
        lf = float(np.clip(steer_front, -g.steer_limit, g.steer_limit))
        lr = float(np.clip(steer_rear, -g.steer_limit, g.steer_limit))
        self.wheel_rate_cmd = rates
        self.steer_cmd = np.array([lf, lr])
        c = self.client
        c.setJointMotorControlArray(
            self.body_id,
            self.wheel_joints,
            pb.VELOCITY_CONTROL,
            targetVelocities=rates.tolist(),
            forces=[g.wheel_max_torque] * 4,
        )
        for j, delta in zip(self.steer_joints, g.ackermann_angles(lf, lr)):
            c.setJointMotorControl2(
                self.body_id,
                j,
                pb.POSITION_CONTROL,
                targetPosition=float(delta),
                force=g.steer_max_torque,
                maxVelocity=g.steer_max_rate,
                positionGain=0.2,
                velocityGain=1.0,
            )

    def apply_passive(self) -> None:
        """Spring-damper forces of the passive travel and roll joints (call every substep)."""
        states = self.client.getJointStates(self.body_id, self.passive_joints)
        q = np.fromiter((s[0] for s in states), float, 4)
        qd = np.fromiter((s[1] for s in states), float, 4)
        f = self._preload - self._k * q - self._c * qd
        self.client.setJointMotorControlArray(
            self.body_id, self.passive_joints, pb.TORQUE_CONTROL, forces=f.tolist()
        )

    def apply_friction(self, terrain: Terrain) -> None:
        """Set each wheel's friction from the map at its contact point (call every substep).

        The contact point is taken below the wheel centre along the body's -z axis; PyBullet
        multiplies the two bodies' coefficients and the ground's is 1, so the wheel's value is
        the contact's.
        """
        c = self.client
        _, q = c.getBasePositionAndOrientation(self.body_id)
        m = c.getMatrixFromQuaternion(q)
        r = self.geom.wheel_radius
        zx, zy = m[2] * r, m[5] * r  # body z axis (third column) times r
        states = c.getLinkStates(self.body_id, self.wheel_links)
        fmap = terrain.friction
        for i, st in enumerate(states):
            p = st[4]
            mu = fmap.mu_at(p[0] - zx, p[1] - zy)
            if mu != self._mu[i]:
                c.changeDynamics(self.body_id, self.wheel_links[i], lateralFriction=mu)
                self._mu[i] = mu

    # ------------------------------------------------------------------ ground truth
    def ground_truth(self, t: float, terrain_id: int) -> GroundTruth:
        """Read the exact state (see :class:`GroundTruth` for frames and units)."""
        c = self.client
        g = self.geom
        pos, quat = c.getBasePositionAndOrientation(self.body_id)
        lin, ang = c.getBaseVelocity(self.body_id)
        rot = np.array(c.getMatrixFromQuaternion(quat)).reshape(3, 3)
        v_body = rot.T @ np.asarray(lin)
        w_body = rot.T @ np.asarray(ang)
        joints = c.getJointStates(self.body_id, list(range(c.getNumJoints(self.body_id))))
        jq = {name: joints[j][0] for name, j in self.joint.items()}
        wheel_rate = np.array([joints[j][1] for j in self.wheel_joints])
        wheel_angle = np.array([joints[j][0] for j in self.wheel_joints])
        wheel_steer = np.array([joints[j][0] for j in self.steer_joints])
        wheel_states = c.getLinkStates(self.body_id, self.wheel_links, computeLinkVelocity=1)
        knuckle_states = c.getLinkStates(self.body_id, self.knuckle_links)
        v_long = np.empty(4)
        v_lat = np.empty(4)
        for i in range(4):
            kr = np.array(c.getMatrixFromQuaternion(knuckle_states[i][5])).reshape(3, 3)
            v = np.asarray(wheel_states[i][6])
            v_long[i] = v @ kr[:, 0]
            v_lat[i] = v @ kr[:, 1]
        tread = wheel_rate * g.wheel_radius
        normal_force = np.zeros(4)
        contact_point = np.full((4, 3), np.nan)
        for i, link in enumerate(self.wheel_links):
            pts = c.getContactPoints(bodyA=self.body_id, bodyB=terrain_id, linkIndexA=link)
            if pts:
                normal_force[i] = sum(p[9] for p in pts)
                deepest = min(pts, key=lambda p: p[8])
                contact_point[i] = deepest[6]
        return GroundTruth(
            t=t,
            pose=np.array([*pos, *quat]),
            twist=np.array([v_body[0], v_body[1], w_body[2]]),
            wheel_rate=wheel_rate,
            wheel_angle=wheel_angle,
            slip_ratio=slip_ratio(tread, v_long),
            slip_angle=slip_angle(v_long, v_lat),
            axle_roll=np.array([jq["roll_F"], jq["roll_R"]]),
            axle_height=np.array([-(g.axle_z + jq["travel_F"]), -(g.axle_z + jq["travel_R"])]),
            steering=axle_steering_from_wheels(g, wheel_steer),
            wheel_steer=wheel_steer,
            wheel_v_long=v_long,
            wheel_v_lat=v_lat,
            wheel_torque=np.array([joints[j][3] for j in self.wheel_joints]),
            friction=np.array(self._mu, dtype=np.float64),
            normal_force=normal_force,
            contact_point=contact_point,
        )


def axle_steering_from_wheels(geom: RoverGeometry, wheel_steer: np.ndarray) -> np.ndarray:
    """Invert the per-axle Ackermann mapping: (lambda_F, lambda_R) from 4 wheel angles [rad].

    From tan(delta) = a t / (a - y t) with a the arm to the turn-centre line and t = tan(lambda):
    t = a tan(delta) / (a + y tan(delta)). The two wheels of an axle are averaged.
    """
    out = np.zeros(2)
    for k, axle in enumerate(AXLES):
        arm = (geom.axle_x if axle == "F" else -geom.axle_x) - geom.ackermann_center_x
        vals = []
        for i, w in enumerate(WHEELS):
            if w[0] != axle:
                continue
            y = geom.wheel_offset(w)[1]
            td = math.tan(wheel_steer[i])
            vals.append(math.atan(arm * td / (arm + y * td)))
        out[k] = 0.5 * (vals[0] + vals[1])
    return out
