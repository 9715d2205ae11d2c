"""Terrain heights against Bullet's own ray casts, friction map, tiling textures."""

import contextlib

import numpy as np
import pybullet as pb
import pytest
from conftest import rough_scenario
from pybullet_utils.bullet_client import BulletClient

from rover_env.config.scenario import FrictionMapConfig, FrictionPatch, TerrainConfig
from rover_env.sim.terrain import FrictionMap, Terrain
from rover_env.sim.textures import ground_texture, tread_texture


@contextlib.contextmanager
def terrain_client(cfg: TerrainConfig):
    """A terrain alone in its own PyBullet client, disconnected afterwards: yields (client, terrain)."""
    client = BulletClient(connection_mode=pb.DIRECT)
    try:
        yield client, Terrain(client, cfg, FrictionMapConfig())
    finally:
        client.disconnect()


@pytest.mark.parametrize(
    "cfg",
    [
        rough_scenario().terrain,
        TerrainConfig(
            kind="flat",
            size=(20.0, 20.0),
            slope_deg=10.0,
            slope_azimuth_deg=30.0,
            texture="sand",
            texture_px=64,
        ),
        TerrainConfig(
            kind="rough",
            size=(12.0, 12.0),
            cell=0.1,
            roughness=0.03,
            slope_deg=8.0,
            texture="gravel",
            texture_px=64,
        ),
    ],
)
def test_height_at_matches_bullet_ray_casts(cfg):
    with terrain_client(cfg) as (client, terrain):
        rng = np.random.default_rng(0)
        pts = rng.uniform(-0.45, 0.45, (200, 2)) * np.array(cfg.size)
        starts = np.column_stack([pts, np.full(len(pts), 50.0)])
        ends = np.column_stack([pts, np.full(len(pts), -50.0)])
        hits = client.rayTestBatch(starts.tolist(), ends.tolist())
        z_ray = np.array([h[3][2] for h in hits])
        assert all(h[0] == terrain.body_id for h in hits)
        np.testing.assert_allclose(terrain.height_at(pts[:, 0], pts[:, 1]), z_ray, atol=1e-5)
        if cfg.roughness > 0:
            assert terrain.heights.std() > 0.5 * cfg.roughness


def test_rough_terrain_relief_statistics():
    from rover_env.sim.terrain import make_heights

    cfg = rough_scenario(roughness=0.04).terrain
    _, _, h = make_heights(cfg)
    assert h.std() == pytest.approx(0.04, rel=1e-6)
    slope = np.hypot(*np.gradient(h, cfg.cell))
    assert np.percentile(slope, 99) < np.tan(np.radians(25))  # drivable, wheels stay in contact


def test_friction_map_patches_override_in_order():
    fm = FrictionMap(
        FrictionMapConfig(
            default_mu=0.9,
            patches=(
                FrictionPatch(mu=0.2, center=(0.0, 0.0), size=(4.0, 2.0), yaw_deg=90.0),
                FrictionPatch(mu=0.5, center=(0.0, 1.5), shape="circle", radius=0.5),
            ),
        )
    )
    assert fm.mu_at(0.0, -1.8) == 0.2  # rotated rect: 4 m along y
    assert fm.mu_at(1.5, 0.0) == 0.9  # only 2 m along x after the 90 deg turn
    assert fm.mu_at(0.0, 1.5) == 0.5  # later patch wins
    xs, ys = np.meshgrid(np.linspace(-3, 3, 31), np.linspace(-3, 3, 31))
    grid = fm.mu_grid(xs, ys)
    assert np.array_equal(grid, np.vectorize(fm.mu_at)(xs, ys))


