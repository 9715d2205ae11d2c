"""What the kinematics estimator reads of the rover, as body-frame points: pure geometry.

The wheels (tread and side discs), steering arms, tie-rod markers and the balls about the eight
marker centres of a :class:`perception.models.rover.RoverKinematicModel` at a joint state
(:func:`kinematic_parts`), and the points that bound where they can be a frame later
(:func:`joint_window_parts`): what an estimator asks a camera with a windowed readout to show;
and the fisheye pixels where any of them can appear over the joints' ranges
(:func:`kinematics_roi`: a sensor's region of interest, and the rover's parts to leave out of
the fisheye's odometry). Nothing here knows how an image is made.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from perception.models.cameras import OmniCamera
from perception.models.rover import AXLES, PLATE, WHEELS


@functools.lru_cache(maxsize=8)
def _part_shapes(r: float, width: float, marker_size: float, outline: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points [m] of one wheel in its knuckle frame, and of a ball about a marker centre.

    The wheel (axle along y): its tread, 5 lines across, and its two side discs, 4 rings each.
    The ball holds a marker's square, whatever the square's attitude. ``outline``: only what
    bounds the parts' images (the wheel's two rims at 24 points, whose chords sag 0.9 % of the
    radius, and the corners of the cube about the ball).
    """
    wheel: np.ndarray
    ball: np.ndarray
    if outline:
        phi = np.linspace(0.0, 2 * math.pi, 25)[:-1]
        P, Y = np.meshgrid(phi, np.array([-0.5, 0.5]) * width)
        wheel = np.stack([r * np.cos(P), Y, r * np.sin(P)], -1).reshape(-1, 3)
        ball = (
            0.75
            * marker_size
            * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
        )
        wheel.setflags(write=False)
        ball.setflags(write=False)
        return wheel, ball
    phi = np.linspace(0.0, 2 * math.pi, 97)[:-1]
    P, Y = np.meshgrid(phi, np.linspace(-0.5, 0.5, 5) * width)
    cyl = np.stack([r * np.cos(P), Y, r * np.sin(P)], -1).reshape(-1, 3)
    Pd, Qd, Yd = np.meshgrid(phi[::2], np.linspace(0.25, 1.0, 4) * r, np.array([-0.5, 0.5]) * width)
    disc = np.stack([Qd * np.cos(Pd), Yd, Qd * np.sin(Pd)], -1).reshape(-1, 3)
    ball = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=float)
    ball *= 0.75 * marker_size / np.maximum(np.linalg.norm(ball, axis=1, keepdims=True), 1.0)
    wheel = np.vstack([cyl, disc])
    wheel.setflags(write=False)
    ball.setflags(write=False)
    return wheel, ball


def kinematic_parts(model, psi, depth, delta, outline: bool = False) -> list[np.ndarray]:
    """Body-frame points [m] of everything the kinematics estimator reads, at one joint state.

    One point set per part, each with a convex image: every wheel (tread and side discs), its
    steering arm and tie-rod marker, and a ball around each of the eight marker centres.

    Args:
        model: The rover's :class:`perception.models.rover.RoverKinematicModel`.
        psi: Axle roll (F, R) [rad].
        depth: Axle-body distance (F, R) [m].
        delta: Wheel steering angles (FL, FR, RL, RR) [rad].
        outline: Only points that bound each part's image (far fewer: for bounding boxes).
    """
    wheel, ball = _part_shapes(model.wheel_radius, model.wheel_width, model.marker_size, outline)
    parts = []
    for k, (R, c) in enumerate(model.wheel_frames(psi, depth, delta)):
        parts.append(wheel @ R.T + c)
        parts.append(model.occluders(WHEELS[k], R, c)[0])
    centres = np.array(list(model.marker_positions(psi, depth, delta).values()))
    parts.extend(centres[:, None, :] + ball[None])
    return parts


