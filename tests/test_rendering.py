"""Rendered images against geometry: pinhole projection of known points, sun shadows vs ray casting."""

import math

import numpy as np
import pybullet as pb
import pytest
from conftest import flat_scenario
from pybullet_utils.bullet_client import BulletClient
from scipy.ndimage import minimum_filter

from perception.models.cameras import PinholeCamera
from rover_env.config.cameras import DownwardCameraConfig
from rover_env.rendering import renderer_for
from rover_env.rendering.base import Lighting, look_at, view_planes
from rover_env.rendering.shadows import ShadowCaster
from rover_env.sensors.cameras import DownwardCamera
from rover_env.sim.simulation import RoverSim, quat_to_yaw


def mast_camera(sim: RoverSim) -> PinholeCamera:
    return DownwardCamera(sim, DownwardCameraConfig(shadows=False)).model


def body_pose(sim: RoverSim) -> np.ndarray:
    pos, quat = sim.client.getBasePositionAndOrientation(sim.rover.body_id)
    T = np.eye(4)
    T[:3, :3] = np.array(sim.client.getMatrixFromQuaternion(quat)).reshape(3, 3)
    T[:3, 3] = pos
    return T


def sun_behind(sim: RoverSim, elevation_deg: float) -> tuple[float, float, float]:
    _, quat = sim.client.getBasePositionAndOrientation(sim.rover.body_id)
    az = quat_to_yaw(quat) + math.pi
    el = math.radians(elevation_deg)
    return (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))


def caster_world(sim: RoverSim) -> BulletClient:
    """A separate client holding the rover's visual shapes as static collision primitives."""
    src, body = sim.client, sim.rover.body_id
    oc = BulletClient(connection_mode=pb.DIRECT)
    wheels = set(sim.rover.wheel_links)
    g = sim.geometry
    for vs in src.getVisualShapeData(body):
        link, gtype, dims, lpos, lorn = vs[1], vs[2], vs[3], vs[5], vs[6]
        if link == -1:
            wpos, worn = src.getBasePositionAndOrientation(body)
        else:
            st = src.getLinkState(body, link)
            wpos, worn = st[0], st[1]
        pos, orn = src.multiplyTransforms(wpos, worn, lpos, lorn)
        if link in wheels:
            shape = oc.createCollisionShape(pb.GEOM_CYLINDER, radius=g.wheel_radius, height=g.wheel_width)
            orn = src.multiplyTransforms(
                [0, 0, 0], worn, [0, 0, 0], src.getQuaternionFromEuler([math.pi / 2, 0, 0])
            )[1]
            pos = src.getLinkState(body, link)[4]
        elif gtype == pb.GEOM_BOX:
            shape = oc.createCollisionShape(pb.GEOM_BOX, halfExtents=[d / 2 for d in dims])
        elif gtype == pb.GEOM_CYLINDER:
            shape = oc.createCollisionShape(pb.GEOM_CYLINDER, radius=dims[1], height=dims[0])
        else:
            continue
        oc.createMultiBody(0, shape, -1, pos, orn)
    return oc


@pytest.fixture(scope="module", params=["gl", "tiny"])
def parked_sim(request):
    sim = RoverSim(flat_scenario(mu=1.0), renderer=request.param)
    sim.reset(7.3, -4.1, math.radians(35.0))  # far from the world origin, at an angle
    yield sim
    sim.close()


def test_downward_camera_sees_known_ground_points_where_the_model_says(parked_sim):
    sim = parked_sim
    cam = mast_camera(sim)
    T_wc = body_pose(sim) @ cam.T_body_cam
    view = renderer_for(sim).render_pinhole(cam, T_wc, Lighting((0.0, 0.0, 1.0), shadows=False))
    ground = view.segmentation == sim.terrain.body_id
    # depth buffer points lie on the ground plane z = 0 ...
    assert np.abs(view.points_world[ground][:, 2]).max() < 2e-3
    # ... and project back to their own pixels through the camera model
    rows, cols = np.nonzero(ground)
    sel = np.random.default_rng(0).choice(len(rows), 500, replace=False)
    pw = view.points_world[rows[sel], cols[sel]]
    pc = (np.linalg.inv(T_wc) @ np.column_stack([pw, np.ones(500)]).T).T[:, :3]
    px = cam.project(pc)
    assert np.abs(px - np.column_stack([cols[sel], rows[sel]])).max() < 1e-3  # float32 points


