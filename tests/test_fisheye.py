"""The rendered fisheye against its OmniCamera model: geometry, seams, fiducials and treads in view."""

import math

import cv2
import gymnasium as gym
import numpy as np
import pytest
from conftest import flat_scenario
from scipy.ndimage import maximum_filter, minimum_filter

from perception.models.rover_parts import joint_window_parts, kinematic_parts
from rover_env.config.cameras import FisheyeCameraConfig
from rover_env.config.io import ConfigError
from rover_env.rendering import renderer_for
from rover_env.rendering.cubemap import CubemapRemap
from rover_env.sensors.cameras import FisheyeCamera
from rover_env.sim.geometry import AXLES, WHEELS, RoverGeometry
from rover_env.sim.simulation import RoverSim

RENDERERS = ["gl", pytest.param("tiny", marks=pytest.mark.slow)]


@pytest.fixture(scope="module", params=RENDERERS)
def lifted_sim(request):
    """A parked rover lifted 8 cm so that any joint state can be set without touching the ground."""
    sim = RoverSim(flat_scenario(mu=1.0), renderer=request.param)
    sim.reset(7.3, -4.1, math.radians(35.0))
    c, body = sim.client, sim.rover.body_id
    pos, quat = c.getBasePositionAndOrientation(body)
    c.resetBasePositionAndOrientation(body, [pos[0], pos[1], pos[2] + 0.08], quat)
    yield sim
    sim.close()


def set_joints(sim, lam, psi, travel, wheel_angles) -> None:
    """Kinematic joint state: axle steering lam (2), roll psi (2), travel (2), wheel angles (4)."""
    c, rv, g = sim.client, sim.rover, sim.geometry
    delta = g.ackermann_angles(lam[0], lam[1])
    for i, a in enumerate(AXLES):
        c.resetJointState(rv.body_id, rv.joint[f"roll_{a}"], psi[i])
        c.resetJointState(rv.body_id, rv.joint[f"travel_{a}"], travel[i])
    for i, w in enumerate(WHEELS):
        c.resetJointState(rv.body_id, rv.joint[f"steer_{w}"], delta[i])
        c.resetJointState(rv.body_id, rv.joint[f"wheel_{w}"], wheel_angles[i])


def link_pose(sim, link_name):
    st = sim.client.getLinkState(sim.rover.body_id, sim.rover.link[link_name], computeForwardKinematics=1)
    return np.array(sim.client.getMatrixFromQuaternion(st[5])).reshape(3, 3), np.asarray(st[4])


def feasible_states(g, n, rng):
    """Random joint states over the full steering and roll range; travel where the axle beam
    stays below the body (the simulator does not collide them, a real rover cannot pass)."""
    corners = [
        (np.array([sf, sr]) * g.steer_limit, np.array([pf, pr]) * g.roll_limit, np.full(2, -0.03))
        for sf, sr, pf, pr in [(1, -1, 1, -1), (-1, 1, -1, 1), (1, 1, -1, -1), (-1, -1, 1, 1)]
    ]
    out = list(corners)
    body_bottom = -g.body_size[2] / 2
    while len(out) < n:
        lam = rng.uniform(-g.steer_limit, g.steer_limit, 2)
        psi = rng.uniform(-g.roll_limit, g.roll_limit, 2)
        d = rng.uniform(-g.travel_limit, g.travel_limit, 2)
        beam_top = g.axle_z + d + g.axle_beam_size[2] / 2 + g.axle_beam_size[1] / 2 * np.abs(np.sin(psi))
        if np.all(beam_top < body_bottom):
            out.append((lam, psi, d))
    return out