@pytest.mark.parametrize("name", ["regolith", "sand", "gravel", "concrete"])
def test_ground_textures_tile_without_seams_and_have_detail(name):
    img = ground_texture(name, px=256, seed=1).astype(np.float64).mean(axis=2)
    interior = np.abs(np.diff(img, axis=1)).mean()
    seam = np.abs(img[:, 0] - img[:, -1]).mean()
    assert seam < 1.5 * interior
    assert interior > 2.0  # pixel-scale detail for optical flow
    assert ground_texture(name, px=256, seed=1).tobytes() == ground_texture(name, px=256, seed=1).tobytes()


def test_tread_texture_has_a_white_marker_at_u_half():
    img = tread_texture(px_u=360, px_v=100, marker_arc=np.radians(16))
    tread = img[:75].mean(axis=(0, 2))
    white = np.where(tread > 240)[0]
    assert white.min() >= 180 - 9 and white.max() <= 180 + 9
    assert len(white) == pytest.approx(16, abs=2)


# a small rough terrain with a coarse texture, for rendering tests
SMALL_ROUGH = TerrainConfig(kind="rough", size=(12.0, 12.0), cell=0.1, roughness=0.03, wavelength=2.0, seed=3,
                            texture="sand", texture_px=64)  # fmt: skip


def test_rough_ground_is_drawn_exactly_near_the_focus_and_never_above_it_elsewhere():
    """Level of detail: the collision triangles near the rover, a lower 1 m mesh farther away."""
    from perception.models.cameras import PinholeCamera
    from rover_env.config.cameras import FINE_RADIUS
    from rover_env.rendering.base import Lighting, look_at
    from rover_env.rendering.tiny import TinyRenderer

    cfg = SMALL_ROUGH
    with terrain_client(cfg) as (client, terrain):
        renderer = TinyRenderer(client, terrain)
        detail = renderer.detail
        cam = PinholeCamera.from_fov((200, 200), np.radians(110.0), np.radians(110.0))
        T = look_at([1.3, -0.7, 2.5], [1.3, -0.7, 0.0], up=(1.0, 0.0, 0.0))
        light = Lighting((0.0, 0.0, 1.0), shadows=False)

        def ground_points():
            view = renderer.render_pinhole(cam, T, light, cull=False)
            p = view.points_world[np.isin(view.segmentation, detail.ground_ids)].astype(np.float64)
            return p, p[:, 2] - terrain.height_at(p[:, 0], p[:, 1])

        p, dz = ground_points()  # no focus yet: only the far mesh, which stays below the ground
        assert detail.ground_ids == (terrain.body_id,)
        assert dz.max() < 1e-3 and dz.min() > -0.2
        coarse_gap = np.median(dz)
        assert -0.06 < coarse_gap < -2e-3
        detail.focus(1.3, -0.7)
        n_near = len(detail.ground_ids) - 1
        assert 12 <= n_near <= (2 * FINE_RADIUS + 2) ** 2
        p, dz = ground_points()
        near = np.hypot(p[:, 0] - 1.3, p[:, 1] + 0.7) < FINE_RADIUS - 0.05
        assert near.sum() > 5000
        assert np.abs(dz[near]).max() < 2e-3  # the exact triangles (float32 depth)
        assert dz[~near].max() < 1e-3
        detail.focus(4.0, 4.0)  # moved: chunks near the old focus go, chunks near the new come
        assert len(detail.ground_ids) - 1 <= (2 * FINE_RADIUS + 2) ** 2
        _, dz = ground_points()
        assert np.median(dz) < -2e-3  # the view at (1.3, -0.7) sees the far mesh again
        detail.drop_detail()
        assert detail.ground_ids == (terrain.body_id,)