def test_small_squares_on_the_ground_appear_where_the_model_projects_them(parked_sim):
    """Not circular: the squares' image centroids come from the rasteriser alone."""
    sim = parked_sim
    c = sim.client
    cam = mast_camera(sim)
    T_wc = body_pose(sim) @ cam.T_body_cam
    rng = np.random.default_rng(7)
    shape = c.createVisualShape(pb.GEOM_BOX, halfExtents=[0.015, 0.015, 0.0005], rgbaColor=[1, 0, 0, 1])
    centres = []
    grid = np.stack(np.meshgrid(np.linspace(50, 590, 8), np.linspace(50, 430, 5)), -1).reshape(-1, 2)
    for px in grid + rng.uniform(-10, 10, grid.shape):  # apart, at random sub-pixel positions
        ray = np.linalg.inv(cam.K) @ np.array([px[0], px[1], 1.0])
        d = T_wc[:3, :3] @ ray
        p = T_wc[:3, 3] - d * (T_wc[2, 3] / d[2])  # on z = 0
        centres.append(p + [0.0, 0.0, 0.001])  # top face of the 1 mm plate
    ids = [c.createMultiBody(0, -1, shape, p.tolist()) for p in centres]
    try:
        view = renderer_for(sim).render_pinhole(cam, T_wc, Lighting((0.0, 0.0, 1.0), shadows=False))
    finally:
        for b in ids:
            c.removeBody(b)
    T_cw = np.linalg.inv(T_wc)
    err = []
    for b, p in zip(ids, centres, strict=True):
        rows, cols = np.nonzero(view.segmentation == b)
        assert len(rows) > 150
        err.append([cols.mean(), rows.mean()] - cam.project(T_cw[:3, :3] @ p + T_cw[:3, 3]))
    err = np.asarray(err)
    print(
        f"{renderer_for(sim).name} ground squares: bias {err.mean(axis=0).round(3)} px, "
        f"max {np.abs(err).max():.2f} px"
    )
    assert np.abs(err).max() < 0.25
    assert np.abs(err.mean(axis=0)).max() < 0.05  # no half-pixel convention error


def test_self_shadow_contrast_geometry_and_no_acne(parked_sim):
    sim = parked_sim
    cam = mast_camera(sim)
    T_wc = body_pose(sim) @ cam.T_body_cam
    sun = sun_behind(sim, 30.0)
    on = renderer_for(sim).render_pinhole(cam, T_wc, Lighting(sun, shadows=True))
    off = renderer_for(sim).render_pinhole(cam, T_wc, Lighting(sun, shadows=False))
    ground = on.segmentation == sim.terrain.body_id
    # geometric prediction: ray from each ground point toward the sun hits the rover
    oc = caster_world(sim)
    try:
        rows, cols = np.nonzero(ground)
        keep = (rows % 3 == 0) & (cols % 3 == 0)
        rows, cols = rows[keep], cols[keep]
        p = on.points_world[rows, cols]
        s = np.asarray(sun)
        pred = np.zeros(len(p), dtype=bool)
        for k in range(0, len(p), 8000):
            hits = oc.rayTestBatch((p[k : k + 8000] + 1e-4 * s).tolist(), (p[k : k + 8000] + 10 * s).tolist())
            pred[k : k + 8000] = [h[0] >= 0 for h in hits]
    finally:
        oc.disconnect()
    assert 0.1 < pred.mean() < 0.9, "the rover's shadow should fill part of the view"
    g_on = on.rgb.astype(float).mean(axis=2)[rows, cols]
    g_off = off.rgb.astype(float).mean(axis=2)[rows, cols]
    ratio = g_off[pred].mean() / g_on[pred].mean()
    rendered = g_on < 0.7 * g_off
    iou = (rendered & pred).sum() / (rendered | pred).sum()
    acne = np.abs(g_on[~pred] - g_off[~pred]).mean()
    print(
        f"{renderer_for(sim).name} shadow: lit/shadow ratio {ratio:.2f}, IoU {iou:.3f}, "
        f"lit-ground change {acne:.3f} grey levels"
    )
    assert ratio >= 2.5
    assert iou >= 0.9
    assert acne < 2.0  # no acne on lit ground


def test_shadow_lookup_from_depth_matches_the_lookup_of_3d_points(parked_sim):
    sim = parked_sim
    cam = mast_camera(sim)
    T_wc = body_pose(sim) @ cam.T_body_cam
    sun = sun_behind(sim, 30.0)
    view = renderer_for(sim).render_pinhole(cam, T_wc, Lighting(sun, shadows=False))
    smap = ShadowCaster(sim.client, sim.rover.body_id).shadow_map(sun, 0.005)
    from_points = smap.lookup(view.points_world)
    from_depth = smap.lookup_view(view.depth, cam.K, T_wc)
    print(f"shadowed {from_points.mean():.3f}; paths differ on {(from_points != from_depth).sum()} pixels")
    assert 0.1 < from_points.mean() < 0.9
    assert (from_points != from_depth).mean() < 1e-3  # cell-border rounding only