def test_fisheye_pixels_see_what_the_model_projects_there(lifted_sim):
    sim = lifted_sim
    set_joints(sim, (0.2, -0.1), (0.1, -0.05), (0.0, 0.0), (0.0,) * 4)
    cam = FisheyeCamera(sim)
    view = cam.render_view()
    T_cam_world = np.linalg.inv(cam.T_world_cam())
    hit = view.segmentation >= 0
    rows, cols = np.nonzero(hit)
    p = view.points_world[hit].astype(np.float64)
    px = cam.model.world2cam(p @ T_cam_world[:3, :3].T + T_cam_world[:3, 3])
    ok = np.isfinite(px[:, 0])  # the few rim pixels whose face sample lies just beyond 95 deg
    err = np.hypot(px[ok, 0] - cols[ok], px[ok, 1] - rows[ok])
    print(f"fisheye reprojection: median {np.median(err):.2f} px, max {err.max():.2f} px on {ok.sum()} px")
    assert ok.mean() > 0.999
    # points are looked up at the nearest face pixel (face pixels are no larger than image pixels)
    assert err.max() < 1.0 and np.median(err) < 0.4
    # the image circle: 190 deg, cut by the top and bottom edges
    assert cam.model.max_fov == pytest.approx(math.radians(190.0))
    valid = cam.remapper.valid
    assert valid[240, 25] and valid[240, 614] and not valid[240, 15] and not valid[0, 0]
    assert valid[0, 320] and valid[479, 320]


