"""The simulated rover in one PyBullet client: actuation, passive suspension, ground truth."""

from __future__ import annotations

import math
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import pybullet as pb

from perception.models.drive_geometry import ackermann_arms, axle_steering_angles
from perception.models.wheel_kinematics import slip_ratio
from rover_env.sim.geometry import AXLES, GRAVITY, WHEELS, RoverGeometry
from rover_env.sim.ground_truth import GroundTruth
from rover_env.sim.ruts import RutMap
from rover_env.sim.textures import tread_texture, write_cached
from rover_env.sim.transforms import quat_to_matrix
from rover_env.sim.urdf import urdf_file

if TYPE_CHECKING:
    from pybullet_utils.bullet_client import BulletClient

    from rover_env.sim.soil_contact import SoilGround
    from rover_env.sim.terrain import Terrain


#: How far past a soil patch's edge a wheel on it stays on it [m]: no flicker at the edge.
SOIL_EDGE = 0.05


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
        self._roll_joints = [self.joint[f"roll_{a}"] for a in AXLES]
        self._travel_joints = [self.joint[f"travel_{a}"] for a in AXLES]
        self.passive_joints = [self.joint[f"{k}_{a}"] for a in AXLES for k in ("travel", "roll")]
        g = geometry
        per_axle_load = g.sprung_mass * GRAVITY / 2.0
        # per passive joint (travel_F, roll_F, travel_R, roll_R): stiffness, damping, preload
        self._k = np.array([g.travel_stiffness, g.roll_stiffness] * 2)
        self._c = np.array([g.travel_damping, g.roll_damping] * 2)
        self._preload = np.array([-per_axle_load, 0.0] * 2)
        self._k_list = self._k.tolist()
        self._c_list = self._c.tolist()
        self._preload_list = self._preload.tolist()
        # The per-substep calls, bound once: BulletClient's attribute lookup costs more than
        # the calls themselves at 240 Hz.
        cid = client._client
        self._read_passive = partial(
            pb.getJointStates, self.body_id, self.passive_joints, physicsClientId=cid
        )
        self._write_passive = partial(
            pb.setJointMotorControlArray,
            self.body_id,
            self.passive_joints,
            pb.TORQUE_CONTROL,
            physicsClientId=cid,
        )
        self._read_base = partial(pb.getBasePositionAndOrientation, self.body_id, physicsClientId=cid)
        self._read_wheels = partial(pb.getLinkStates, self.body_id, self.wheel_links, physicsClientId=cid)
        self._read_wheels_with_velocity = partial(
            pb.getLinkStates, self.body_id, self.wheel_links, computeLinkVelocity=1, physicsClientId=cid
        )
        self._read_knuckles = partial(pb.getLinkStates, self.body_id, self.knuckle_links, physicsClientId=cid)
        self._read_wheel_joints = partial(
            pb.getJointStates, self.body_id, self.wheel_joints, physicsClientId=cid
        )
        self._read_base_velocity = partial(pb.getBaseVelocity, self.body_id, physicsClientId=cid)
        self._read_all_joints = partial(
            pb.getJointStates,
            self.body_id,
            list(range(client.getNumJoints(self.body_id))),
            physicsClientId=cid,
        )
        self._write_wheels = partial(
            pb.setJointMotorControlArray,
            self.body_id,
            self.wheel_joints,
            pb.VELOCITY_CONTROL,
            physicsClientId=cid,
        )
        self._write_steer = partial(
            pb.setJointMotorControl2, self.body_id, controlMode=pb.POSITION_CONTROL, physicsClientId=cid
        )
        self._arms = _ackermann_arms(geometry)
        self._wheel_index = {link: i for i, link in enumerate(self.wheel_links)}
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
            f"tread:v2:{g.correction_marker_arc:.6f}",
            lambda: tread_texture(marker_arc=g.correction_marker_arc),
        )
        self._tread_tex = client.loadTexture(str(tex))
        #: Link index -> image file of the texture on that link's visual shapes.
        self.link_textures = {link: tex for link in self.wheel_links}
        for link in self.wheel_links:
            client.changeVisualShape(
                self.body_id, link, textureUniqueId=self._tread_tex, rgbaColor=[1, 1, 1, 1]
            )
        self._mu = [-1.0] * 4
        self.dig = np.zeros(4)  # how far each wheel has dug into loose soil (0-1)
        #: The deformable soil under the wheels (:meth:`attach_soil`), or None.
        self.soil: SoilGround | None = None
        self._on_soil = [False] * 4
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
        self.dig = np.zeros(4)
        if self.soil is not None:
            self.soil.reset()
            self.ruts.reset(float(position[0]), float(position[1]))
            for i, link in enumerate(self.wheel_links):  # every wheel on the rigid ground again
                if self._on_soil[i]:
                    c.setCollisionFilterPair(self.body_id, self._terrain_id, link, -1, 1)
                    self._on_soil[i] = False
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
        lim = g.steer_limit
        lf = min(lim, max(-lim, float(steer_front)))
        lr = min(lim, max(-lim, float(steer_rear)))
        self.wheel_rate_cmd = rates
        self.steer_cmd = np.array([lf, lr])
        self._write_wheels(targetVelocities=rates.tolist(), forces=[g.wheel_max_torque] * 4)
        for j, delta in zip(self.steer_joints, g.ackermann_angles(lf, lr)):
            self._write_steer(
                jointIndex=j,
                targetPosition=float(delta),
                force=g.steer_max_torque,
                maxVelocity=g.steer_max_rate,
                positionGain=0.2,
                velocityGain=1.0,
            )

    def apply_passive(self) -> None:
        """Spring-damper forces of the passive travel and roll joints (call every substep)."""
        forces = [
            p - k * st[0] - c * st[1]
            for st, k, c, p in zip(self._read_passive(), self._k_list, self._c_list, self._preload_list)
        ]
        self._write_passive(forces=forces)

    def apply_friction(self, terrain: Terrain, states=None) -> None:
        """Set each wheel's friction from the map at its contact point (call every substep).

        The contact point is taken below the wheel centre along the body's -z axis; PyBullet
        multiplies the two bodies' coefficients and the ground's is 1, so the wheel's value is
        the contact's. On loose soil it is reduced by the wheel's :attr:`dig`
        (:meth:`update_dig`). ``states``: this substep's wheel link states, if already read;
        wheels on deformable soil (which do not touch the rigid ground) are left alone.
        """
        x, y, z, w = self._read_base()[1]
        r = self.geom.wheel_radius
        # body z axis (third column of the rotation matrix) times r, x and y components
        zx = 2.0 * (x * z + w * y) * r
        zy = 2.0 * (y * z - w * x) * r
        fmap = terrain.friction
        mu_at, loose, dig = fmap.mu_at, fmap.loose, self.dig
        current = self._mu
        on_soil = self._on_soil
        for i, st in enumerate(self._read_wheels() if states is None else states):
            if on_soil[i]:
                continue
            p = st[4]
            if loose:
                mu, loss = fmap.mu_loss_at(p[0] - zx, p[1] - zy)
                mu *= 1.0 - loss * float(dig[i])
            else:
                mu = mu_at(p[0] - zx, p[1] - zy)
            if mu != current[i]:
                self.client.changeDynamics(self.body_id, self.wheel_links[i], lateralFriction=mu)
                current[i] = mu

    def attach_soil(self, terrain: Terrain, dt: float) -> None:
        """Let the wheels sink into ``terrain``'s deformable soils at substep ``dt`` [s]."""
        from rover_env.sim.soil_contact import SoilGround
        from rover_env.sim.terramechanics import WheelSpec

        g = self.geom
        wheel = WheelSpec(radius=g.wheel_radius, width=g.wheel_width)
        self.soil = SoilGround(list(terrain.friction.soils), wheel, 4, dt)
        #: What the wheels leave in the soil, around the rover (:class:`rover_env.sim.ruts.RutMap`).
        self.ruts = RutMap()
        self._terrain_id = terrain.body_id
        cid = self.client._client
        self._push = partial(pb.applyExternalForce, physicsClientId=cid)
        self._turn = partial(pb.applyExternalTorque, physicsClientId=cid)

    def apply_soil(self, terrain: Terrain, states=None) -> None:
        """Forces of the soil on the wheels standing on it (call every substep, before stepping).

        A wheel over a soil patch stops colliding with the rigid ground and is carried by the
        soil instead (:class:`rover_env.sim.soil_contact.SoilGround`). ``states``: this
        substep's wheel link states with their velocities, if already read.
        """
        soil = self.soil
        if soil is None:
            return
        wheels = np.array(
            [(*st[4], *st[5], *st[6], *st[7]) for st in (states or self._read_wheels_with_velocity())]
        )  # per wheel: frame origin, frame orientation, velocity, angular velocity
        cx, cy = wheels[:, 0], wheels[:, 1]
        ground = terrain.height_at(cx, cy)
        normal = terrain.normal_at(cx, cy)
        fmap = terrain.friction
        index = [fmap.soil_at(x, y) for x, y in zip(cx.tolist(), cy.tolist(), strict=True)]
        for i, was in enumerate(soil.index.tolist()):  # a wheel leaves soil only 5 cm past its edge
            if (
                was >= 0
                and index[i] != was
                and fmap.soil_at(float(cx[i]), float(cy[i]), grow=SOIL_EDGE) == was
            ):
                index[i] = was
        c = self.client
        for i, link in enumerate(self.wheel_links):
            on = index[i] >= 0
            if on != self._on_soil[i]:
                c.setCollisionFilterPair(self.body_id, terrain.body_id, link, -1, int(not on))
                self._on_soil[i] = on
        # the ruts: read where each wheel is about to meet the soil, pressed where it leaves it
        ruts = self.ruts
        x_, y_ = cx.tolist(), cy.tolist()
        ruts.follow(sum(x_) / len(x_), sum(y_) / len(y_))
        c_ = soil.contact
        prior, shear, leave = ruts.meet(wheels, soil.frames, c_.last, c_.rolled, soil.wheel.shear_radius)
        force, torque = soil.step(index, wheels, ground, normal, prior, shear)
        ruts.press(
            leave, soil.frames[:, 0, :2], self.geom.wheel_width, soil.sinkage, c_.last[:, 8], soil.index >= 0,
            soil.rows, soil.index,
        )  # fmt: skip
        push, turn = self._push, self._turn
        for i, link in enumerate(self.wheel_links):
            if index[i] >= 0:
                push(self.body_id, link, force[i].tolist(), wheels[i, :3].tolist(), pb.WORLD_FRAME)
                turn(self.body_id, link, torque[i].tolist(), pb.WORLD_FRAME)

    def _wheel_velocities(self) -> tuple[list[float], list[float], list[tuple[float, float, float]]]:
        """Per wheel: centre velocity along its knuckle's x (rolling) and y (lateral) axes [m/s].

        Also that x axis, the wheel's heading (world frame).
        """
        v_long_l, v_lat_l, heading_l = [], [], []
        for w_st, k_st in zip(self._read_wheels_with_velocity(), self._read_knuckles()):
            vx, vy, vz = w_st[6]
            kx, ky, kz, kw = k_st[5]
            h = (1 - 2 * (ky * ky + kz * kz), 2 * (kx * ky + kz * kw), 2 * (kx * kz - ky * kw))
            v_long_l.append(vx * h[0] + vy * h[1] + vz * h[2])
            v_lat_l.append(
                vx * 2 * (kx * ky - kz * kw)
                + vy * (1 - 2 * (kx * kx + kz * kz))
                + vz * 2 * (ky * kz + kx * kw)
            )
            heading_l.append(h)
        return v_long_l, v_lat_l, heading_l

    def update_dig(self, terrain: Terrain) -> None:
        """Set how far each wheel has dug into loose soil from its exact slip now (call every substep).

        See ``FrictionMapConfig``: the dig follows the slip ratio and slip speed |omega r - v_long|.
        """
        v_long = np.array(self._wheel_velocities()[0])
        rate = np.array([s[1] for s in self._read_wheel_joints()])
        surface = rate * self.geom.wheel_radius
        self.dig = terrain.friction.dig(slip_ratio(surface, v_long), surface - v_long)

    # ------------------------------------------------------------------ ground truth
    def ground_truth(self, t: float, terrain_id: int) -> GroundTruth:
        """Read the exact state (see :class:`GroundTruth` for frames and units)."""
        g = self.geom
        pos, quat = self._read_base()
        lin, ang = self._read_base_velocity()
        rot = quat_to_matrix(quat)
        v_body = rot.T @ np.asarray(lin)
        w_body = rot.T @ np.asarray(ang)
        joints = self._read_all_joints()
        q = [s[0] for s in joints]
        qd = [s[1] for s in joints]
        wheel_steer = np.array([q[j] for j in self.steer_joints])
        v_long_l, v_lat_l, heading = self._wheel_velocities()
        r = g.wheel_radius
        wheel_rate = np.array([qd[j] for j in self.wheel_joints])
        v_long = np.array(v_long_l)
        beta = [math.atan2(vy, vx) for vx, vy in zip(v_long_l, v_lat_l)]
        normal_force = [0.0] * 4
        contact_point = [[math.nan] * 3 for _ in range(4)]
        depth = [math.inf] * 4
        pull = np.zeros(4)
        for p in self.client.getContactPoints(bodyA=self.body_id, bodyB=terrain_id):
            i = self._wheel_index.get(p[3])
            if i is None:
                continue
            normal_force[i] += p[9]
            if p[8] < depth[i]:
                depth[i] = p[8]
                contact_point[i] = p[6]
            # the friction on the wheel (body A) along its heading
            f = p[10] * np.asarray(p[11]) + p[12] * np.asarray(p[13])
            pull[i] += float(f @ heading[i])
        friction = np.array(self._mu, dtype=np.float64)
        sinkage = np.zeros(4)
        curves = np.full((4, 3), math.nan)  # pull ratio, slip of best pull, of best efficiency
        slip = slip_ratio(wheel_rate * r, v_long)
        soil = self.soil
        if soil is not None:  # wheels on soil: the soil's load, its lowest rim point, tan(phi)
            for i, st in enumerate(self._read_wheels()):
                k = int(soil.index[i])
                if k >= 0:
                    heading_i, left = soil.frames[i, 0], soil.frames[i, 1]
                    normal = np.cross(heading_i, left)
                    normal_force[i] = float(soil.contact.last[i, 1])
                    contact_point[i] = (np.asarray(st[4]) - normal * soil.wheel.shear_radius).tolist()
                    friction[i] = float(soil.contact._p[i, 9])
                    sinkage[i] = float(soil.sinkage[i])
                    pull[i] = float(soil.contact.last[i, 0])
                    if normal_force[i] > 0.0:
                        curves[i] = soil.curves[k].at(normal_force[i], float(slip[i]))
        return GroundTruth(
            t=t,
            pose=np.array([*pos, *quat]),
            twist=np.array([v_body[0], v_body[1], w_body[2]]),
            wheel_rate=wheel_rate,
            wheel_angle=np.array([q[j] for j in self.wheel_joints]),
            slip_ratio=slip,
            slip_angle=np.array(beta),
            axle_roll=np.array([q[j] for j in self._roll_joints]),
            axle_height=np.array([-(g.axle_z + q[j]) for j in self._travel_joints]),
            steering=axle_steering_from_wheels(g, wheel_steer, self._arms),
            wheel_steer=wheel_steer,
            wheel_v_long=v_long,
            wheel_v_lat=np.array(v_lat_l),
            wheel_torque=np.array([joints[j][3] for j in self.wheel_joints]),
            friction=friction,
            normal_force=np.array(normal_force),
            contact_point=np.array(contact_point, dtype=np.float64),
            sinkage=sinkage,
            drawbar_pull=pull,
            load=np.array(normal_force),
            pull_ratio=curves[:, 0],
            slip_best_pull=curves[:, 1],
            slip_best_efficiency=curves[:, 2],
        )


def _ackermann_arms(geom: RoverGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Per wheel: arm from the turn-centre line along x [m], lateral offset y [m] (read-only)."""
    arm, y = ackermann_arms(geom.axle_x, geom.track, geom.ackermann_center_x)
    arm.flags.writeable = False
    y.flags.writeable = False
    return arm, y


def axle_steering_from_wheels(
    geom: RoverGeometry, wheel_steer: np.ndarray, arms: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """(lambda_F, lambda_R) from 4 wheel angles [rad].

    See :func:`perception.models.drive_geometry.axle_steering_angles`.
    """
    return axle_steering_angles(arms if arms is not None else _ackermann_arms(geom), wheel_steer)