def test_homography_turns_image_motion_of_a_known_displacement_into_metres(parked_sim):
    """Move the rover 8 cm forward and 3 cm left; measure the texture's image shift by phase
    correlation and convert both ends through H^-1 into body-frame metres."""
    import cv2

    sim = parked_sim
    cam = DownwardCamera(sim, DownwardCameraConfig(shadows=False))
    c, body = sim.client, sim.rover.body_id
    pos0, quat = c.getBasePositionAndOrientation(body)
    T = body_pose(sim)
    r3 = T[2, :3]  # ground z_world = 0 written in the body frame: z = a x + b y + c
    plane = (-r3[0] / r3[2], -r3[1] / r3[2], -pos0[2] / r3[2])
    move_body = np.array([0.08, 0.03, 0.0])
    try:
        img0 = cam.capture().image
        c.resetBasePositionAndOrientation(body, (np.asarray(pos0) + T[:3, :3] @ move_body).tolist(), quat)
        img1 = cam.capture().image
    finally:
        c.resetBasePositionAndOrientation(body, pos0, quat)
    g0 = cv2.cvtColor(img0, cv2.COLOR_RGB2GRAY).astype(np.float64)
    g1 = cv2.cvtColor(img1, cv2.COLOR_RGB2GRAY).astype(np.float64)
    (dx, dy), _ = cv2.phaseCorrelate(g0, g1)
    centre = np.array([[319.5, 239.5]])
    a = cam.model.pixels_to_ground(centre, plane)[0]
    b = cam.model.pixels_to_ground(centre + [dx, dy], plane)[0]
    # a ground point fixed in the world moves by -displacement in the body frame
    measured = a - b
    print(f"homography: moved {move_body[:2]} m, measured {measured.round(5)} m")
    assert np.linalg.norm(measured - move_body[:2]) < 0.01 * np.linalg.norm(move_body[:2])


def test_frame_pairs_are_one_period_apart_with_the_hook_in_between(parked_sim):
    cam = DownwardCamera(parked_sim, DownwardCameraConfig.preset("train", shadows=False))
    seen = []
    prev, curr = parked_sim.capture_pair(cam, on_prev=lambda f: seen.append((f.t, parked_sim.t)))
    assert curr.t - prev.t == pytest.approx(1 / 60, abs=1e-12)
    assert seen == [(prev.t, prev.t)]  # the hook ran before physics advanced to I_curr
    assert prev.image.shape == (120, 160, 3)
    prev2, curr2 = parked_sim.capture_pair(cam, chained=True)
    assert prev2 is curr and curr2.t == pytest.approx(curr.t + 1 / 60, abs=1e-12)


def test_impossible_camera_configurations_fail_clearly(parked_sim):
    from rover_env.config.io import ConfigError

    with pytest.raises(ConfigError, match="width"):
        DownwardCameraConfig(width=0)
    with pytest.raises(ConfigError, match="hfov_deg"):
        DownwardCameraConfig(hfov_deg=200.0)
    with pytest.raises(ConfigError, match="preset"):
        DownwardCameraConfig.preset("huge")
    with pytest.raises(ConfigError, match="does not divide"):
        DownwardCamera(parked_sim, DownwardCameraConfig(rate_hz=50.0))


@pytest.mark.parametrize("renderer", ["tiny", "gl"])
def test_both_renderers_put_boxes_where_the_pinhole_model_projects_them(renderer):
    from rover_env.rendering.gl import GLRenderer
    from rover_env.rendering.tiny import TinyRenderer

    c = BulletClient(connection_mode=pb.DIRECT)
    r = GLRenderer(c) if renderer == "gl" else TinyRenderer(c)
    try:
        cam = PinholeCamera(
            K=np.array([[300.0, 0, 160.3], [0, 300.0, 118.8], [0, 0, 1]]),
            distortion=np.zeros(5),
            image_size=(321, 243),
        )
        shape = c.createVisualShape(pb.GEOM_BOX, halfExtents=[0.0333, 0.0333, 0.001], rgbaColor=[1, 0, 0, 1])
        rng = np.random.default_rng(1)
        err = []
        for _ in range(60):
            p = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), 1.0])
            body = c.createMultiBody(0, -1, shape, p.tolist())
            view = r.render_pinhole(cam, np.eye(4), Lighting((0, 0, -1.0), shadows=False))
            rows, cols = np.nonzero(view.segmentation == body)
            err.append([cols.mean(), rows.mean()] - cam.project(p))
            c.removeBody(body)
    finally:
        r.release()
        c.disconnect()
    bias = np.mean(err, axis=0)
    print(f"{renderer}: box centroid bias {bias.round(3)} px")
    assert np.abs(bias).max() < 0.12  # rasterisation noise of one box is ~0.27 px