@pytest.mark.parametrize(
    "cfg",
    [
        TerrainConfig(
            kind="rough",
            size=(12.0, 12.0),
            cell=0.1,
            roughness=0.03,
            wavelength=2.0,
            seed=3,
            texture="sand",
            texture_px=64,
        ),  # fmt: skip
        TerrainConfig(
            kind="flat",
            size=(12.0, 12.0),
            slope_deg=6.0,
            slope_azimuth_deg=30.0,
            texture="gravel",
            texture_px=64,
        ),  # fmt: skip
    ],
)
def test_near_focus_draws_the_same_ground_within_range_and_nothing_beyond(cfg):
    """focus(near=r): only ground within r is drawn, and it is the ground the full scene draws there."""
    from perception.models.cameras import PinholeCamera
    from rover_env.rendering.base import Lighting, look_at
    from rover_env.rendering.tiny import TinyRenderer
    from rover_env.sim.terrain import FINE_CHUNK

    with terrain_client(cfg) as (client, terrain):
        renderer = TinyRenderer(client, terrain)
        detail = renderer.detail
        # an oblique view from near the focus that sees the ground far beyond the range
        cam = PinholeCamera.from_fov((160, 120), np.radians(90.0), np.radians(70.0))
        x, y, r = 1.3, -0.7, 1.0
        z = float(terrain.height_at(x, y)) + 0.4
        T = look_at([x, y, z], [x + 3.0, y + 1.0, z - 1.2])
        light = Lighting((0.3, 0.2, 1.0), shadows=False)
        detail.focus(x, y)
        full = renderer.render_pinhole(cam, T, light, cull=False)
        detail.focus(x, y, near=r)
        near = renderer.render_pinhole(cam, T, light, cull=False)
        p = full.points_world.astype(np.float64)
        hit = full.segmentation >= 0
        dist = np.hypot(p[..., 0] - x, p[..., 1] - y)
        # whole chunks are drawn: all ground within r, none beyond r + a chunk's diagonal
        inside, beyond = hit & (dist < r - 0.05), hit & (dist > r + np.sqrt(2) * FINE_CHUNK + 0.05)
        assert inside.sum() > 3000 and beyond.sum() > 1000
        same = np.all(near.rgb == full.rgb, axis=-1)
        assert same[inside].mean() > 0.99  # chunk seams may rasterise a pixel differently
        assert np.all(near.segmentation[beyond] < 0)  # not drawn: the background shows
        detail.focus(x, y)  # full again: everything is back, exactly
        again = renderer.render_pinhole(cam, T, light, cull=False)
        assert np.array_equal(again.rgb, full.rgb)
        with pytest.raises(ValueError, match="near"):
            detail.focus(x, y, near=5.0)
        detail.drop_detail()
        assert detail.ground_ids == (terrain.body_id,)


def test_culling_chunks_outside_a_view_leaves_its_image_unchanged():
    """GroundDetail.cull hides the exact chunks a view cannot see; the image stays the same, to the pixel."""
    from perception.models.cameras import PinholeCamera
    from rover_env.rendering.base import Lighting, look_at
    from rover_env.rendering.tiny import TinyRenderer

    cfg = SMALL_ROUGH
    with terrain_client(cfg) as (client, terrain):
        renderer = TinyRenderer(client, terrain)
        detail = renderer.detail
        cam = PinholeCamera.from_fov((160, 120), np.radians(77.0), np.radians(57.0))
        light = Lighting((0.3, 0.2, 1.0), shadows=False)
        x, y = 0.4, -0.3
        eye = [x, y, float(terrain.height_at(x, y)) + 0.8]

        def drawn() -> int:
            return sum(detail._shown[b] for b in detail._chunks.values())

        # ahead, oblique, straight down
        for target, up in (([x + 1.0, y, 0.0], (0, 0, 1)), ([x + 1.5, y + 1.2, 0.2], (0, 0, 1)),
                           ([x, y, 0.0], (1, 0, 0))):  # fmt: skip
            T = look_at(eye, target, up=up)
            detail.focus(x, y, near=2.0)
            before = drawn()
            full = renderer.render_pinhole(cam, T, light, cull=False)
            culled = renderer.render_pinhole(cam, T, light, cull=True)
            kept = drawn()
            assert np.array_equal(culled.rgb, full.rgb) and np.array_equal(culled.depth, full.depth)
            assert kept < before / 2, (kept, before)
