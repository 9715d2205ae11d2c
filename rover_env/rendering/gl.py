"""OpenGL rendering of a PyBullet scene (moderngl, OpenGL 3.3 core, headless EGL).

:class:`GLRenderer` mirrors the visual shapes of every body in one ``BulletClient`` (boxes,
spheres, cylinders and OBJ meshes with their colours and textures) and the terrain's exact height
grid, poses the links at each render by forward kinematics from the base pose and joint
positions that PyBullet reports (reading only: the physics does not depend on what is rendered),
and draws:

* pinhole views with exactly the intrinsics K of :class:`perception.PinholeCamera` (pixel
  centres at integer coordinates, row 0 at the top), diffuse sun and ambient sky light, and the
  shadow of every body but the ground, from a shadow map rendered from the sun (orthographic,
  fitted to the casters' bounding sphere, normal-offset);
* fisheye images: the :class:`rover_env.rendering.cubemap.CubemapRemap` views rendered into one atlas,
  read back and remapped on the CPU through the exact :class:`perception.OmniCamera` map (one
  fixed-point ``cv2.remap``: cheaper than a remap pass on llvmpipe);
* per-pixel labels for tests and evaluation: segmentation (body + ((link + 1) << 24)), depth
  along the optical axis and world points.

Textures are mipmapped and sampled trilinearly (see :data:`LOD_BIAS`). One GL context per
renderer (one per simulation); :meth:`GLRenderer.release` frees it. On Mesa's llvmpipe set
``LP_NUM_THREADS`` to choose how many cores it rasterises on. The same code runs on a GPU.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rover_env.config.cameras import FINE_RADIUS
from rover_env.rendering.base import (
    RUT_VIEW_HALF,
    FisheyeView,
    Lighting,
    MotionSpec,
    RenderedView,
    Renderer,
    view_planes,
)
from rover_env.sim.terrain import Terrain
from rover_env.sim.transforms import quat_to_matrix

if TYPE_CHECKING:
    from rover_env.rendering.cubemap import CubemapRemap

log = logging.getLogger(__name__)

SHADOW_MAP_PX = 2048  # largest shadow map edge [texels]
#: Textures are sampled one mipmap level sharper than a pixel's footprint asks for. Trilinear
#: mipmapping picks its level from the footprint's longest side, which blurs ground seen at a
#: slant and the treads; at the default level the train preset's slip events are less precise
#: and the wheel rates less accurate (benchmarks/ablations.py lod_bias).
LOD_BIAS = -1.0
_CHUNK = 0.8  # [m] least edge of a terrain chunk (the unit of view culling)
_CHUNK_CELLS = 8  # least grid cells along a chunk's edge

# One source, four programs: GROUND (untinted texture) or bodies (colours, optional texture), each
# with or without
# LABELS (segmentation, depth and world point outputs: for tests and evaluation only, since every
# varying costs time per pixel on a CPU rasteriser). Vertices are in the world frame: bodies are
# posed on the CPU (indexing link matrices per vertex in a shader is slow on llvmpipe).
_SCENE_VS = """
uniform mat4 u_proj;
uniform mat4 u_view;
uniform mat4 u_light;
uniform float u_normal_offset;
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
out vec3 v_normal;
out vec2 v_uv;
out vec3 v_light;
#ifndef GROUND
in vec4 in_color;
in float in_link;
out vec4 v_color;
#else
out vec2 v_xy;
#endif
#ifdef LABELS
out vec3 v_world;
out float v_depth;
flat out int v_link;
#endif
#ifdef MOTION
// each link's centre of mass, linear and angular velocity (index: link + 1), world frame
uniform vec3 u_com[MOTION_LINKS];
uniform vec3 u_lin[MOTION_LINKS];
uniform vec3 u_ang[MOTION_LINKS];
uniform bool u_moving;
uniform mat3 u_cam_R;  // world -> the view's optical frame
uniform vec3 u_cam_c;  // its origin [m]
uniform vec3 u_cam_v;  // its velocity [m/s]
uniform vec3 u_cam_w;  // its angular velocity [rad/s]
out vec3 v_p;  // the point relative to the camera, optical frame [m]
out vec3 v_q;  // its velocity relative to the camera, optical frame [m/s]
#endif
void main() {
    vec4 w = vec4(in_pos, 1.0);
    vec3 n = in_normal;
#ifndef GROUND
    v_color = in_color;
#else
    v_xy = w.xy;
#endif
    vec4 cam = u_view * w;
    gl_Position = u_proj * cam;
    v_normal = n;
    v_uv = in_uv;
    v_light = (u_light * vec4(w.xyz + u_normal_offset * n, 1.0)).xyz * 0.5 + 0.5;
#ifdef MOTION
    // both are affine in position over a rigid triangle: exact when interpolated
#ifdef GROUND
    vec3 vel = vec3(0.0);
#else
    int k = int(in_link + 0.5);
    vec3 vel = u_moving ? u_lin[k] + cross(u_ang[k], w.xyz - u_com[k]) : vec3(0.0);
#endif
    vec3 d = w.xyz - u_cam_c;
    v_p = u_cam_R * d;
    v_q = u_cam_R * (vel - u_cam_v - cross(u_cam_w, d));
#endif
#ifdef LABELS
    v_world = w.xyz;
    v_depth = cam.z;
#ifdef GROUND
    v_link = 0;
#else
    v_link = int(in_link + 0.5);
#endif
#endif
}
"""

_SCENE_FS = """
uniform sampler2D u_tex;
uniform float u_lod_bias;
uniform bool u_textured;
uniform sampler2DShadow u_shadow;
uniform bool u_shadows;
uniform vec3 u_sun;
uniform float u_ambient;
uniform float u_diffuse;
// cloud shadows: u = dot(a.xy, light uv) + a.z metres past the leading edge; b = (length,
// transmission, edge)
uniform int u_nclouds;
uniform vec3 u_cloud_a[4];
uniform vec3 u_cloud_b[4];
#ifdef GROUND
uniform bool u_look;  // the ground's albedo and contrast changed (domain randomisation)
uniform float u_albedo;
uniform float u_contrast;
uniform vec3 u_tex_mean;
// the ruts (rover_env.sim.ruts): depth of the soil's surface below the ground [m], its box
// (x0, y0, 1 / edge x, 1 / edge y) [m, 1/m] and cell [m]
uniform bool u_has_ruts;
uniform sampler2D u_ruts;
uniform vec4 u_rut_box;
uniform float u_rut_cell;
in vec2 v_xy;
#endif
in vec3 v_normal;
in vec2 v_uv;
in vec3 v_light;
layout(location = 0) out vec4 f_color;
#ifndef GROUND
in vec4 v_color;
#endif
#ifdef LABELS
uniform int u_body;
in vec3 v_world;
in float v_depth;
flat in int v_link;
layout(location = 1) out int f_id;
layout(location = 2) out float f_depth;
layout(location = 3) out vec4 f_world;
#endif
#ifdef MOTION
uniform vec3 u_focal;  // the view's fx, skew and fy [px]
in vec3 v_p;
in vec3 v_q;
layout(location = 1) out vec2 f_motion;
#endif
void main() {
#ifdef GROUND
    vec4 albedo = texture(u_tex, v_uv, u_lod_bias);
    if (u_look) albedo.rgb = u_albedo * (u_tex_mean + u_contrast * (albedo.rgb - u_tex_mean));
#else
    vec4 albedo = v_color;
    if (u_textured) albedo *= texture(u_tex, v_uv, u_lod_bias);
#endif
    vec3 nrm = normalize(v_normal);
#ifdef GROUND
    if (u_has_ruts) {
        vec2 uv = (v_xy - u_rut_box.xy) * u_rut_box.zw;
        if (all(greaterThan(uv, vec2(0.0))) && all(lessThan(uv, vec2(1.0)))) {
            // the surface z = ground - depth: the depth's slope tilts the ground's normal
            vec2 du = vec2(u_rut_cell * u_rut_box.z, 0.0);
            vec2 dv = vec2(0.0, u_rut_cell * u_rut_box.w);
            float gx = texture(u_ruts, uv + du).r - texture(u_ruts, uv - du).r;
            float gy = texture(u_ruts, uv + dv).r - texture(u_ruts, uv - dv).r;
            nrm = normalize(nrm / nrm.z + vec3(gx, gy, 0.0) / (2.0 * u_rut_cell));
        }
    }
#endif
    float cos_i = max(dot(nrm, u_sun), 0.0);
    float lit = u_shadows ? texture(u_shadow, v_light) : 1.0;
    float sky = 1.0;
    for (int i = 0; i < u_nclouds; ++i) {
        float u = dot(u_cloud_a[i].xy, v_light.xy) + u_cloud_a[i].z;
        float e = u_cloud_b[i].z;
        float cover = clamp(0.5 - u / e, 0.0, 1.0) * clamp(0.5 + (u + u_cloud_b[i].x) / e, 0.0, 1.0);
        sky *= 1.0 - cover * (1.0 - u_cloud_b[i].y);
    }
    float shade = u_ambient + u_diffuse * sky * cos_i * lit;
    f_color = vec4(min(albedo.rgb * shade, vec3(1.0)), lit < 0.5 ? 1.0 : 0.0);
#ifdef MOTION
    // the pixel's velocity: K's rows times d(p.xy / p.z)/dt
    float iz = 1.0 / v_p.z;
    vec2 n_dot = (v_q.xy - v_p.xy * (v_q.z * iz)) * iz;
    f_motion = vec2(u_focal.x * n_dot.x + u_focal.y * n_dot.y, u_focal.z * n_dot.y);
#endif
#ifdef LABELS
    f_id = u_body + (v_link << 24);
    f_depth = v_depth;
    f_world = vec4(v_world, 1.0);
#endif
}
"""


#: Links (base included) whose velocities the motion program takes.
MOTION_LINKS = 32
#: Program modes: colour only, colour and labels, colour and velocity buffer.
_MODES: tuple[bool | str, ...] = (False, True, "motion")
_MODE_DEFINES: dict[bool | str, tuple[str, ...]] = {
    False: (),
    True: ("LABELS",),
    "motion": ("MOTION", f"MOTION_LINKS {MOTION_LINKS}"),
}


def _variant(source: str, *defines: str) -> str:
    return "#version 330\n" + "".join(f"#define {d}\n" for d in defines) + source


_DEPTH_VS = """
#version 330
uniform mat4 u_light;
in vec3 in_pos;
void main() {
    gl_Position = u_light * vec4(in_pos, 1.0);
}
"""

_DEPTH_FS = """
#version 330
void main() {}
"""

# The pixels a view need not draw, at the near plane first: the scene's fragments there fail the
# depth test before they are shaded (llvmpipe tests depth early), and they stay the clear colour.
_SKIP_VS = """
#version 330
in vec2 in_pos;
void main() {
    gl_Position = vec4(in_pos, -1.0, 1.0);
}
"""

_SKIP_FS = """
#version 330
layout(location = 0) out vec4 f_color;
layout(location = 1) out vec2 f_motion;
void main() {
    f_color = vec4(0.0);
    f_motion = vec2(0.0);
}
"""


def skip_rects(keep: np.ndarray) -> np.ndarray:
    """Rectangles (N, 4) int (x0, y0, x1, y1) [px, end exclusive] that cover every pixel not in ``keep``.

    ``keep``: (H, W) bool, the pixels that must be drawn. One rectangle per row and run of
    pixels not kept (a few hundred for a lens's outline: nothing to draw).
    """
    keep = np.asarray(keep, dtype=bool)
    out = []
    for y, row in enumerate(keep):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], (~row).view(np.int8), [0]])))
        for x0, x1 in zip(edges[::2], edges[1::2], strict=True):
            out.append((int(x0), y, int(x1), y + 1))
    return np.array(out, dtype=np.int64).reshape(-1, 4)


class GLUnavailableError(RuntimeError):
    """An OpenGL 3.3 context cannot be created on this machine (the message says why)."""


_EGL_PID: int | None = None  # the process that created an EGL context in this address space


def usable_here() -> tuple[bool, str]:
    """Whether this process may create GL contexts.

    :func:`gl_status`, and not a fork of a process that had already used EGL (Mesa's state does
    not survive a fork: the child would hang).

    Returns:
        (usable, reason): reason is "" when usable.
    """
    if _EGL_PID is not None and _EGL_PID != os.getpid():
        return False, (
            "this process was forked from one that had already rendered with OpenGL, and Mesa's EGL "
            "state does not survive a fork; start workers with 'spawn' or 'forkserver' (for example "
            "gymnasium.make_vec(..., vector_kwargs={'context': 'forkserver'}); stable-baselines3's "
            "SubprocVecEnv uses forkserver), or create the environments before rendering in the parent"
        )
    return gl_status()


@functools.lru_cache(maxsize=1)
def gl_status() -> tuple[bool, str]:
    """Whether a headless EGL OpenGL 3.3 context can be created here, and why not.

    Probed once per process in a child process, so that a failing or crashing driver cannot take
    this process down and no EGL state exists in this process before it forks (vector
    environments fork their workers).

    Returns:
        (available, reason): reason is "" when available, else what is missing.
    """
    try:
        import moderngl  # noqa: F401
    except ImportError as exc:
        return False, f"the Python package moderngl is not installed ({exc}); pip install moderngl"
    import ctypes.util

    if ctypes.util.find_library("EGL") is None:
        return False, "libEGL.so is not installed (Debian: apt-get install libegl1 libgl1-mesa-dri)"
    probe = (
        "import moderngl\n"
        "ctx = moderngl.create_context(standalone=True, backend='egl')\n"
        "assert ctx.version_code >= 330, ctx.version_code\n"
        "print(ctx.info['GL_RENDERER'])\n"
        "ctx.release()\n"
    )
    try:
        out = subprocess.run(
            [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, env=dict(os.environ)
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"the EGL probe did not run ({exc})"
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["no message"])[-1]
        return False, (
            f"no EGL OpenGL 3.3 context could be created ({last}); a headless machine needs Mesa's "
            "EGL and llvmpipe (Debian: apt-get install libegl1 libgl1-mesa-dri)"
        )
    log.debug("OpenGL renderer: %s", out.stdout.strip())
    return True, ""


def _create_context():
    global _EGL_PID
    import moderngl

    ok, why = usable_here()
    if not ok:
        raise GLUnavailableError(why)
    _EGL_PID = os.getpid()
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl")
    except Exception as exc:  # moderngl raises plain Exception subclasses
        raise GLUnavailableError(f"no EGL OpenGL context could be created: {exc}") from exc
    if ctx.version_code < 330:
        ctx.release()
        raise GLUnavailableError(f"OpenGL {ctx.version_code} < 3.3 on {ctx.info['GL_RENDERER']}")
    return ctx


@functools.lru_cache(maxsize=32)
def load_obj(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles of an OBJ mesh: (N, 3) positions, (N, 3) normals, (N, 2) uvs per corner (N = 3 x faces).

    Polygons are split into fans; missing normals are the faces' own, missing uvs are 0.

    Raises:
        ValueError: The file has no faces or an index out of range.
    """
    v, vt, vn, corners = [], [], [], []
    with open(path) as fh:
        for line in fh:
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "v":
                v.append([float(x) for x in tok[1:4]])
            elif tok[0] == "vt":
                vt.append([float(x) for x in tok[1:3]])
            elif tok[0] == "vn":
                vn.append([float(x) for x in tok[1:4]])
            elif tok[0] == "f":
                idx = []
                for corner in tok[1:]:
                    parts = (corner.split("/") + ["", ""])[:3]
                    idx.append([int(p) if p else 0 for p in parts])
                for k in range(1, len(idx) - 1):
                    corners += [idx[0], idx[k], idx[k + 1]]
    if not corners:
        raise ValueError(f"{path}: no faces in this OBJ mesh")
    c = np.asarray(corners)
    pos_all, uv_all, n_all = (
        np.asarray(v, float),
        np.asarray(vt or [[0, 0]], float),
        np.asarray(vn or [[0, 0, 1]], float),
    )

    def pick(arr, col):
        i = c[:, col]
        i = np.where(i < 0, len(arr) + i, i - 1)
        if np.any(i >= len(arr)):
            raise ValueError(f"{path}: a face refers to a missing vertex, uv or normal")
        return arr[np.maximum(i, 0)]

    pos = pick(pos_all, 0)
    uv = pick(uv_all, 1) if vt else np.zeros((len(c), 2))
    if vn:
        nrm = pick(n_all, 2)
    else:
        tri = pos.reshape(-1, 3, 3)
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
        nrm = np.repeat(fn, 3, axis=0)
    return pos, nrm, uv


def _box(half):
    """Triangles of a box with half extents ``half`` [m]: positions, normals, uvs."""
    pos, nrm, uv = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            a, b = [(axis + 1) % 3, (axis + 2) % 3]
            quad = []
            for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis] = sign * half[axis]
                p[a], p[b] = s * half[a], t * half[b]
                quad.append(p)
            for i in (0, 1, 2, 0, 2, 3):
                pos.append(quad[i])
                nrm.append(n)
                uv.append([0.5 + 0.5 * np.sign(quad[i][a]), 0.5 + 0.5 * np.sign(quad[i][b])])
    return np.array(pos), np.array(nrm), np.array(uv)


