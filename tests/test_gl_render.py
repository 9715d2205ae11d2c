"""The OpenGL renderer: its resources, its inputs, and its images against TinyRenderer's."""

import math

import numpy as np
import pytest
from conftest import flat_scenario, rough_scenario

from rover_env.rendering import renderer_for
from rover_env.rendering.gl import GLRenderer, gl_status, load_obj, projection_from_K, skip_rects
from rover_env.sim.simulation import RoverSim

pytestmark = pytest.mark.skipif(not gl_status()[0], reason=f"no OpenGL context here: {gl_status()[1]}")


def test_projection_maps_pixel_centres_to_the_model_pixels():
    """A point on pixel (u, v)'s ray lands at the centre of window pixel (u, v), row 0 first."""
    K = np.array([[210.0, 0.0, 81.3], [0.0, 190.0, 58.9], [0.0, 0.0, 1.0]])
    w, h, near, far = 160, 120, 0.05, 20.0
    P = projection_from_K(K, (w, h), near, far)
    rng = np.random.default_rng(0)
    u, v, z = rng.uniform(0, w - 1, 50), rng.uniform(0, h - 1, 50), rng.uniform(0.1, 10.0, 50)
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z, np.ones(50)], 1)
    clip = pts @ P.T
    ndc = clip[:, :3] / clip[:, 3:]
    win_x = (ndc[:, 0] + 1) / 2 * w  # window coordinates: pixel i spans [i, i + 1)
    win_y = (ndc[:, 1] + 1) / 2 * h
    np.testing.assert_allclose(win_x - 0.5, u, atol=1e-9)
    np.testing.assert_allclose(win_y - 0.5, v, atol=1e-9)
    z_ndc = ndc[:, 2]
    assert np.all((z_ndc > -1) & (z_ndc < 1))
    near_pt = np.array([0.0, 0.0, near, 1.0]) @ P.T
    assert near_pt[2] / near_pt[3] == pytest.approx(-1.0)


def test_the_rectangles_a_view_skips_cover_exactly_the_pixels_it_need_not_draw():
    rng = np.random.default_rng(3)
    keep = rng.random((37, 53)) < 0.6
    keep[5] = True  # a row with nothing to skip
    keep[9] = False  # and one with nothing to keep
    rects = skip_rects(keep)
    covered = np.zeros(keep.shape, int)
    for x0, y0, x1, y1 in rects:
        assert y1 == y0 + 1 and x1 > x0
        covered[y0:y1, x0:x1] += 1
    np.testing.assert_array_equal(covered, ~keep)  # each pixel not kept once, no kept one
    assert skip_rects(np.ones((4, 6), bool)).shape == (0, 4)


def test_obj_loader_triangulates_and_checks_indices(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n")
    pos, nrm, uv = load_obj(str(path))
    assert pos.shape == (6, 3) and uv.shape == (6, 2)
    np.testing.assert_allclose(nrm, np.tile([0.0, 0.0, 1.0], (6, 1)))  # face normals when none given
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="missing vertex"):
        load_obj(str(bad))


def test_no_gl_objects_leak_across_resets_and_close_releases_the_context():
    import gymnasium as gym

    import rover_env  # noqa: F401

    env = gym.make("Rover-v0", renderer="gl")
    try:
        env.reset(seed=0)
        for _ in range(5):
            env.step(np.array([0.5, 0.1, 0.0], dtype=np.float32))
        gl = renderer_for(env.unwrapped.sim)
        assert isinstance(gl, GLRenderer)
        count = gl.object_count
        for seed in range(1, 6):
            env.reset(seed=seed)
            for _ in range(3):
                env.step(np.array([0.5, -0.1, 0.0], dtype=np.float32))
        assert gl.object_count == count
    finally:
        env.close()
    assert gl.released and not env.unwrapped.sim._attached


@pytest.mark.parametrize("scenario", [flat_scenario, rough_scenario])
def test_gl_and_tiny_see_the_same_ground_and_rover(scenario):
    """A view from behind the rover: the same pixels are ground, rover and shadow, and ground and
    rover have the same mean brightness (TinyRenderer samples textures by nearest neighbour, GL
    filters them: pixels differ, the scene does not)."""
    from perception.models.cameras import PinholeCamera
    from rover_env.rendering import focus_on_rover
    from rover_env.rendering.base import Lighting, look_at

    cam = PinholeCamera.from_fov((320, 240), math.radians(60.0), math.radians(46.0))
    out = {}
    for renderer in ("tiny", "gl"):
        sim = RoverSim(scenario(), renderer=renderer)
        try:
            sim.reset(1.0, -0.5, math.radians(20.0))
            pos = np.array(sim.base_pose()[0])
            sun = (-0.5, 0.3, 0.8)
            r = focus_on_rover(sim)
            T = look_at(pos + [-1.6, -0.9, 1.1], pos)
            v = r.render_pinhole(cam, T, Lighting(sun, shadows=True), far=30.0)
            label = np.full(v.segmentation.shape, -1)
            label[np.isin(v.segmentation, r.ground_ids)] = 0
            label[(v.segmentation >= 0) & ((v.segmentation & 0xFFFFFF) == sim.rover.body_id)] = 1
            out[renderer] = (label, v.rgb.astype(float).mean(axis=2), v.shadow)
        finally:
            sim.close()
    (la, ga, sa), (lb, gb, sb) = out["tiny"], out["gl"]
    same = la == lb
    print(f"labels agree on {same.mean():.4f}; rover {np.sum(la == 1)} px")
    assert same.mean() > 0.99 and (la == 1).sum() > 2000
    for k in (0, 1):
        sel = same & (la == k)
        ma, mb = ga[sel].mean(), gb[sel].mean()
        print(f"class {k}: mean grey tiny {ma:.1f}, gl {mb:.1f}")
        assert abs(ma - mb) < 0.06 * ma
    ground = same & (la == 0)
    assert sa[ground].any() and np.mean(sa[ground] == sb[ground]) > 0.99


