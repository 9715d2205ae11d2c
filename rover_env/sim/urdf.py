"""Generate the rover's URDF (and its wheel mesh) from a :class:`RoverGeometry`.

The URDF is the only description of the robot; it is derived from the geometry dataclass every
time (and cached by content hash), so there is no hand-maintained copy to drift.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rover_env.sim.geometry import AXLES, MARKER_THICKNESS, RoverGeometry
from rover_env.sim.textures import cache_dir

BODY_RGBA = (0.78, 0.64, 0.32, 1.0)
MAST_RGBA = (0.25, 0.25, 0.27, 1.0)
METAL_RGBA = (0.35, 0.35, 0.38, 1.0)
DARK_RGBA = (0.18, 0.18, 0.2, 1.0)


def _fmt(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in v)


def _box_inertia(m: float, size) -> tuple[float, float, float]:
    x, y, z = size
    return (m * (y * y + z * z) / 12, m * (x * x + z * z) / 12, m * (x * x + y * y) / 12)


def _inertial(m: float, diag, scale: float) -> str:
    ixx, iyy, izz = (max(v * scale, 1e-6) for v in diag)
    return (
        f'<inertial><origin xyz="0 0 0" rpy="0 0 0"/><mass value="{m:.6g}"/>'
        f'<inertia ixx="{ixx:.6g}" ixy="0" ixz="0" iyy="{iyy:.6g}" iyz="0" izz="{izz:.6g}"/>'
        "</inertial>"
    )


def _visual_box(xyz, rpy, size, rgba) -> str:
    return (
        f'<visual><origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>'
        f'<geometry><box size="{_fmt(size)}"/></geometry>'
        f'<material name="m{abs(hash(tuple(rgba))) % 10**6}"><color rgba="{_fmt(rgba)}"/>'
        "</material></visual>"
    )


def _rpy_z_to(normal) -> tuple[float, float, float]:
    """URDF rpy of a rotation that maps the local z axis onto ``normal``."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, n)
    s = np.linalg.norm(axis)
    if s < 1e-9:
        rot = Rotation.identity() if n[2] > 0 else Rotation.from_rotvec([math.pi, 0, 0])
    else:
        rot = Rotation.from_rotvec(axis / s * math.atan2(s, float(z @ n)))
    with warnings.catch_warnings():  # gimbal lock (normal along +-x) still gives the right rotation
        warnings.simplefilter("ignore", UserWarning)
        r, p, y = rot.as_euler("xyz")
    return (r, p, y)


def max_wheel_steer(geom: RoverGeometry) -> float:
    """Largest per-wheel steering angle the Ackermann mapping can ask for [rad]."""
    angles = np.concatenate(
        [
            np.abs(geom.ackermann_angles(geom.steer_limit, geom.steer_limit)),
            np.abs(geom.ackermann_angles(-geom.steer_limit, -geom.steer_limit)),
        ]
    )
    return float(angles.max())


def wheel_mesh(geom: RoverGeometry, segments: int = 64) -> Path:
    """Write (once) the wheel OBJ: a cylinder about y with tread and sidewall UVs.

    Tread texture u = 0.5 + phi / (2 pi), where phi is the angle about +y from the wheel's +z
    axis (so the correction marker at u = 0.5 sits at +z for wheel angle 0); v in [0.27, 0.98]
    across the tread (image rows of the tread strip), sidewalls at v = 0.1 (the atlas's sidewall
    grey), v = 0 at the image's bottom row. Every triangle is wound counter-clockwise seen from
    outside: renderers cull back faces, and a sidewall wound the other way is not drawn (the
    fisheye then saw the far sidewall through the near one).
    """
    r, w = geom.wheel_radius, geom.wheel_width
    key = f"wheel-v4:{r:.6f}:{w:.6f}:{segments}"
    path = cache_dir() / f"wheel_{hashlib.sha1(key.encode()).hexdigest()[:12]}.obj"
    if path.is_file():
        return path
    lines = ["# rover_env wheel mesh"]
    phis = -math.pi + 2 * math.pi * np.arange(segments + 1) / segments
    for yv, vv in ((w / 2, 0.98), (-w / 2, 0.27)):
        for phi in phis:
            lines.append(f"v {r * math.sin(phi):.6f} {yv:.6f} {r * math.cos(phi):.6f}")
            lines.append(f"vt {0.5 + phi / (2 * math.pi):.6f} {vv:.4f}")
            lines.append(f"vn {math.sin(phi):.6f} 0 {math.cos(phi):.6f}")
    m = segments + 1
    faces = []
    for k in range(segments):
        a, b, c, d = k + 1, k + 2, m + k + 1, m + k + 2
        faces += [(a, c, b), (b, c, d)]
    base = 2 * m
    for side, yv in ((1, w / 2), (-1, -w / 2)):
        centre = base + 1
        lines.append(f"v 0 {yv:.6f} 0")
        lines.append("vt 0.5 0.1")
        lines.append(f"vn 0 {side} 0")
        for phi in phis:
            lines.append(f"v {r * math.sin(phi):.6f} {yv:.6f} {r * math.cos(phi):.6f}")
            lines.append(f"vt {0.5 + phi / (2 * math.pi):.6f} 0.1")
            lines.append(f"vn 0 {side} 0")
        for k in range(segments):
            i, j = centre + 1 + k, centre + 2 + k
            faces.append((centre, i, j) if side > 0 else (centre, j, i))  # counter-clockwise from outside
        base += m + 1
    lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in faces]
    _atomic_write(path, "\n".join(lines) + "\n")
    return path