def joint_window_parts(model, psi, depth, delta, spread: tuple[float, float, float]) -> np.ndarray:
    """Body-frame points [m] bounding the images of :func:`kinematic_parts` over a box of joint states.

    The outlines of the parts at the box's eight corners (each axle's roll and travel and
    every wheel's steering angle moved together by -+ ``spread``) bound where they can be a
    frame later, for joint changes within ``spread`` per frame: the parts move smoothly with the
    joints, so their images between the corners stay within the corners' bounding box up to
    curvature, which a window's pixel margin covers.

    Args:
        model: The rover's :class:`perception.models.rover.RoverKinematicModel`.
        psi: Axle roll (F, R) [rad].
        depth: Axle-body distance (F, R) [m].
        delta: Wheel steering angles (FL, FR, RL, RR) [rad].
        spread: (roll [rad], travel [m], steering [rad]) either side of the state.

    Returns:
        (N, 3) points.
    """
    wheel, ball = _part_shapes(model.wheel_radius, model.wheel_width, model.marker_size, True)
    sr, st, ss = (float(v) for v in spread)
    knuckles, plate_sets = _window_shapes(model, wheel)
    out = []
    for i, axle in enumerate(AXLES):
        # axle-frame points at the two steering corners: (2, n, 3) with the marker centres last
        parts: list[np.ndarray] = []
        centres: list[np.ndarray] = []
        for w in (axle + "L", axle + "R"):
            knuckle = knuckles[w]
            d = float(delta[WHEELS.index(w)]) + np.array([-ss, ss])
            c, s_ = np.cos(d)[:, None], np.sin(d)[:, None]
            x, y, z = knuckle[:, 0], knuckle[:, 1], knuckle[:, 2]
            rot = np.stack([c * x - s_ * y, s_ * x + c * y, np.broadcast_to(z, c.shape[:1] + z.shape)], -1)
            rot += model.kingpin_local(w)
            parts.append(rot[:, :-1])
            centres.append(rot[:, -1:])  # the tie-rod marker
        plates = plate_sets[axle]
        local = np.concatenate([*parts, *centres, np.broadcast_to(plates, (2,) + plates.shape)], axis=1)
        n_markers = 2 + len(plates)
        for roll in (psi[i] - sr, psi[i] + sr):
            cr, sn = math.cos(roll), math.sin(roll)
            R = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sn], [0.0, sn, cr]])
            for d_ in (depth[i] - st, depth[i] + st):
                body = local @ R.T + model.roll_centre(axle, d_)
                out.append(body[:, :-n_markers].reshape(-1, 3))
                # each marker's ball, axis-aligned in the body frame as in kinematic_parts
                out.append((body[:, -n_markers:, None, :] + ball).reshape(-1, 3))
    return np.vstack(out)


_WINDOW_SHAPES: dict[int, tuple] = {}  # id(model) -> (model, knuckle points, plate markers)


def _window_shapes(model, wheel: np.ndarray) -> tuple[dict, dict]:
    """The fixed point sets of :func:`joint_window_parts`, built once per model.

    Per wheel its knuckle-frame outline (tread rims, arm and marker, the tie-rod marker's centre
    last) and per axle its plate markers' centres.
    """
    entry = _WINDOW_SHAPES.get(id(model))
    if entry is None or entry[0] is not model:
        knuckles = {
            w: np.vstack([wheel, model.occluders(w, np.eye(3), np.zeros(3))[0], model.tip_knuckle(w)])
            for w in WHEELS
        }
        plates = {a: np.array([model.plate_marker_local(m) for m in PLATE[a]]) for a in AXLES}
        if len(_WINDOW_SHAPES) > 16:
            _WINDOW_SHAPES.clear()
        entry = _WINDOW_SHAPES[id(model)] = (model, knuckles, plates)
    return entry[1], entry[2]


def kinematics_roi(
    camera: OmniCamera,
    model,
    roll_limit: float,
    travel_limit: float,
    steer_limit: float,
    margin: float = 0.04,
) -> np.ndarray:
    """Fisheye pixels in which the kinematics estimator can find a wheel, marker or steering arm.

    The wheels' treads and side discs, the eight markers and the steering arms
    (:func:`kinematic_parts`) are projected over the whole joint range (axle roll, travel and
    steering at their limits and between); the convex hull of each part's image is filled, and
    the union is grown by ``margin``: nothing the estimator reads lies outside it.

    Args:
        camera: The fisheye model (its ``T_body_cam`` is the mount).
        model: The rover's :class:`perception.models.rover.RoverKinematicModel`.
        roll_limit: Axle roll range +- [rad].
        travel_limit: Axle travel range +- about ``model.nominal_depth`` [m].
        steer_limit: Axle steering range +- [rad].
        margin: Growth of the region, as a share of the image width.

    Returns:
        (H, W) bool mask.
    """
    w, h = camera.image_size
    T_cam_body = np.linalg.inv(camera.T_body_cam)
    mask = np.zeros((h, w), np.uint8)
    for psi in np.linspace(-roll_limit, roll_limit, 9):
        for d in model.nominal_depth + np.linspace(-travel_limit, travel_limit, 5):
            for lam in np.linspace(-steer_limit, steer_limit, 13):
                delta = model.wheel_angles(lam, -lam)  # both axles through their range
                parts = kinematic_parts(model, (psi, -psi), (d, d), delta)
                sizes = np.cumsum([len(q) for q in parts])[:-1]
                body = np.vstack(parts)
                pix = camera.world2cam(body @ T_cam_body[:3, :3].T + T_cam_body[:3, 3])
                for q in np.split(pix, sizes):
                    q = q[np.all(np.isfinite(q), axis=1)]
                    if len(q):
                        hull = cv2.convexHull(np.rint(q * 16).astype(np.int32))
                        cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    k = max(2, int(round(margin * w)))
    grown = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1)))
    return np.asarray(grown).astype(bool)