def test_link_poses_are_pybullets_forward_kinematics_and_rendering_leaves_the_physics_alone():
    """The renderer's own forward kinematics equals PyBullet's recomputed one (PyBullet's stored
    link frames lag a step; recomputing them would change the physics)."""
    sim = RoverSim(flat_scenario(), renderer="gl")
    try:
        sim.reset(0.0, 0.0, 0.3)
        sim.rover.command(np.full(4, 10.0), 0.2, -0.1)
        sim.step(0.7)
        gl = renderer_for(sim)
        c, body = sim.client, sim.rover.body_id
        M = gl._link_poses(body)
        states = c.getLinkStates(body, list(range(c.getNumJoints(body))), computeForwardKinematics=1)
        for k, st in enumerate(states):
            np.testing.assert_allclose(M[k + 1, :3, 3], st[0], atol=1e-12)
            R = np.array(c.getMatrixFromQuaternion(st[1])).reshape(3, 3)
            np.testing.assert_allclose(M[k + 1, :3, :3], R, atol=1e-12)
    finally:
        sim.close()


@pytest.mark.parametrize("renderer", ["gl", "tiny"])
def test_ruts_in_soil_are_shaded_by_the_slope_of_their_walls(renderer):
    """After a drive on soil, a view down on the rear wheels' tracks against the same view with
    the ruts left out: the ground outside the tracks is the same to the bit; at each track's edges
    the shading is that of the rut surface's slope (Lambert's law with the normal tilted by the
    depth's central difference over one cell), the wall facing the sun brighter, the other in
    its own shade (ambient light only). Both renderers."""
    from perception.models.cameras import PinholeCamera
    from rover_env.config.scenario import FrictionPatch
    from rover_env.rendering import focus_on_rover
    from rover_env.rendering.base import Lighting, look_at

    patch = FrictionPatch(mu=0.5, center=(10.0, 0.0), size=(40.0, 20.0), soil="toyoura")
    sim = RoverSim(flat_scenario(mu=1.0, patches=[patch]), renderer=renderer)
    try:
        sim.reset(0.0, 0.0, 0.0)
        g = sim.geometry
        sim.rover.command(np.full(4, 0.3 / g.wheel_radius), 0.0, 0.0)
        sim.step(3.0)
        rear = np.array([st[4] for st in sim.rover._read_wheels()])[2:]
        x = float(rear[:, 0].mean()) - 0.3
        ruts = sim.rover.ruts
        x0, y0, depth = ruts.surface(x, 0.0, 0.5)
        d = float(depth.max())
        assert d > 0.01  # a rut of a centimetre or more
        cam = PinholeCamera.from_fov((320, 240), math.radians(50.0), math.radians(38.0))
        sin_e = 0.5  # the sun 30 degrees up, from +y (across the tracks)
        light = Lighting((0.0, math.sqrt(1 - sin_e**2), sin_e), ambient=0.25, diffuse=1.0, shadows=False)
        r = focus_on_rover(sim)
        T = look_at((x, 0.0, 0.9), (x, 0.0, 0.0), up=(1.0, 0.0, 0.0))
        seen = r.render_pinhole(cam, T, light, far=5.0)
        r.ruts = None
        flat = r.render_pinhole(cam, T, light, far=5.0)
        ground = np.isin(seen.segmentation, r.ground_ids)
        a, b = seen.rgb.astype(float).mean(axis=2), flat.rgb.astype(float).mean(axis=2)
        y = seen.points_world[..., 1]
        near = np.zeros(ground.shape, bool)
        for yc in rear[:, 1]:
            near |= np.abs(y - yc) < 0.5 * g.wheel_width + 0.03
        # away from the tracks nothing changes
        assert ground[~near].sum() > 10_000 and np.array_equal(a[ground & ~near], b[ground & ~near])
        # at the tracks' edges: the shading of the slope's normal over the flat ground's
        ok = ground & near & (b > 40)
        ratio = a[ok] / b[ok]
        flat_shade = 0.25 + sin_e
        s = d / (2.0 * ruts.cell)  # the steepest slope the central difference reads
        n = np.array([0.0, s, 1.0]) / math.hypot(s, 1.0)
        brightest = (0.25 + float(n @ light.sun_direction)) / flat_shade
        darkest = 0.25 / flat_shade  # the wall away from the sun is in its own shade
        print(f"{renderer}: rut {1e3 * d:.1f} mm: ratios {ratio.min():.3f}..{ratio.max():.3f}, "
              f"predicted {darkest:.3f}..{brightest:.3f}")  # fmt: skip
        assert ratio.max() == pytest.approx(brightest, rel=0.05)
        assert ratio.min() == pytest.approx(darkest, rel=0.05)
        assert np.mean(np.abs(ratio - 1.0) > 0.05) > 0.1  # the walls are a good share of the band
    finally:
        sim.close()