def _cylinder(radius, length, segments=48):
    phi = np.linspace(0, 2 * math.pi, segments + 1)
    pos, nrm, uv = [], [], []
    for k in range(segments):
        p0, p1 = phi[k], phi[k + 1]
        c0, s0, c1, s1 = math.cos(p0), math.sin(p0), math.cos(p1), math.sin(p1)
        z0, z1 = -length / 2, length / 2
        quad = [(c0, s0, z0), (c1, s1, z0), (c1, s1, z1), (c0, s0, z1)]
        for i in (0, 1, 2, 0, 2, 3):
            cx, sx, z = quad[i]
            pos.append([radius * cx, radius * sx, z])
            nrm.append([cx, sx, 0.0])
            uv.append([k / segments, 0.5 + z / length])
        for z, sgn in ((z1, 1.0), (z0, -1.0)):
            tri = [(0.0, 0.0), (c0, s0), (c1, s1)] if sgn > 0 else [(0.0, 0.0), (c1, s1), (c0, s0)]
            for cx, sx in tri:
                pos.append([radius * cx, radius * sx, z])
                nrm.append([0.0, 0.0, sgn])
                uv.append([0.5, 0.5])
    return np.array(pos), np.array(nrm), np.array(uv)


def _sphere(radius, rings=16, segments=32):
    th = np.linspace(0, math.pi, rings + 1)
    ph = np.linspace(0, 2 * math.pi, segments + 1)
    pos, uv = [], []
    for i in range(rings):
        for j in range(segments):
            q = [(th[i], ph[j]), (th[i + 1], ph[j]), (th[i + 1], ph[j + 1]), (th[i], ph[j + 1])]
            for k in (0, 1, 2, 0, 2, 3):
                t, p = q[k]
                pos.append([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])
                uv.append([p / (2 * math.pi), t / math.pi])
    n = np.array(pos)
    return radius * n, n, np.array(uv)