def _atomic_write(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=path.suffix)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def _mast_visuals(geom: RoverGeometry) -> str:
    """Post, boom and camera housing of the downward camera (visual only: they cast the shadow)."""
    t = geom.mast_thickness
    top = geom.body_size[2] / 2
    cx, cy, cz = geom.mast_camera_position
    housing = (0.07, 0.09, 0.05)
    boom_z = cz + housing[2] + t / 2  # above the housing, out of the camera's view
    post_h = boom_z + t / 2 - top
    boom_len = cx - geom.mast_x + t / 2
    return (
        _visual_box((geom.mast_x, cy, top + post_h / 2), (0, 0, 0), (t, t, post_h), MAST_RGBA)
        + _visual_box(
            (geom.mast_x - t / 2 + boom_len / 2, cy, boom_z), (0, 0, 0), (boom_len, t, t), MAST_RGBA
        )
        + _visual_box((cx, cy, cz + 0.005 + housing[2] / 2), (0, 0, 0), housing, MAST_RGBA)
    )


def build_urdf(geom: RoverGeometry) -> str:
    """The rover's URDF text for ``geom``.

    Wheels collide as spheres of the wheel radius: a fully crowned tyre with one contact point
    under the centre. A flat rigid cylinder on rigid ground flips its load between the tread
    edges every few steps, which shows up as about 2 % of false slip in turns; the sphere rolls
    as an exact circle. The wheel's visual is the textured cylinder.

    Link names: ``body``; per axle a in F, R: ``carriage_a``, ``axle_a``; per wheel w in
    FL, FR, RL, RR: ``knuckle_w``, ``wheel_w``. Joint names: ``travel_a`` (prismatic z),
    ``roll_a`` (revolute x), ``steer_w`` (revolute z), ``wheel_w`` (continuous y).
    """
    s = geom.inertia_scale
    fid = {f.name: f for f in geom.fiducials()}
    parts = ['<?xml version="1.0"?>', '<robot name="rover">']
    parts.append(
        f'<link name="body">{_inertial(geom.body_mass, _box_inertia(geom.body_mass, geom.body_size), s)}'
        + _visual_box((0, 0, 0), (0, 0, 0), geom.body_size, BODY_RGBA)
        + _mast_visuals(geom)
        + f'<collision><origin xyz="0 0 0" rpy="0 0 0"/><geometry><box size="{_fmt(geom.body_size)}"/>'
        "</geometry></collision></link>"
    )
    steer_lim = max_wheel_steer(geom) + math.radians(3)
    mesh = wheel_mesh(geom)
    r, w = geom.wheel_radius, geom.wheel_width
    wheel_inertia = (
        geom.wheel_mass * (3 * r * r + w * w) / 12,
        geom.wheel_mass * r * r / 2,
        geom.wheel_mass * (3 * r * r + w * w) / 12,
    )
    for axle in AXLES:
        origin = geom.axle_origin(axle)
        beam = geom.axle_beam_size
        plate, rod = ("A", "B") if axle == "F" else ("C", "D")
        parts.append(
            f'<link name="carriage_{axle}">'
            f"{_inertial(geom.carriage_mass, _box_inertia(geom.carriage_mass, (0.08, 0.08, 0.08)), s)}"
            + _visual_box((0, 0, 0.02), (0, 0, 0), (0.07, 0.07, 0.06), DARK_RGBA)
            + "</link>"
        )
        parts.append(
            f'<joint name="travel_{axle}" type="prismatic"><parent link="body"/>'
            f'<child link="carriage_{axle}"/><origin xyz="{_fmt(origin)}" rpy="0 0 0"/>'
            f'<axis xyz="0 0 1"/><limit lower="{-geom.travel_limit:.6g}" '
            f'upper="{geom.travel_limit:.6g}" effort="5000" velocity="5"/></joint>'
        )
        axle_visuals = _visual_box((0, 0, 0), (0, 0, 0), beam, METAL_RGBA)
        for idx in (1, 2):
            f = fid[f"{plate}{idx}"]
            axle_visuals += _visual_box(
                f.position, _rpy_z_to(f.normal), (f.size, f.size, MARKER_THICKNESS), f.rgba
            )
        parts.append(
            f'<link name="axle_{axle}">'
            f"{_inertial(geom.axle_mass, _box_inertia(geom.axle_mass, beam), s)}"
            f"{axle_visuals}</link>"
        )
        parts.append(
            f'<joint name="roll_{axle}" type="revolute"><parent link="carriage_{axle}"/>'
            f'<child link="axle_{axle}"/><origin xyz="0 0 0" rpy="0 0 0"/>'
            f'<axis xyz="1 0 0"/><limit lower="{-geom.roll_limit:.6g}" '
            f'upper="{geom.roll_limit:.6g}" effort="5000" velocity="10"/></joint>'
        )
        for idx, side in ((1, "L"), (2, "R")):
            wheel = axle + side
            f = fid[f"{rod}{idx}"]
            tip = np.asarray(f.position)
            # horizontal arm from the kingpin to just short of the tip, under the marker plate
            arm_len = float(np.hypot(tip[0], tip[1])) - 0.012
            arm_yaw = math.atan2(tip[1], tip[0])
            arm_mid = (arm_len / 2 * math.cos(arm_yaw), arm_len / 2 * math.sin(arm_yaw), tip[2])
            knuckle_vis = _visual_box(arm_mid, (0, 0, arm_yaw), (arm_len, 0.015, 0.012), METAL_RGBA)
            knuckle_vis += _visual_box(
                f.position, _rpy_z_to(f.normal), (f.size, f.size, MARKER_THICKNESS), f.rgba
            )
            parts.append(
                f'<link name="knuckle_{wheel}">'
                f"{_inertial(geom.knuckle_mass, _box_inertia(geom.knuckle_mass, (0.05, 0.05, 0.05)), s)}"
                f"{knuckle_vis}</link>"
            )
            parts.append(
                f'<joint name="steer_{wheel}" type="revolute"><parent link="axle_{axle}"/>'
                f'<child link="knuckle_{wheel}"/>'
                f'<origin xyz="{_fmt(geom.wheel_offset(wheel))}" rpy="0 0 0"/>'
                f'<axis xyz="0 0 1"/><limit lower="{-steer_lim:.6g}" upper="{steer_lim:.6g}" '
                f'effort="{geom.steer_max_torque:.6g}" velocity="{geom.steer_max_rate:.6g}"/>'
                "</joint>"
            )
            parts.append(
                f'<link name="wheel_{wheel}">{_inertial(geom.wheel_mass, wheel_inertia, s)}'
                f'<visual><origin xyz="0 0 0" rpy="0 0 0"/><geometry><mesh filename="{mesh}" '
                'scale="1 1 1"/></geometry></visual>'
                '<collision><origin xyz="0 0 0" rpy="0 0 0"/><geometry>'
                f'<sphere radius="{r:.6g}"/></geometry></collision></link>'
            )
            parts.append(
                f'<joint name="wheel_{wheel}" type="continuous"><parent link="knuckle_{wheel}"/>'
                f'<child link="wheel_{wheel}"/><origin xyz="0 0 0" rpy="0 0 0"/>'
                f'<axis xyz="0 1 0"/><limit effort="{geom.wheel_max_torque:.6g}" '
                f'velocity="{geom.wheel_max_rate:.6g}"/></joint>'
            )
    parts.append("</robot>")
    return "\n".join(parts)


def urdf_file(geom: RoverGeometry) -> Path:
    """Path of the cached URDF for ``geom`` (written on first use)."""
    text = build_urdf(geom)
    path = cache_dir() / f"rover_{hashlib.sha1(text.encode()).hexdigest()[:16]}.urdf"
    if not path.is_file():
        _atomic_write(path, text)
    return path