def test_fisheye_has_no_seams(lifted_sim):
    """Turning the cube 45 deg about the optical axis moves every face edge; the image must not care."""
    sim = lifted_sim
    set_joints(sim, (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0,) * 4)
    cam = FisheyeCamera(sim)
    other = CubemapRemap(cam.model, cube_roll=math.pi / 4)
    a = cam.capture().image.astype(np.float32)
    b = renderer_for(sim).render_fisheye(other, cam.T_world_cam(), cam.lighting).rgb
    diff = np.abs(a - b.astype(np.float32)).mean(axis=2)

    def seam_band(face_index, r=2):
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        f = (face_index + 1).astype(np.uint8)
        return (cv2.dilate(f, k) != cv2.erode(f, k)) & (face_index >= 0)

    inner = cv2.erode(cam.remapper.valid.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    sa, sb = seam_band(cam.remapper.face_index), seam_band(other.face_index)
    on_seams = diff[inner & (sa | sb)].mean()
    elsewhere = diff[inner & ~sa & ~sb].mean()
    print(f"seams: mean |difference| {on_seams:.2f} grey levels on face edges, {elsewhere:.2f} elsewhere")
    assert on_seams < 1.25 * elsewhere + 0.5
    assert elsewhere < 4.0  # the two cubes resample the same scene


@pytest.mark.parametrize("renderer", RENDERERS)
def test_no_step_across_cube_face_borders_on_a_smooth_texture(tmp_path, renderer):
    """Along every face border, the step between the two sides is no larger than the image's
    own gradient next to it (a seam would show as a step where the texture has none)."""
    from rover_env.config.scenario import ScenarioConfig, TerrainConfig
    from rover_env.task.course import CourseConfig

    yy, xx = np.mgrid[0:512, 0:512] / 512.0
    smooth = 128 + 50 * np.sin(2 * np.pi * (2 * xx + yy)) * np.cos(2 * np.pi * 3 * yy)
    cv2.imwrite(str(tmp_path / "smooth.png"), np.repeat(smooth[..., None], 3, axis=2).astype(np.uint8))
    scenario = ScenarioConfig(
        name="smooth",
        course=CourseConfig(waypoints=((3.0, 0.0),)),
        terrain=TerrainConfig(size=(20.0, 20.0), texture=str(tmp_path / "smooth.png"), texture_tile=1.5),
    )
    sim = RoverSim(scenario, renderer=renderer)
    try:
        sim.reset(0.3, -0.2, 0.4)
        cam = FisheyeCamera(sim, FisheyeCameraConfig(shadows=False))
        view = cam.render_view()
    finally:
        sim.close()
    img = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    ground = view.segmentation == 0  # the terrain is body 0
    ground = cv2.erode(ground.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    face = cam.remapper.face_index
    worst, pairs = 0.0, 0
    for axis in (0, 1):  # vertical and horizontal neighbours
        a = [slice(2, -3), slice(2, -3)]
        b = list(a)
        b[axis] = slice(3, -2)
        across = (face[tuple(a)] != face[tuple(b)]) & ground[tuple(a)] & ground[tuple(b)]
        step = np.abs(img[tuple(a)] - img[tuple(b)])
        # the image's own gradient: the largest same-direction step within the face, 3 px around
        # (the renderer samples texels by nearest neighbour, so the texture itself steps)
        within = np.where(face[tuple(a)] == face[tuple(b)], step, 0.0).astype(np.float32)
        own = cv2.dilate(within, np.ones((7, 7), np.uint8))
        excess = step[across] - own[across]
        pairs += int(across.sum())
        worst = max(worst, float(excess.max()))
    print(
        f"face borders: {pairs} pixel pairs on the ground; largest step above the local gradient {worst:.1f}"
    )
    assert pairs > 500
    assert worst <= 1.0  # one grey level of rounding


def magenta_blobs(rgb):
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    mask = (hsv[..., 0] > 140) & (hsv[..., 0] < 160) & (hsv[..., 1] > 120) & (hsv[..., 2] > 25)
    _, _, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return stats[1:], centroids[1:]


def test_fiducials_and_treads_in_view_and_where_the_model_says_over_50_states(lifted_sim):
    sim = lifted_sim
    g = sim.geometry
    cam = FisheyeCamera(sim)
    fids = [f for f in g.fiducials() if f.name[0] in "ABCD"]
    assert len(fids) == 8
    rng = np.random.default_rng(20261122)
    errors, tread_px = [], []
    for lam, psi, d in feasible_states(g, 54, rng):
        set_joints(sim, lam, psi, d, rng.uniform(-math.pi, math.pi, 4))
        view = cam.render_view()
        stats, centroids = magenta_blobs(view.rgb)
        T = np.linalg.inv(cam.T_world_cam())
        for f in fids:
            R, t = link_pose(sim, f.link)
            face_centre = R @ (np.asarray(f.position) + 0.001 * np.asarray(f.normal)) + t  # 2 mm plate
            px = cam.model.world2cam(T[:3, :3] @ face_centre + T[:3, 3])
            dist = np.hypot(centroids[:, 0] - px[0], centroids[:, 1] - px[1])
            j = int(np.argmin(dist))
            assert stats[j, cv2.CC_STAT_AREA] > 100, f"{f.name} mostly hidden at lam={lam}, psi={psi}"
            errors.append(dist[j])
        for w in WHEELS:
            link = sim.rover.link[f"wheel_{w}"]
            R, t = link_pose(sim, f"wheel_{w}")
            mine = view.segmentation == sim.rover.body_id + ((link + 1) << 24)
            local = (view.points_world[mine] - t) @ R  # wheel frame, axis y
            on_tread = (np.hypot(local[:, 0], local[:, 2]) > g.wheel_radius - 0.002) & (
                np.abs(local[:, 1]) < g.wheel_width / 2 - 0.002
            )
            tread_px.append(int(on_tread.sum()))
    errors = np.asarray(errors)
    print(
        f"fiducial centroids over {len(errors) // 8} states: mean {errors.mean():.2f} px, "
        f"p95 {np.percentile(errors, 95):.2f} px, max {errors.max():.2f} px; "
        f"tread pixels per wheel: min {min(tread_px)}, median {int(np.median(tread_px))}"
    )
    assert errors.max() <= 1.5
    assert min(tread_px) >= 250  # about 300 px at full lock and full roll, ~1900 typical


def test_roi_holds_every_wheel_and_marker_pixel_over_the_joint_range_and_renders_them_exactly(lifted_sim):
    """The train preset's fisheye renders only kinematics_roi; nothing the estimator reads is outside."""
    sim = lifted_sim
    full = FisheyeCamera(sim, FisheyeCameraConfig.preset("half"))
    roi = FisheyeCamera(sim, FisheyeCameraConfig.preset("half", roi=True))
    rendered = roi.remapper.rendered
    assert roi.remapper.face_pixels < 0.35 * full.remapper.face_pixels
    assert len(roi.remapper.faces) == 4  # one view per wheel corner
    wheels = [sim.rover.body_id + ((sim.rover.link[f"wheel_{w}"] + 1) << 24) for w in WHEELS]
    rng = np.random.default_rng(5)
    for lam, psi, d in feasible_states(sim.geometry, 10, rng):
        set_joints(sim, lam, psi, d, rng.uniform(-math.pi, math.pi, 4))
        view = full.render_view()
        stats, centroids = magenta_blobs(view.rgb)
        needed = np.isin(view.segmentation, wheels)
        for x, y, w, h in stats[:, :4]:
            needed[y : y + h, x : x + w] = True
        needed &= full.remapper.valid
        assert needed.sum() > 2000
        assert np.all(rendered[needed]), f"ROI misses {np.sum(needed & ~rendered)} px at lam={lam}, psi={psi}"
        # the ROI views see the same surfaces along the same rays; outside the ROI it is black
        small = roi.render_view()
        assert not small.rgb[~rendered].any()
        T_cam_world = np.linalg.inv(roi.T_world_cam())
        hit = rendered & (small.segmentation >= 0)
        p = small.points_world[hit].astype(np.float64)
        px = roi.model.world2cam(p @ T_cam_world[:3, :3].T + T_cam_world[:3, 3])
        rows, cols = np.nonzero(hit)
        err = np.hypot(px[:, 0] - cols, px[:, 1] - rows)
        # nearest view pixel; at the rim a view pixel spans up to 1.7 image pixels tangentially
        assert np.nanmax(err) < 1.25 and np.nanmedian(err) < 0.5
        # labels differ only along edges (sampled from other views): compare away from them
        seg = view.segmentation
        interior = rendered & (minimum_filter(seg, 3) == maximum_filter(seg, 3))
        same = (small.segmentation == seg)[interior]
        assert same.mean() > 0.999


def test_joint_window_parts_are_the_part_outlines_at_the_corners_of_the_joint_box():
    """The vectorised corners equal kinematic_parts (the model's own geometry) at each corner."""
    g = RoverGeometry()
    model = g.kinematic_model(np.eye(4))
    psi, depth = np.array([0.05, -0.08]), np.array([0.16, 0.14])
    delta = model.wheel_angles(0.3, -0.2)
    spread = (0.06, 0.01, 0.08)
    corners = [
        np.vstack(kinematic_parts(model, psi + a, depth + b, delta + c, outline=True))
        for a in (-spread[0], spread[0])
        for b in (-spread[1], spread[1])
        for c in (-spread[2], spread[2])
    ]
    got = joint_window_parts(model, psi, depth, delta, spread)
    want = np.vstack(corners)
    assert got.shape == want.shape
    # the same points (in another order): compare them sorted
    order = lambda a: a[np.lexsort(np.round(a, 9).T)]  # noqa: E731
    np.testing.assert_allclose(order(got), order(want), atol=1e-12)


def test_windows_about_the_joint_state_render_the_parts_a_frame_later_at_under_half_the_roi(lifted_sim):
    """A tracker's windows (joint_window_parts about the last state) still hold every wheel, arm
    and marker pixel after the joints move within the spread, rendered as in the whole ROI."""
    sim = lifted_sim
    cam = FisheyeCamera(sim, FisheyeCameraConfig.preset("half", roi=True))
    model = sim.geometry.kinematic_model(cam.T_body_cam)
    rv = sim.rover
    # the wheels, and the knuckles' steering arms and tie-rod markers; plate markers below
    read = [
        rv.body_id + ((rv.link[f"{part}_{w}"] + 1) << 24) for part in ("wheel", "knuckle") for w in WHEELS
    ]
    spread = (0.06, 0.01, 0.08)  # roll [rad], travel [m], wheel steering [rad]
    rng = np.random.default_rng(11)
    areas, diffs = [], []
    for lam, psi, d in feasible_states(sim.geometry, 6, rng):
        set_joints(sim, lam, psi, d, rng.uniform(-math.pi, math.pi, 4))
        gt = sim.ground_truth()
        parts = joint_window_parts(model, gt.axle_roll, gt.axle_height, gt.wheel_steer, spread)
        windows = cam.windows(parts)
        areas.append(sum((u1 - u0) * (v1 - v0) for u0, v0, u1, v1 in windows))
        # a frame later: roll and travel moved by up to 0.9 of their spread, the axles' steering
        # by up to 0.6 of it (the inner wheel turns up to 1.3x its axle)
        step = rng.uniform(-1.0, 1.0, (3, 2)) * np.array(
            [[0.9 * spread[0]], [0.9 * spread[1]], [0.6 * spread[2]]]
        )
        set_joints(sim, lam + step[2], psi + step[0], d + step[1], rng.uniform(-math.pi, math.pi, 4))
        whole, win = cam.render_view(), cam.render_view(parts)
        needed = np.isin(whole.segmentation, read)
        stats, _ = magenta_blobs(whole.rgb)
        assert len(stats) == 8
        for x, y, w, h in stats[:, :4]:
            needed[y : y + h, x : x + w] = True
        assert needed.sum() > 3000
        assert np.array_equal(win.segmentation[needed], whole.segmentation[needed])
        diffs.append(np.abs(win.rgb[needed].astype(int) - whole.rgb[needed]).max(axis=1))
        # outside the windows the image is black
        inside = np.zeros(cam.remapper.atlas_size[::-1], bool)
        for fc, (u0, v0, u1, v1) in zip(cam.remapper.faces, windows, strict=True):
            inside[fc.atlas_row + v0 : fc.atlas_row + v1, u0:u1] = True
        lit = cam.remapper.lookup(inside, outside=False)
        assert not win.rgb[~lit & (cv2.dilate(lit.view(np.uint8), np.ones((3, 3), np.uint8)) == 0)].any()
    diffs = np.concatenate(diffs)
    print(
        f"window pixels: {np.mean(areas):.0f} of {cam.remapper.face_pixels} ROI face pixels; "
        f"part pixels within 1 grey level: {np.mean(diffs <= 1):.4f}, max difference {diffs.max()}"
    )
    assert max(areas) < 0.55 * cam.remapper.face_pixels
    assert np.mean(diffs <= 1) > 0.999


def test_fisheye_config_errors():
    with pytest.raises(ConfigError, match="fov_deg"):
        FisheyeCameraConfig(fov_deg=170.0)
    with pytest.raises(ConfigError, match="width"):
        FisheyeCameraConfig(width=8)
    with pytest.raises(ConfigError, match="preset"):
        FisheyeCameraConfig.preset("huge")
    assert FisheyeCameraConfig.preset("train").width == 160


def checkerboard_corners(cam, view, square, reach=1.5, min_square_px=16.0):
    """Sub-pixel corners of the checkerboard ground seen by ``cam`` and their camera-frame points.

    The corner search starts at each grid corner's model projection; ``cv2.cornerSubPix`` then
    moves it to the saddle point the image actually shows.
    """
    T_wc = cam.T_world_cam()
    T_cw = np.linalg.inv(T_wc)
    cx, cy = T_wc[0, 3], T_wc[1, 3]
    n = int(reach / square)
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))
    gx = (np.round(cx / square) + i.ravel()) * square
    gy = (np.round(cy / square) + j.ravel()) * square

    def project(x, y):
        p = np.stack([x, y, np.zeros_like(x)], 1)
        return cam.model.world2cam(p @ T_cw[:3, :3].T + T_cw[:3, 3]), p @ T_cw[:3, :3].T + T_cw[:3, 3]

    px, pc = project(gx, gy)
    side = np.minimum(
        np.hypot(*(project(gx + square, gy)[0] - px).T), np.hypot(*(project(gx, gy + square)[0] - px).T)
    )
    w, h = cam.model.image_size
    ok = np.isfinite(px).all(axis=1) & (side >= min_square_px)
    ok &= (px[:, 0] > 8) & (px[:, 0] < w - 9) & (px[:, 1] > 8) & (px[:, 1] < h - 9)
    ground = (view.segmentation == cam.sim.terrain.body_id).astype(np.uint8)
    clear = cv2.erode(ground, np.ones((15, 15), np.uint8)) > 0  # no rover part within 7 px
    idx = np.flatnonzero(ok)
    idx = idx[clear[np.rint(px[idx, 1]).astype(int), np.rint(px[idx, 0]).astype(int)]]
    gray = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY)
    start = px[idx].astype(np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    found = cv2.cornerSubPix(gray, start.copy(), (5, 5), (-1, -1), crit).reshape(-1, 2)
    return found, pc[idx], px[idx]


@pytest.mark.parametrize("renderer", RENDERERS)
def test_omni_model_refits_from_rendered_checkerboard_corners(renderer):
    from perception.models.calibration import fit_omni_camera
    from rover_env.config.scenario import load_scenario

    scenario = load_scenario("calibration")
    square = scenario.terrain.checker_square
    assert square == pytest.approx(0.05)
    sim = RoverSim(scenario, renderer=renderer)
    try:
        # 2x supersampled faces: the remap then averages the rasteriser's aliased edges
        cam = FisheyeCamera(sim, FisheyeCameraConfig(shadows=False, oversample=2.0))
        found, points, predicted = [], [], []
        for x, y, yaw in [(0.013, 0.021, 0.1), (0.31, -0.22, 0.75), (-0.17, 0.4, 1.9)]:
            sim.reset(x, y, yaw)
            f, p, pred = checkerboard_corners(cam, cam.render_view(), square)
            found.append(f)
            points.append(p)
            predicted.append(pred)
    finally:
        sim.close()
    found, points, predicted = (np.concatenate(v) for v in (found, points, predicted))
    moved = np.hypot(*(found - predicted).T)
    fit = fit_omni_camera(found, points, cam.model.image_size, cam.model.max_fov)
    # the fitted model against the rendering model, over the directions the corners cover
    alpha = np.arccos(points[:, 2] / np.linalg.norm(points, axis=1))
    grid_a, grid_p = np.meshgrid(np.linspace(0.05, alpha.max(), 40), np.linspace(-np.pi, np.pi, 72))
    rays = np.stack([np.sin(grid_a) * np.cos(grid_p), np.sin(grid_a) * np.sin(grid_p), np.cos(grid_a)], -1)
    model_gap = np.hypot(*(fit.camera.world2cam(rays) - cam.model.world2cam(rays)).reshape(-1, 2).T)
    print(
        f"{renderer} checkerboard: {fit.inliers.sum()} of {len(found)} corners "
        f"up to {np.degrees(alpha.max()):.0f} deg, "
        f"detected {np.median(moved):.2f} px (median) from the rendering model; "
        f"fit RMS {fit.rms_px:.3f} px, "
        f"max {fit.max_px:.2f} px; fitted vs rendering model: max {np.nanmax(model_gap):.2f} px"
    )
    assert fit.inliers.sum() >= 200 and fit.inliers.mean() > 0.9
    assert fit.rms_px <= 0.3
    assert np.nanmax(model_gap) < 0.5


def test_renderer_choice_errors_and_fallback(monkeypatch, caplog):
    """Unknown names list the choices; an explicit 'gl' that cannot start names what is missing;
    'auto' falls back to TinyRenderer with one warning."""
    import logging

    import rover_env.rendering as rendering
    import rover_env.rendering.gl as gl_render

    with pytest.raises(ValueError, match="'gl'.*'tiny'.*'auto'"):
        RoverSim(flat_scenario(mu=1.0), renderer="vulkan")
    monkeypatch.setattr(gl_render, "gl_status", lambda: (False, "libEGL.so is not installed"))
    rendering._warn_fallback.cache_clear()
    with pytest.raises(gl_render.GLUnavailableError, match="libEGL.so is not installed"):
        renderer_for(RoverSim(flat_scenario(mu=1.0), renderer="gl"))
    with pytest.raises(gl_render.GLUnavailableError, match="libEGL.so is not installed"):
        gym.make("Rover-v0", renderer="gl")  # an environment says so when it is made
    with caplog.at_level(logging.WARNING, logger="rover_env.rendering"):
        sims = [RoverSim(flat_scenario(mu=1.0)) for _ in range(2)]
        names = [renderer_for(s).name for s in sims]
    try:
        assert names == ["tiny", "tiny"]
        warned = [r for r in caplog.records if "TinyRenderer" in r.getMessage()]
        assert len(warned) == 1 and "libEGL.so" in warned[0].getMessage()
    finally:
        for s in sims:
            s.close()
        rendering._warn_fallback.cache_clear()