#: Index-buffer gaps shorter than this are drawn rather than skipped: a draw call costs more on
#: llvmpipe (~60 us) than some hundred off-screen triangles.
_MERGE_GAP = 600


def _index_runs(bounds: np.ndarray, items: np.ndarray) -> list[tuple[int, int]]:
    """Draws (first index, count) of ``items`` (sorted), item i spanning ``bounds[i:i + 2]``.

    Consecutive items share a draw, and runs less than ``_MERGE_GAP`` indices apart are merged.
    """
    if not len(items):
        return []
    runs = []
    a, b = int(bounds[items[0]]), int(bounds[items[0] + 1])
    for i in items[1:].tolist():
        lo, hi = int(bounds[i]), int(bounds[i + 1])
        if lo - b < _MERGE_GAP:
            b = hi
        else:
            runs.append((a, b - a))
            a, b = lo, hi
    runs.append((a, b - a))
    return [r for r in runs if r[1] > 0]


def _pose_matrix(pos, orn) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_matrix(orn), pos
    return T


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` [rad] about the unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _joint_table(client, body: int) -> list:
    """The kinematic chain of ``body``, one entry per joint (= link).

    Each: parent link, parent inertial -> joint frame (4x4), unit axis, kind ("revolute",
    "prismatic" or "fixed") and joint -> own inertial frame (4x4).
    """
    import pybullet as pb

    out = []
    for k in range(client.getNumJoints(body)):
        info = client.getJointInfo(body, k)
        kind = {pb.JOINT_REVOLUTE: "revolute", pb.JOINT_PRISMATIC: "prismatic"}.get(info[2], "fixed")
        axis = np.asarray(info[13], dtype=np.float64)
        if np.linalg.norm(axis) > 0:
            axis = axis / np.linalg.norm(axis)
        dyn = client.getDynamicsInfo(body, k)
        out.append((info[16], _pose_matrix(info[14], info[15]), axis, kind, _pose_matrix(dyn[3], dyn[4])))
    return out


def projection_from_K(K: np.ndarray, size: tuple[int, int], near: float, far: float) -> np.ndarray:
    """4x4 matrix from the camera optical frame (x right, y down, z forward) [m] to GL clip space.

    Window pixel (i, j) (centre at i + 0.5, j + 0.5) sees image point (i, j) of the pinhole ``K``:
    pixel centres at integer coordinates, and window row j is image row j (row 0 is read back
    first, so images need no flip). ``size`` = (W, H) [px]; ``near``/``far`` clip distances [m].
    """
    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    P = np.zeros((4, 4))
    P[0, 0] = 2 * fx / w
    P[0, 2] = 2 * (cx + 0.5) / w - 1
    P[1, 1] = 2 * fy / h
    P[1, 2] = 2 * (cy + 0.5) / h - 1
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


_UNIFORMS: dict[int, dict] = {}  # id(program) -> {name: (uniform or None, last value)}


def _set(prog, name: str, value) -> None:
    """Set uniform ``name`` of ``prog`` (bytes are written raw) if it changed.

    A uniform that the compiler removed is skipped.
    """
    cache = _UNIFORMS.setdefault(id(prog), {})
    entry = cache.get(name)
    if entry is None:
        try:
            entry = [prog[name], None]
        except KeyError:
            entry = [None, None]
        cache[name] = entry
    u = entry[0]
    if u is None or entry[1] == value:
        return
    entry[1] = value
    if isinstance(value, bytes):
        u.write(value)
    else:
        u.value = value


_VERTEX = (
    ("3f", "in_pos", 12),
    ("3f", "in_normal", 12),
    ("2f", "in_uv", 8),
    ("4f", "in_color", 16),
    ("1f", "in_link", 4),
)


def _layout(prog, vbo, skip=()) -> tuple:
    """A vertex-array binding of the 13-float vertex layout for ``prog``, skipping what it does not read."""
    fmt, names = [], []
    for f, name, nbytes in _VERTEX:
        try:
            prog[name]
            present = name not in skip
        except KeyError:
            present = False
        if present:
            fmt.append(f)
            names.append(name)
        else:
            fmt.append(f"{nbytes}x")
    return (vbo, " ".join(fmt), *names)


def _cloud_uniforms(bands, light: np.ndarray) -> tuple[tuple, bytes, bytes]:
    """The scene program's cloud-shadow uniforms for ``bands`` under light matrix ``light``.

    A band's place u [m past its leading edge] is affine in the light's (u, v) texture
    coordinates, which are the same along a sun ray: solved from three ground points.
    """
    if not bands:
        return (), b"", b""
    a = np.zeros((4, 3), np.float32)
    b = np.zeros((4, 3), np.float32)

    def uv(x, y):
        return (light[:2, :2] @ (x, y) + light[:2, 3]) * 0.5 + 0.5  # z = 0

    for i, (dx, dy, lead, length, trans, edge) in enumerate(bands[:4]):
        p0 = uv(dx * lead, dy * lead)
        M = np.array([uv(dx * (lead + 1), dy * (lead + 1)) - p0, uv(dx * lead - dy, dy * lead + dx) - p0])
        g = np.linalg.solve(M, [1.0, 0.0])  # one metre along the wind, none across it
        a[i] = (g[0], g[1], -float(g @ p0))
        b[i] = (length, trans, edge)
    return tuple(bands[:4]), a.tobytes(), b.tobytes()


def _link_arrays(links: dict) -> tuple[bytes, bytes, bytes]:
    """The motion program's (com, linear, angular velocity) arrays of ``links`` (index: link + 1)."""
    out = np.zeros((3, MOTION_LINKS, 3), np.float32)
    for k, (c, v, w) in links.items():
        if not -1 <= k < MOTION_LINKS - 1:
            raise ValueError(f"link {k}: the motion program takes links -1..{MOTION_LINKS - 2}")
        out[:, k + 1] = (c, v, w)
    return out[0].tobytes(), out[1].tobytes(), out[2].tobytes()


def _gl(m: np.ndarray) -> bytes:
    """A float32 column-major copy of matrix ``m`` for a uniform."""
    return np.asarray(m, dtype=np.float32).T.tobytes()


class _Group:
    """Triangles of one body sharing a texture, posed into the world on the CPU.

    13-float vertices in link frames (the last float is link + 1), uploaded when the body moves.
    """

    def __init__(self, local: np.ndarray, tris: np.ndarray, vbo, vaos: dict, texture) -> None:
        self.local = local
        links = self.local[:, 12].astype(np.int64)
        n = int(links.max()) + 2
        self.bounds = np.searchsorted(links, np.arange(n))  # vertex range of each link
        tri_links = links[tris[:, 0]]
        #: Index-buffer range [first, last) of each link's triangles (3 indices each).
        self.tri_bounds = 3 * np.searchsorted(tri_links, np.arange(n))
        #: (links + 1,) link-frame centre and radius of each link's vertices [m].
        self.centre = np.zeros((n - 1, 3))
        self.radius = np.full(n - 1, -1.0)  # -1: no vertices
        for k in range(n - 1):
            p = local[self.bounds[k] : self.bounds[k + 1], :3]
            if len(p):
                self.centre[k] = 0.5 * (p.min(axis=0) + p.max(axis=0))
                self.radius[k] = float(np.linalg.norm(p - self.centre[k], axis=1).max())
        self.world = self.local.copy()
        self.world_centre = self.centre.copy()
        self.vbo, self.vaos, self.count, self.texture = vbo, vaos, 3 * len(tris), texture

    def visible_runs(self, planes: np.ndarray) -> list[tuple[int, int]]:
        """(first index, index count) of the runs of links whose bounding sphere may be in view."""
        dist = self.world_centre @ planes[:, :3].T + planes[:, 3]  # (links, planes)
        seen = (self.radius >= 0) & np.all(dist >= -self.radius[:, None], axis=1)
        return _index_runs(self.tri_bounds, np.flatnonzero(seen))

    def pose(self, M: np.ndarray) -> None:
        """Move the vertices to link poses ``M`` ((links + 1, 4, 4), link -> world) and upload them."""
        L, W = self.local, self.world
        for k in range(len(self.bounds) - 1):
            a, b = self.bounds[k], self.bounds[k + 1]
            if a == b:
                continue
            R, t = M[k, :3, :3], M[k, :3, 3]
            W[a:b, 0:3] = L[a:b, 0:3] @ R.T + t
            W[a:b, 3:6] = L[a:b, 3:6] @ R.T
        m = len(self.centre)
        self.world_centre = np.einsum("kij,kj->ki", M[:m, :3, :3], self.centre) + M[:m, :3, 3]
        self.vbo.write(W.tobytes())


class GLRenderer(Renderer):
    """Draws one PyBullet client's scene with OpenGL; see the module docstring.

    Args:
        client: The BulletClient whose bodies are drawn (a body created later is picked up at
            the next render; its visual shapes must not change after its first render).
        terrain: The ground; drawn from its exact height grid (its PyBullet body is not mirrored).
        textures: PyBullet texture id -> image file, for the textures assigned to bodies.
        link_textures: (body, link) -> image file: the texture of that link's visual shapes
            (PyBullet does not report textures set by ``changeVisualShape`` on mesh shapes).
        shadow_px: Largest shadow-map edge [texels].
        lod_bias: Mipmap level bias of texture sampling [levels] (see :data:`LOD_BIAS`).
        ruts: The wheels' ruts in deformable soil (:class:`rover_env.sim.ruts.RutMap`), if any:
            within :data:`~rover_env.rendering.base.RUT_VIEW_HALF` of the focus the ground is
            shaded with the slope of their surface (its normal tilted, texel by texel). The
            ruts do not move the ground's triangles: the depth's parallax (a 2 cm rut seen from
            0.5 m moves its floor by 4 % of the distance to the view's centre) and the shadows
            cast inside a rut are not drawn.

    Raises:
        GLUnavailableError: No OpenGL 3.3 context can be created.
    """

    name = "gl"
    draws_motion = True

    def __init__(
        self,
        client,
        terrain: Terrain | None = None,
        textures: dict[int, str | Path] | None = None,
        link_textures: dict[tuple[int, int], str | Path] | None = None,
        shadow_px: int = SHADOW_MAP_PX,
        lod_bias: float = LOD_BIAS,
        ruts=None,
    ) -> None:
        import moderngl

        self._mgl = moderngl
        self.ruts = ruts
        self._rut_tex: Any = None
        self._rut_key: tuple | None = None
        self._rut_box = (0.0, 0.0, 1.0, 1.0)
        self.client = client
        self.terrain = terrain
        self._texture_files = {int(k): str(v) for k, v in (textures or {}).items()}
        self._link_textures = {(int(b), int(k)): str(v) for (b, k), v in (link_textures or {}).items()}
        self.ctx = _create_context()
        self._objects: list = []
        self.released = False
        with self.ctx:  # current for the objects below (other contexts may exist in this process)
            ctx = self.ctx
            #: (ground, mode) -> program; mode: False (colour), True (labels), "motion" (colour
            #: and velocity buffer)
            self._progs = {
                (ground, mode): self._own(
                    ctx.program(
                        vertex_shader=_variant(_SCENE_VS, *defs),
                        fragment_shader=_variant(_SCENE_FS, *defs),
                    )
                )
                for ground in (False, True)
                for mode in _MODES
                for defs in [(("GROUND",) if ground else ()) + _MODE_DEFINES[mode]]
            }
            self._prog_depth = self._own(ctx.program(vertex_shader=_DEPTH_VS, fragment_shader=_DEPTH_FS))
            self._prog_skip = self._own(ctx.program(vertex_shader=_SKIP_VS, fragment_shader=_SKIP_FS))
            self._skips: dict[int, tuple] = {}  # id(keep) -> (keep, its vertex array or None)
            for prog in self._progs.values():
                _set(prog, "u_tex", 0)
                _set(prog, "u_lod_bias", float(lod_bias))
                _set(prog, "u_shadow", 1)
                _set(prog, "u_ruts", 2)
            self._textures: dict[str, object] = {}
            self._texture_means: dict[str, tuple[float, float, float]] = {}
            self._bodies: dict[int, list[_Group]] = {}
            self._posed: dict[int, bytes] = {}  # body -> the link poses its vertices are at
            self._joints: dict[int, list] = {}  # body -> _joint_table
            self._fk_cache: dict[int, tuple] = {}  # body -> (base pose and joints read, link poses)
            self._body_radius: dict[int, np.ndarray] = {}  # body -> (links + 1,) bounding radius [m]
            self._fbos: dict[tuple, tuple] = {}
            self._fisheye: dict[int, tuple] = {}
            #: Largest shadow-map edge [texels].
            self.shadow_px = int(shadow_px)
            self._shadow_maps: dict[int, dict] = {}
            self._shadow_key: tuple | None = None
            self._light = np.eye(4)
            self._light_R = 1.0
            self._focus: tuple | None = None
            self._focus_key: tuple | None = ("unset",)
            self._focused = np.zeros(0, np.int64)
            self._terrain = self._build_terrain(terrain) if terrain is not None else None

    # ------------------------------------------------------------------ resources
    def _own(self, obj):
        self._objects.append(obj)
        return obj

    @property
    def object_count(self) -> int:
        """GL objects (buffers, textures, framebuffers, programs, vertex arrays) alive now."""
        return len(self._objects)

    def release(self) -> None:
        """Free every GL object and the context; safe to call more than once."""
        if self.released:
            return
        self.released = True
        for prog in self._progs.values():
            _UNIFORMS.pop(id(prog), None)
        _UNIFORMS.pop(id(self._prog_depth), None)
        self._skips.clear()
        with self.ctx:
            for obj in reversed(self._objects):
                try:
                    obj.release()
                except Exception:  # noqa: BLE001 - the context may already be gone
                    pass
        self._objects.clear()
        self.ctx.release()

    def _texture(self, path: str):
        """The mipmapped, repeating texture of an image file (loaded once)."""
        tex = self._textures.get(path)
        if tex is None:
            from rover_env.sim.textures import read_texture

            img = np.ascontiguousarray(read_texture(path)[::-1])  # v = 0 at the image's bottom row
            h, w = img.shape[:2]
            tex = self._own(self.ctx.texture((w, h), 3, img.tobytes()))
            tex.build_mipmaps()
            tex.filter = (self._mgl.LINEAR_MIPMAP_LINEAR, self._mgl.LINEAR)
            self._textures[path] = tex
            r, g, b = (float(v) for v in img.reshape(-1, 3).mean(axis=0) / 255.0)
            self._texture_means[path] = (r, g, b)
        return tex

    # ------------------------------------------------------------------ scene
    def _vaos(self, data: np.ndarray, ground: bool, ibo=None, dynamic: bool = False) -> tuple:
        """A buffer of ``data`` (13-float vertices) and its vertex arrays.

        For the image, label and motion programs (and the shadow pass for bodies): keys False,
        True, "motion", "depth".
        """
        vbo = self._own(
            self.ctx.buffer(np.ascontiguousarray(data, dtype=np.float32).tobytes(), dynamic=dynamic)
        )
        out: dict[bool | str, Any] = {}
        for mode in _MODES:
            prog = self._progs[(ground, mode)]
            out[mode] = self._own(self.ctx.vertex_array(prog, [_layout(prog, vbo)], ibo))
        if not ground:
            out["depth"] = self._own(
                self.ctx.vertex_array(self._prog_depth, [_layout(self._prog_depth, vbo)], ibo)
            )
        return vbo, out

    def _build_body(self, body: int) -> None:
        import pybullet as pb

        c = self.client
        groups: dict[str | None, list[np.ndarray]] = {}
        n_links = c.getNumJoints(body)
        radius = np.zeros(n_links + 1)
        for vs in c.getVisualShapeData(body, flags=pb.VISUAL_SHAPE_DATA_TEXTURE_UNIQUE_IDS):
            link, gtype, dims, fname, lpos, lorn, rgba = vs[1], vs[2], vs[3], vs[4], vs[5], vs[6], vs[7]
            tex_id = vs[8] if len(vs) > 8 else -1
            if rgba[3] <= 0.0:
                continue
            if gtype == pb.GEOM_BOX:
                pos, nrm, uv = _box(np.asarray(dims) / 2)
            elif gtype == pb.GEOM_SPHERE:
                pos, nrm, uv = _sphere(dims[0])
            elif gtype in (pb.GEOM_CYLINDER, pb.GEOM_CAPSULE):
                pos, nrm, uv = _cylinder(dims[1], dims[0])
            elif gtype == pb.GEOM_MESH:
                name = fname.decode() if isinstance(fname, bytes) else fname
                if not name or not Path(name).is_file():
                    log.warning(
                        "GL renderer: body %d link %d: mesh %r has no file; not drawn", body, link, name
                    )
                    continue
                pos, nrm, uv = load_obj(name)
                pos = pos * np.asarray(dims)
                nrm = nrm / np.asarray(dims)
                nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            else:
                log.warning("GL renderer: body %d link %d: geometry type %d is not drawn", body, link, gtype)
                continue
            R = quat_to_matrix(lorn)
            pos = pos @ R.T + np.asarray(lpos)
            nrm = nrm @ R.T
            radius[link + 1] = max(radius[link + 1], float(np.linalg.norm(pos, axis=1).max()))
            texture = self._link_textures.get((body, link))
            if texture is None and tex_id is not None and tex_id >= 0:
                texture = self._texture_files.get(int(tex_id))
                if texture is None:
                    log.warning(
                        "GL renderer: body %d: texture id %d has no known file; drawn untextured",
                        body,
                        tex_id,
                    )
            data = np.empty((len(pos), 13), np.float32)
            data[:, 0:3], data[:, 3:6], data[:, 6:8] = pos, nrm, uv
            data[:, 8:12] = rgba
            data[:, 12] = link + 1
            groups.setdefault(texture, []).append(data)
        out = []
        for texture, parts in groups.items():
            data = np.vstack(parts)
            # shared corners once (indexed: each vertex is shaded once), sorted by link for posing
            data, index = np.unique(data.astype(np.float32), axis=0, return_inverse=True)
            order = np.argsort(data[:, 12], kind="stable")
            rank = np.empty_like(order)
            rank[order] = np.arange(len(order))
            data = data[order]
            # triangles sorted by link too: a view draws only the links it can see
            tris = rank[index.ravel()].reshape(-1, 3)
            tris = tris[np.argsort(data[tris[:, 0], 12], kind="stable")]
            ibo = self._own(self.ctx.buffer(tris.astype(np.int32).tobytes()))
            vbo, vaos = self._vaos(data, False, ibo=ibo, dynamic=True)
            vaos["ibo"] = ibo
            out.append(_Group(data, tris, vbo, vaos, self._texture(texture) if texture else None))
        self._bodies[body] = out
        self._body_radius[body] = radius

    def _build_terrain(self, terrain: Terrain):
        """The ground as chunks in one vertex array.

        The exact grid, and on rough ground the coarse far-ground grid (``Terrain.coarse_grid``,
        which lies just below the exact one).
        """
        levels = [terrain.render_grid()]
        if terrain.heights is not None:
            levels.append(terrain.coarse_grid())
        tile = terrain.cfg.texture_tile
        verts, tris, starts, boxes, rects, level_of = [], [], [], [], [], []
        count = nverts = 0
        for level, (xs, ys, h, normals) in enumerate(levels):
            gx, gy = np.meshgrid(xs, ys)
            ny, nx = h.shape
            data = np.zeros((ny, nx, 13), np.float32)
            data[..., 0], data[..., 1], data[..., 2] = gx, gy, h
            data[..., 3:6] = normals
            data[..., 6], data[..., 7] = gx / tile, gy / tile
            data[..., 8:12] = 1.0
            # chunks of at least _CHUNK metres and _CHUNK_CELLS cells a side, or one quad of a
            # plane; each owns a contiguous block of vertices (edges duplicated), so a draw of a
            # chunk shades only its own vertices
            nxc = max(_CHUNK_CELLS, int(round(_CHUNK / float(xs[1] - xs[0]))))
            nyc = max(_CHUNK_CELLS, int(round(_CHUNK / float(ys[1] - ys[0]))))
            if terrain.heights is None:  # a plane: one quad per chunk
                nxc = nyc = 1
            for j0 in range(0, ny - 1, nyc):
                for i0 in range(0, nx - 1, nxc):
                    j1, i1 = min(j0 + nyc, ny - 1), min(i0 + nxc, nx - 1)
                    blk = data[j0 : j1 + 1, i0 : i1 + 1].reshape(-1, 13)
                    bj, bi = j1 - j0 + 1, i1 - i0 + 1
                    idx = nverts + np.arange(bj * bi, dtype=np.int64).reshape(bj, bi)
                    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
                    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
                    t = np.concatenate(
                        [np.stack([a, b, c], 1), np.stack([b, d, c], 1)]
                    ).ravel()  # Bullet's split
                    verts.append(blk)
                    tris.append(t)
                    starts.append(count)
                    count += len(t)
                    nverts += len(blk)
                    hb = h[j0 : j1 + 1, i0 : i1 + 1]
                    x0, x1, y0, y1 = xs[i0], xs[i1], ys[j0], ys[j1]
                    boxes.append(
                        [[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (hb.min(), hb.max())]
                    )
                    rects.append([x0, x1, y0, y1])
                    level_of.append(level)
        ibo = self._own(self.ctx.buffer(np.concatenate(tris).astype(np.int32).tobytes()))
        starts.append(count)
        return {
            "vaos": self._vaos(np.vstack(verts), True, ibo)[1],
            "starts": np.asarray(starts),
            "boxes": np.asarray(boxes, dtype=np.float64),
            "rects": np.asarray(rects, dtype=np.float64),
            "level": np.asarray(level_of),
            "levels": len(levels),
            "fine_radius": FINE_RADIUS,
            "body": terrain.body_id,
        }

    @property
    def ground_ids(self) -> tuple[int, ...]:
        """The terrain's body (the label of ground pixels; empty without a terrain)."""
        return () if self.terrain is None else (self.terrain.body_id,)

    def focus(self, x: float, y: float, near: float | None = None) -> None:
        """Draw the ground for views taken from near world (x, y) [m] (see :meth:`Renderer.focus`).

        On rough ground the exact grid is drawn within the terrain's ``FINE_RADIUS`` of (x, y)
        and the coarse far-ground mesh beyond; with ``near`` [m] only the exact ground within
        ``near`` (views that see no farther). Until the first call all ground is drawn exactly.
        """
        self._focus = (float(x), float(y), None if near is None else float(near))

    def _update_ruts(self) -> bool:
        """Upload the ruts' surface about the focus if it changed; whether any are drawn."""
        ruts = self.ruts
        if ruts is None or not ruts.pressed:
            return False
        if self._focus is None:
            cx, cy = (float(v) for v in ruts.origin + 0.5 * ruts.size)
        else:
            cx, cy = self._focus[0], self._focus[1]
        key = (ruts.version, round(cx / ruts.cell), round(cy / ruts.cell))
        if key != self._rut_key:
            x0, y0, depth = ruts.surface(cx, cy, RUT_VIEW_HALF)
            if self._rut_tex is None or self._rut_tex.size != depth.shape[::-1]:
                self._rut_tex = self._own(self.ctx.texture(depth.shape[::-1], 1, dtype="f4"))
                self._rut_tex.repeat_x = self._rut_tex.repeat_y = False
            self._rut_tex.write(np.ascontiguousarray(depth).tobytes())
            edge = depth.shape[0] * ruts.cell
            self._rut_box = (x0, y0, 1.0 / edge, 1.0 / edge)
            self._rut_key = key
        return True

    def _ground_chunks(self, planes: np.ndarray) -> np.ndarray:
        """Indices of the ground chunks to draw in the view bounded by ``planes`` (world frame)."""
        t = self._terrain
        if t is None:
            return np.zeros(0, dtype=np.int64)
        if self._focus != self._focus_key:  # the chunks the focus draws, then each view culls them
            self._focus_key = self._focus
            if self._focus is None:
                keep = t["level"] == 0
            else:
                x, y, near = self._focus
                r = t["rects"]
                dist = np.hypot(np.maximum.reduce([r[:, 0] - x, x - r[:, 1], np.zeros(len(r))]),
                                np.maximum.reduce([r[:, 2] - y, y - r[:, 3], np.zeros(len(r))]))  # fmt: skip
                if near is not None:
                    keep = (t["level"] == 0) & (dist <= near)
                elif t["levels"] == 1:
                    keep = t["level"] == 0
                else:
                    keep = ((t["level"] == 0) & (dist <= t["fine_radius"])) | (t["level"] == 1)
            self._focused = np.flatnonzero(keep)
        idx = self._focused
        inside = (t["boxes"][idx] @ planes[:, :3].T + planes[:, 3] >= 0.0).any(axis=1).all(axis=1)
        return idx[inside]

    def _sync_bodies(self) -> dict[int, np.ndarray]:
        """Mirror new bodies, drop removed ones; the link -> world matrices of each body now."""
        c = self.client
        skip = set(self.ground_ids)
        alive = [c.getBodyUniqueId(i) for i in range(c.getNumBodies())]
        for body in list(self._bodies):
            if body not in alive:
                self._drop_body(body)
        poses = {}
        for body in alive:
            if body in skip:
                continue
            if body not in self._bodies:
                self._build_body(body)
            if not self._bodies[body]:
                continue
            M = self._link_poses(body)
            poses[body] = M
            key = M.tobytes()
            if self._posed.get(body) != key:
                self._posed[body] = key
                for g in self._bodies[body]:
                    g.pose(M)
        return poses

    def _link_poses(self, body: int) -> np.ndarray:
        """(links + 1, 4, 4) world poses of the base's and each link's inertial frame, now.

        Forward kinematics from the base pose and the joint positions, computed here: PyBullet's
        stored link frames lag a physics step behind the base, and asking PyBullet to recompute
        them (``computeForwardKinematics``) changes the next step's numbers, so the physics would
        depend on what is rendered.
        """
        c = self.client
        joints = self._joints.get(body)
        if joints is None:
            joints = self._joints[body] = _joint_table(c, body)
        n = len(joints)
        pos, orn = c.getBasePositionAndOrientation(body)
        q = [s[0] for s in c.getJointStates(body, list(range(n)))] if n else []
        key = (pos, orn, tuple(q))
        cached = self._fk_cache.get(body)
        if cached is not None and cached[0] == key:
            return cached[1]
        M = np.zeros((n + 1, 4, 4))
        M[0, :3, :3], M[0, :3, 3], M[0, 3, 3] = quat_to_matrix(orn), pos, 1.0
        if n:
            for k, (parent, T_parent_joint, axis, kind, T_joint_inertial) in enumerate(joints):
                motion = np.eye(4)
                if kind == "revolute":
                    motion[:3, :3] = _axis_angle(axis, q[k])
                elif kind == "prismatic":
                    motion[:3, 3] = axis * q[k]
                M[k + 1] = M[parent + 1] @ T_parent_joint @ motion @ T_joint_inertial
        self._fk_cache[body] = (key, M)
        return M

    def _drop_body(self, body: int) -> None:
        self._posed.pop(body, None)
        self._joints.pop(body, None)
        self._fk_cache.pop(body, None)
        for g in self._bodies.pop(body, []):
            for obj in (*g.vaos.values(), g.vbo):
                obj.release()
                self._objects.remove(obj)
        self._body_radius.pop(body, None)

    # ------------------------------------------------------------------ shadow map
    def _update_shadow(self, poses: dict[int, np.ndarray], sun: np.ndarray, texel: float) -> dict:
        """The shadow map for a view of pixel footprint ``texel`` [m]: the casters' depth seen from the sun.

        Maps come in power-of-two sizes from 256 to :attr:`shadow_px` texels, the smallest whose
        texels are at most ``texel``; each is rendered once per pose and sun.
        """
        from rover_env.rendering.shadows import sun_frame

        key = (sun.tobytes(), tuple((b, m.tobytes()) for b, m in poses.items()))
        if key != self._shadow_key:
            self._shadow_key = key
            for smap in self._shadow_maps.values():
                smap["fresh"] = False
            xs, ys, s = sun_frame(sun)
            if poses:
                cen = np.vstack([m[:, :3, 3] for m in poses.values()])
                rad = np.concatenate([self._body_radius[b] for b in poses])
                mid = 0.5 * (cen.min(axis=0) + cen.max(axis=0))
                R = float(np.max(np.linalg.norm(cen - mid, axis=1) + rad)) * 1.02 + 1e-3
            else:
                mid, R = np.zeros(3), 1.0
            L = np.eye(4)
            L[0, :3], L[1, :3], L[2, :3] = xs / R, ys / R, -s / R
            L[:3, 3] = -L[:3, :3] @ mid
            self._light, self._light_R = L, R
        px = 256
        while px < self.shadow_px and 2 * self._light_R / px > texel:
            px *= 2
        # a finer map already drawn for this instant serves too (one shadow pass per instant)
        px = max([px] + [k for k, m in self._shadow_maps.items() if m["fresh"]])
        if px not in self._shadow_maps:
            tex = self._own(self.ctx.depth_texture((px, px)))
            tex.compare_func = "<="
            # one comparison per pixel: hard edges, as the exact shadow test draws them. A 2 x 2
            # filtered lookup (softer edges) made the train preset's slip events on the shadow
            # mission less precise (F1 0.86 against 0.97, benchmarks/slip_accuracy.py)
            tex.filter = (self._mgl.NEAREST, self._mgl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
            fbo = self._own(self.ctx.framebuffer(depth_attachment=tex))
            self._shadow_maps[px] = {"texture": tex, "fbo": fbo, "fresh": False}
        smap = self._shadow_maps[px]
        if not smap["fresh"]:
            smap["fresh"] = True
            smap["light"] = self._light
            smap["texel"] = 2 * self._light_R / px
            fbo = smap["fbo"]
            fbo.use()
            fbo.clear(depth=1.0)
            self.ctx.enable(self._mgl.DEPTH_TEST)
            _set(self._prog_depth, "u_light", _gl(self._light))
            for body in poses:
                for g in self._bodies[body]:
                    g.vaos["depth"].render(self._mgl.TRIANGLES, vertices=g.count)
        return smap

    # ------------------------------------------------------------------ drawing
    def _fbo(self, size: tuple[int, int], labels: bool | str):
        key = (size, labels)
        fb = self._fbos.get(key)
        if fb is None:
            ctx = self.ctx
            color = [self._own(ctx.texture(size, 4))]
            if labels == "motion":
                color.append(self._own(ctx.texture(size, 2, dtype="f4")))
            elif labels:
                color += [
                    self._own(ctx.texture(size, 1, dtype="i4")),
                    self._own(ctx.texture(size, 1, dtype="f4")),
                    self._own(ctx.texture(size, 4, dtype="f4")),
                ]
            depth = self._own(ctx.depth_renderbuffer(size))
            fb = (self._own(ctx.framebuffer(color_attachments=color, depth_attachment=depth)), color)
            self._fbos[key] = fb
        return fb

    def _shadow_for(self, lighting: Lighting, poses, T_world_cam: np.ndarray, focal: float):
        """The shadow map for a view from ``T_world_cam``, focal length ``focal`` [px]; None if unlit."""
        if not lighting.shadows:
            return None
        sun = np.asarray(lighting.sun_direction, dtype=np.float64)
        centre = np.mean([m[0, :3, 3] for m in poses.values()], axis=0) if poses else T_world_cam[:3, 3]
        # the shadow falls on ground at least ~0.5 m from a camera on the rover
        dist = max(float(np.linalg.norm(centre - T_world_cam[:3, 3])), 0.5)
        # (a texel falls on level ground stretched by 1 / sin(sun elevation): under a low sun the
        # shadow's edge steps by up to a few pixels; a finer map would cost a pass of up to 4x)
        return self._update_shadow(poses, sun / np.linalg.norm(sun), dist / focal)

    def _draw(
        self,
        view_planes_world,
        T_world_cam,
        P,
        lighting: Lighting,
        poses,
        labels: bool | str,
        smap,
        motion: MotionSpec | None = None,
        K: np.ndarray | None = None,
        links: tuple[bytes, bytes, bytes] | None = None,
    ) -> None:
        """Draw the scene into the bound framebuffer's viewport, with shadow map ``smap`` (or None).

        ``labels``: the program mode (False, True or ``"motion"``, which needs ``motion``, the
        view's intrinsics ``K`` [px] and ``links``, :func:`_link_arrays` of ``motion.links``).
        """
        mgl = self._mgl
        ctx = self.ctx
        sun = np.asarray(lighting.sun_direction, dtype=np.float64)
        sun = sun / np.linalg.norm(sun)
        shadows = smap is not None
        progs = (self._progs[(True, labels)], self._progs[(False, labels)])
        diffuse = float(lighting.diffuse)
        clouds = _cloud_uniforms(lighting.clouds, smap["light"]) if shadows else ((), b"", b"")
        if lighting.clouds and not shadows:  # no light frame: the clouds' shade at the camera
            diffuse *= float(lighting.cloud_shade(np.asarray(T_world_cam)[:3, 3])[0])
        if shadows:
            smap["texture"].use(1)
        view = _gl(np.linalg.inv(T_world_cam))
        for p in progs:
            if shadows:
                _set(p, "u_light", _gl(smap["light"]))
            _set(p, "u_shadows", shadows)
            _set(p, "u_sun", tuple(sun))
            _set(p, "u_ambient", float(lighting.ambient))
            _set(p, "u_diffuse", diffuse)
            _set(p, "u_nclouds", len(clouds[0]))
            if clouds[0]:
                _set(p, "u_cloud_a", clouds[1])
                _set(p, "u_cloud_b", clouds[2])
            _set(p, "u_proj", _gl(P))
            _set(p, "u_view", view)
        link_motion = None
        if labels == "motion":
            assert motion is not None and K is not None and links is not None
            T = np.asarray(T_world_cam, dtype=np.float64)
            focal = (float(K[0, 0]), float(K[0, 1]), float(K[1, 1]))
            for p in progs:
                _set(p, "u_cam_R", _gl(T[:3, :3].T))
                _set(p, "u_cam_c", tuple(float(v) for v in T[:3, 3]))
                _set(p, "u_focal", focal)
                _set(p, "u_cam_v", tuple(float(v) for v in motion.v_cam))
                _set(p, "u_cam_w", tuple(float(v) for v in motion.w_cam))
            link_motion = links
        ctx.enable(mgl.DEPTH_TEST)
        if self._terrain is not None:
            t = self._terrain
            g = progs[0]
            _set(g, "u_body", int(t["body"]))
            terrain = self.terrain
            assert terrain is not None  # a terrain's chunks are drawn only with it
            path = str(terrain.texture_path)
            self._texture(path).use(0)
            look = terrain.albedo != 1.0 or terrain.contrast != 1.0
            _set(g, "u_look", look)
            if look:
                _set(g, "u_albedo", float(terrain.albedo))
                _set(g, "u_contrast", float(terrain.contrast))
                _set(g, "u_tex_mean", self._texture_means[path])
            has_ruts = self._update_ruts()
            _set(g, "u_has_ruts", has_ruts)
            if has_ruts:
                assert self._rut_tex is not None and self.ruts is not None
                self._rut_tex.use(2)
                _set(g, "u_rut_box", self._rut_box)
                _set(g, "u_rut_cell", float(self.ruts.cell))
            visible = self._ground_chunks(view_planes_world)
            if len(visible):
                # runs of consecutive chunks, one draw each (an indirect multi-draw would make
                # llvmpipe wait for the rasteriser to read its buffer)
                vao = t["vaos"][labels]
                for first, count in _index_runs(t["starts"], visible):
                    vao.render(mgl.TRIANGLES, vertices=count, first=first)
        prog = progs[1]
        _set(prog, "u_normal_offset", 1.5 * smap["texel"] if shadows else 0.0)
        for body in poses:
            _set(prog, "u_body", int(body))
            if link_motion is not None:
                moving = body == motion.body  # type: ignore[union-attr]
                _set(prog, "u_moving", moving)
                if moving:
                    for name, arr in zip(("u_com", "u_lin", "u_ang"), link_motion, strict=True):
                        _set(prog, name, arr)
            for g in self._bodies[body]:
                runs = g.visible_runs(view_planes_world)
                if not runs:
                    continue
                _set(prog, "u_textured", g.texture is not None)
                if g.texture is not None:
                    g.texture.use(0)
                for first, count in runs:
                    if count:
                        g.vaos[labels].render(mgl.TRIANGLES, vertices=count, first=first)

    def render_K(
        self,
        K: np.ndarray,
        size: tuple[int, int],
        T_world_cam: np.ndarray,
        lighting: Lighting,
        near: float = 0.05,
        far: float = 20.0,
        segmentation: bool = True,
        motion: MotionSpec | None = None,
        keep: np.ndarray | None = None,
    ) -> RenderedView:
        """See :meth:`Renderer.render_K` (this context is made current for it).

        ``motion``: also draw the velocity buffer (:attr:`RenderedView.motion`) in the colour
        pass (not with ``segmentation``); the colour returned is ``motion.expose``'s, if given.
        ``keep``: (H, W) bool, the pixels that must be drawn; the others may be left black, with
        zero velocity, unshaded (a lens's remap reads only part of the wider view it needs).
        Every kept pixel is the same as without ``keep``. Pass the same array each frame: its
        rectangles are made once per array. None: every pixel is drawn.
        """
        if self.released:
            raise RuntimeError("this GLRenderer is released; create a new one")
        if motion is not None and segmentation:
            raise ValueError(
                "motion: a velocity buffer is drawn without segmentation; pass segmentation=False"
            )
        if keep is not None and np.shape(keep) != (int(size[1]), int(size[0])):
            raise ValueError(f"keep: shape {np.shape(keep)}; the view is {size[0]} x {size[1]} px (H, W)")
        with self.ctx:
            return self._render_K(K, size, T_world_cam, lighting, near, far, segmentation, motion, keep)

    def render_fisheye(
        self,
        remapper: CubemapRemap,
        T_world_cam: np.ndarray,
        lighting: Lighting,
        labels: bool = False,
        near: float = 0.01,
        far: float = 20.0,
        windows=None,
        motion: MotionSpec | None = None,
    ) -> FisheyeView:
        """See :meth:`Renderer.render_fisheye` (this context is made current for it).

        ``motion``: also draw the velocity buffer on the cube faces (not with ``labels``) and
        remap ``motion.expose``'s image of them.
        """
        if self.released:
            raise RuntimeError("this GLRenderer is released; create a new one")
        if motion is not None and labels:
            raise ValueError("motion: a velocity buffer is drawn without labels; pass labels=False")
        with self.ctx:
            return self._render_fisheye(remapper, T_world_cam, lighting, labels, near, far, windows, motion)

    def _render_K(
        self,
        K: np.ndarray,
        size: tuple[int, int],
        T_world_cam: np.ndarray,
        lighting: Lighting,
        near: float = 0.05,
        far: float = 20.0,
        segmentation: bool = True,
        motion: MotionSpec | None = None,
        keep: np.ndarray | None = None,
    ) -> RenderedView:
        """Render the pinhole view ``K`` [px], ``size`` = (W, H) [px] from ``T_world_cam`` (optical frame).

        Returns a :class:`rover_env.rendering.base.RenderedView` with ``shadow`` always, and ``depth`` and
        ``segmentation`` only with ``segmentation`` (None without: they cost read-back time).
        ``near``, ``far``: clip distances [m].
        """
        w, h = int(size[0]), int(size[1])
        poses = self._sync_bodies()
        mode: bool | str = "motion" if motion is not None else bool(segmentation)
        fbo, color = self._fbo((w, h), mode)
        planes = view_planes(K, (w, h), T_world_cam, near)
        P = projection_from_K(K, (w, h), near, far)
        smap = self._shadow_for(lighting, poses, T_world_cam, float(K[0, 0]))
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        if keep is not None:
            self._skip(keep)
        links = None if motion is None else _link_arrays(motion.links)
        self._draw(planes, T_world_cam, P, lighting, poses, mode, smap, motion, K, links)
        rgba = np.frombuffer(fbo.read(components=4, attachment=0), np.uint8).reshape(h, w, 4)
        rgb = np.ascontiguousarray(rgba[..., :3])
        shadow = rgba[..., 3] > 127
        if motion is not None:
            vel = np.frombuffer(fbo.read(components=2, attachment=1, dtype="f4"), np.float32).reshape(h, w, 2)
            if motion.expose is not None:
                rgb = motion.expose(rgb, vel, (0, 0))
            view = RenderedView(rgb, None, None, shadow, np.asarray(K, float), np.asarray(T_world_cam, float))
            view.motion = vel
            return view
        if not segmentation:
            depth = None
            seg = None
        else:
            seg = (
                np.frombuffer(fbo.read(components=1, attachment=1, dtype="i4"), np.int32).reshape(h, w).copy()
            )
            depth = (
                np.frombuffer(fbo.read(components=1, attachment=2, dtype="f4"), np.float32)
                .reshape(h, w)
                .copy()
            )
            zbuf = np.frombuffer(fbo.read(components=1, attachment=-1, dtype="f4"), np.float32).reshape(h, w)
            empty = zbuf >= 1.0
            seg[empty] = -1
            depth[empty] = far
        view = RenderedView(rgb, depth, seg, shadow, np.asarray(K, float), np.asarray(T_world_cam, float))
        return view

    def _skip(self, keep: np.ndarray) -> None:
        """Put the pixels outside ``keep`` (H, W) at the near plane in the bound framebuffer's depth."""
        entry = self._skips.get(id(keep))
        if entry is None or entry[0] is not keep:
            rects = skip_rects(keep).astype(np.float32)
            vao = None
            if len(rects):
                h, w = keep.shape
                x0, y0 = 2.0 * rects[:, 0] / w - 1.0, 2.0 * rects[:, 1] / h - 1.0
                x1, y1 = 2.0 * rects[:, 2] / w - 1.0, 2.0 * rects[:, 3] / h - 1.0
                tris = np.stack([x0, y0, x1, y0, x1, y1, x0, y0, x1, y1, x0, y1], axis=1)
                vbo = self._own(self.ctx.buffer(np.ascontiguousarray(tris, np.float32).tobytes()))
                vao = self._own(self.ctx.vertex_array(self._prog_skip, [(vbo, "2f", "in_pos")]))
            if len(self._skips) >= 8:  # cameras pass one array each; a stray caller must not grow this
                self._skips.clear()
            entry = (keep, vao)
            self._skips[id(keep)] = entry
        if entry[1] is not None:
            self.ctx.enable(self._mgl.DEPTH_TEST)
            entry[1].render(self._mgl.TRIANGLES)

    # ------------------------------------------------------------------ fisheye
    def _fisheye_targets(self, remapper: CubemapRemap):
        key = id(remapper)
        entry = self._fisheye.get(key)
        if entry is not None and entry[0] is remapper:
            return entry
        ctx = self.ctx
        aw = max(fc.size[0] for fc in remapper.faces)
        ah = max(fc.atlas_row + fc.size[1] for fc in remapper.faces)
        atlas = [
            self._own(ctx.texture((aw, ah), 4)),
            self._own(ctx.texture((aw, ah), 1, dtype="i4")),
            self._own(ctx.texture((aw, ah), 1, dtype="f4")),
            self._own(ctx.texture((aw, ah), 4, dtype="f4")),
        ]
        depth = self._own(ctx.depth_renderbuffer((aw, ah)))
        fbo_color = self._own(ctx.framebuffer(color_attachments=atlas[:1], depth_attachment=depth))
        fbo_labels = self._own(ctx.framebuffer(color_attachments=atlas, depth_attachment=depth))
        motion = self._own(ctx.texture((aw, ah), 2, dtype="f4"))
        fbo_motion = self._own(ctx.framebuffer(color_attachments=[atlas[0], motion], depth_attachment=depth))
        entry = (remapper, (aw, ah), fbo_color, fbo_labels, fbo_motion)
        self._fisheye[key] = entry
        return entry

    def _render_fisheye(
        self,
        remapper: CubemapRemap,
        T_world_cam: np.ndarray,
        lighting: Lighting,
        labels: bool = False,
        near: float = 0.01,
        far: float = 20.0,
        windows=None,
        motion: MotionSpec | None = None,
    ):
        """Render the fisheye of ``remapper``'s model at ``T_world_cam`` (see :meth:`render_fisheye`)."""
        _, (aw, ah), fbo_color, fbo_labels, fbo_motion = self._fisheye_targets(remapper)
        poses = self._sync_bodies()
        smap = self._shadow_for(lighting, poses, T_world_cam, float(remapper.focal))
        mode: bool | str = "motion" if motion is not None else bool(labels)
        fbo = fbo_motion if motion is not None else fbo_labels if labels else fbo_color
        fbo.use()
        fbo.viewport = (0, 0, aw, ah)
        fbo.scissor = None
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        links = None if motion is None else _link_arrays(motion.links)  # once for every face
        drawn = []  # the atlas rectangles drawn, (x0, y0, x1, y1) [px, end exclusive]
        for k, fc in enumerate(remapper.faces):
            view = fc.view(T_world_cam, None if windows is None else windows[k])
            if view is None:
                continue
            fw, fh = fc.size
            K, size, T_face, (u0, v0, u1, v1) = view
            drawn.append((u0, fc.atlas_row + v0, u1, fc.atlas_row + v1))
            planes = view_planes(K, size, T_face, near)
            fbo.viewport = (0, fc.atlas_row, fw, fh)
            fbo.scissor = (u0, fc.atlas_row + v0, u1 - u0, v1 - v0)
            P = projection_from_K(fc.K, (fw, fh), near, far)
            self._draw(planes, T_face, P, lighting, poses, mode, smap, motion, fc.K, links)
        fbo.scissor = None
        w, h = remapper.model.image_size
        if motion is not None:
            if not drawn:
                return FisheyeView(rgb=np.zeros((h, w, 3), np.uint8))
            atlas_rgb = np.frombuffer(fbo.read(components=3, attachment=0), np.uint8).reshape(ah, aw, 3)
            if motion.expose is not None:
                vel = np.frombuffer(fbo.read(components=2, attachment=1, dtype="f4"), np.float32)
                vel = vel.reshape(ah, aw, 2)
                atlas_rgb = atlas_rgb.copy()
                for x0, y0, x1, y1 in drawn:  # each view drawn (a window of a face) on its own
                    blk = np.s_[y0:y1, x0:x1]
                    atlas_rgb[blk] = motion.expose(atlas_rgb[blk], vel[blk], (x0, y0))
            return FisheyeView(rgb=remapper.remap(atlas_rgb))
        if not labels:
            if not drawn:
                return FisheyeView(rgb=np.zeros((h, w, 3), np.uint8))
            # the remap on the CPU: reading back the small atlas and one fixed-point cv2.remap
            # cost less than a remap pass on llvmpipe
            atlas_rgb = np.frombuffer(fbo.read(components=3, attachment=0), np.uint8).reshape(ah, aw, 3)
            return FisheyeView(rgb=remapper.remap(atlas_rgb))
        # one read of the colour with its shadow flag; nothing drawn where the world point's w is
        # still the clear colour's 0 (every labelled fragment writes w = 1)
        col = np.frombuffer(fbo_labels.read(components=4, attachment=0), np.uint8).reshape(ah, aw, 4)
        rgb = remapper.remap(np.ascontiguousarray(col[..., :3])) if drawn else np.zeros((h, w, 3), np.uint8)
        seg = (
            np.frombuffer(fbo_labels.read(components=1, attachment=1, dtype="i4"), np.int32)
            .reshape(ah, aw)
            .copy()
        )
        world = np.frombuffer(fbo_labels.read(components=4, attachment=3, dtype="f4"), np.float32).reshape(
            ah, aw, 4
        )
        empty = world[..., 3] < 0.5
        seg[empty] = -1
        pts = np.ascontiguousarray(world[..., :3])
        pts[empty] = np.nan
        shadow = (col[..., 3] > 127) & ~empty
        return FisheyeView(
            rgb=rgb,
            segmentation=remapper.lookup(seg, outside=-1),
            shadow=remapper.lookup(shadow, outside=False),
            points_world=remapper.lookup(pts, outside=np.nan),
        )