@pytest.mark.parametrize("preset", ["train", "eval"])
def test_cameras_ground_range_leaves_the_pixels_they_need_unchanged(preset):
    """With ground_range the preset's cameras draw only near ground; the ground they see is the same."""
    import dataclasses

    from conftest import rough_scenario

    from rover_env.sensors.cameras import FisheyeCamera
    from rover_env.sensors.rig import PERCEPTION_PRESETS

    p = PERCEPTION_PRESETS[preset]
    assert p.downward.ground_range is not None
    sim = RoverSim(rough_scenario())
    try:
        sim.reset(1.0, -0.5, 0.3)
        sim.step(0.5)
        pos = np.array(sim.client.getBasePositionAndOrientation(sim.rover.body_id)[0])
        for cls, cfg in ((DownwardCamera, p.downward), (FisheyeCamera, p.fisheye)):
            full = cls(sim, dataclasses.replace(cfg, ground_range=None)).render_view()
            near = cls(sim, cfg).render_view()
            seen = np.isfinite(full.points_world).all(axis=-1) & (full.segmentation >= 0)
            if cls is FisheyeCamera:
                seen &= cls(sim, cfg).remapper.rendered
            dist = np.hypot(*(full.points_world[..., :2] - pos[:2]).transpose(2, 0, 1))
            if cfg.ground_range is None:
                assert np.array_equal(near.rgb, full.rgb)
                continue
            # away from far ground by a pixel: the fisheye interpolates its views bilinearly
            near_ground = seen & (dist < cfg.ground_range - 0.05)
            inside = minimum_filter(near_ground | ~seen, 3) & near_ground
            assert inside.sum() > 5000
            same = np.all(near.rgb == full.rgb, axis=-1)[inside]
            assert same.mean() > 0.999, f"{cls.__name__}: {np.sum(~same)} of {inside.sum()} px differ"
    finally:
        sim.close()


@pytest.mark.parametrize("principal", [(80.0, 60.0), (-50.0, -40.0), (210.0, 170.0), (-30.0, 60.0)])
def test_view_planes_hold_exactly_the_points_the_view_sees(principal):
    """Points back-projected from pixels inside the image, beyond ``near``, are inside every plane;
    pixels past an edge, or points nearer than ``near``, are outside one. Crops whose principal
    point lies outside the image (a fisheye face's window) included."""
    rng = np.random.default_rng(0)
    K = np.array([[100.0, 0.0, principal[0]], [0.0, 90.0, principal[1]], [0.0, 0.0, 1.0]])
    w, h, near = 160, 120, 0.05
    T = look_at([0.3, -0.2, 1.0], [0.5, 0.1, 0.0])
    planes = view_planes(K, (w, h), T, near)

    def world(u, v, z):
        ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        return (ray * z[:, None]) @ T[:3, :3].T + T[:3, 3]

    def margin(x):  # smallest signed distance to the planes
        return (x @ planes[:, :3].T + planes[:, 3]).min(axis=1)

    n = 2000
    u, v, z = rng.uniform(0.5, w - 0.5, n), rng.uniform(0.5, h - 0.5, n), rng.uniform(near + 0.01, 5.0, n)
    assert (margin(world(u, v, z)) > 0).all()
    outside = [
        world(rng.uniform(-50, -0.5, n), v, z),  # left of the image
        world(rng.uniform(w + 0.5, w + 50, n), v, z),
        world(u, rng.uniform(-50, -0.5, n), z),
        world(u, rng.uniform(h + 0.5, h + 50, n), z),
        world(u, v, rng.uniform(0.001, near - 0.001, n)),  # nearer than near
    ]
    for x in outside:
        assert (margin(x) < 0).all()


def test_every_wheel_triangle_faces_outward_so_no_renderer_culls_it():
    """Renderers that cull back faces (TinyRenderer) draw a triangle only when it is wound
    counter-clockwise seen from outside; the wheel is convex about its centre, so each
    triangle's winding normal points away from the centre."""
    from rover_env.rendering.gl import load_obj
    from rover_env.sim.geometry import RoverGeometry
    from rover_env.sim.urdf import wheel_mesh

    pos, nrm, _ = load_obj(str(wheel_mesh(RoverGeometry())))
    p, n = pos.reshape(-1, 3, 3), nrm.reshape(-1, 3, 3)  # (triangles, corners, xyz)
    winding = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert len(p) == 4 * 64
    assert np.all(np.einsum("ij,ij->i", winding, p.mean(axis=1)) > 0.0)  # away from the centre
    assert np.all(np.einsum("ij,ij->i", winding, n.mean(axis=1)) > 0.0)  # as the file's normals
