"""Domain randomisation: each episode's world drawn from its seed, within documented ranges."""

from __future__ import annotations

import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest
from conftest import flat_scenario

import rover_env  # noqa: F401
from rover_env.config.io import ConfigError
from rover_env.config.randomize import TEXTURE_BANK, RandomizeConfig, WorldDraw, randomize_config, range_keys
from rover_env.config.scenario import load_scenario
from rover_env.rendering.gl import gl_status
from rover_env.sensors.cameras import DownwardCamera
from rover_env.sim.simulation import RoverSim
from rover_env.sim.textures import texture_file


def test_draws_stay_within_their_ranges_and_fixed_ranges_fix_the_value():
    cfg = RandomizeConfig()
    rng = np.random.default_rng(0)
    draws = [WorldDraw.draw(cfg, rng, cameras=2) for _ in range(300)]
    for key in range_keys():
        lo, hi = getattr(cfg, key)
        values = []
        for d in draws:
            v = getattr(d, key, None)
            if key == "mount_rotation_deg":
                values += [math.degrees(a) for m in d.mounts for a in m[:3]]
            elif key == "mount_offset_m":
                values += [a for m in d.mounts for a in m[3:]]
            else:
                values += list(v) if isinstance(v, tuple) else [v]
        values = np.array(values)
        assert lo <= values.min() and values.max() <= hi, key
        assert values.max() - values.min() > 0.8 * (hi - lo), key  # the range is covered
    assert {d.texture for d in draws} == set(TEXTURE_BANK)
    fixed = RandomizeConfig(friction=(0.9, 0.9), textures=("sand",))
    assert {WorldDraw.draw(fixed, rng, 1).friction for _ in range(5)} == {0.9}
    # the world's draws come before the cameras': the same world however many cameras observe it
    a = WorldDraw.draw(cfg, np.random.default_rng(5), 0)
    b = WorldDraw.draw(cfg, np.random.default_rng(5), 2)
    assert (a.friction, a.sun_azimuth_deg, a.texture) == (b.friction, b.sun_azimuth_deg, b.texture)


@pytest.mark.parametrize(
    "value, message",
    [
        ({"friction": (1.2, 0.8)}, "randomize.friction: .* minimum above its maximum"),
        ({"sun_elevation_deg": (-5, 30)}, "randomize.sun_elevation_deg"),
        ({"textures": ["marble"]}, r"randomize.textures\[0\]"),
        ({"albedo": (0.9,)}, "randomize.albedo"),
        ({"windiness": (0, 1)}, "windiness"),
        ("sometimes", "randomize: 'sometimes'"),
        ({"friction": 1.0}, "randomize.friction"),
    ],
)
def test_a_bad_randomisation_is_a_config_error_naming_the_key(value, message):
    with pytest.raises(ConfigError, match=message):
        randomize_config(value)
    if isinstance(value, dict) and "windiness" not in value:  # built directly, too
        with pytest.raises(ConfigError, match=message):
            RandomizeConfig(**value)
    with pytest.raises(ConfigError, match=message.split(":")[0].split(" ")[0]):
        dataclasses.replace(load_scenario("flat_patches"), randomize=value)


def test_off_keeps_todays_worlds_and_a_seed_gives_one_world_whatever_observes_it():
    act = np.array([0.7, 0.2, 0.0], np.float32)

    def run(seed, **kw):
        env = gym.make("RoverSlopeLoose-v0", renderer="tiny", **kw)
        try:
            _, info = env.reset(seed=seed)
            for _ in range(15):
                obs, _, _, _, step_info = env.step(act)
            images = (
                {k: v.copy() for k, v in env.unwrapped.pipeline.last_images.items()}
                if env.unwrapped.pipeline is not None
                else {}
            )
            return obs, np.array(step_info["ground_truth"]["pose"]), info.get("world"), images
        finally:
            env.close()

    o_default, p_default, w_default, _ = run(3)
    o_off, p_off, w_off, _ = run(3, randomize="off")
    assert w_default is None and w_off is None
    np.testing.assert_array_equal(o_default, o_off)
    np.testing.assert_array_equal(p_default, p_off)
    o1, p1, w1, im1 = run(3, randomize="on", camera_effects="field")
    o1b, p1b, w1b, im1b = run(3, randomize="on", camera_effects="field")
    _, p_gt, w_gt, _ = run(3, randomize="on", obs_source="ground_truth")
    _, _, w2, _ = run(4, randomize="on")
    assert w1 == w1b and w1 != w2
    np.testing.assert_array_equal(o1, o1b)
    assert all(np.array_equal(im1[k], im1b[k]) for k in im1)
    np.testing.assert_array_equal(p1, p_gt)  # the same physics whatever observes it
    assert w_gt["friction"] == w1["friction"] and w_gt["mounts"] == ()
    assert not np.array_equal(p1, p_off)  # another friction factor: another drive


def test_the_drawn_world_reaches_the_simulation_and_the_estimator_keeps_the_nominal_mounts():
    env = gym.make(
        "Rover-v0", renderer="tiny", randomize={"friction": (1.3, 1.3), "mount_rotation_deg": (0.4, 0.4)}
    )
    try:
        _, info = env.reset(seed=8)
        u = env.unwrapped
        w = info["world"]
        assert u.sim.terrain.friction.scale == 1.3
        assert u.sim.terrain.friction.mu_at(0.0, 50.0) == pytest.approx(1.3 * u.scenario.friction.default_mu)
        assert u.sim.scenario.sun.elevation_deg == w["sun_elevation_deg"]
        tcfg = u.scenario.terrain
        assert u.sim.terrain.texture_path == texture_file(w["texture"], tcfg.texture_px, tcfg.seed)
        for cam in u.pipeline.cameras:
            spec = next(s for s in u.rig.values() if np.allclose(s.mount, cam.T_body_cam))
            true = np.linalg.inv(u.sim.base_matrix()) @ cam.T_world_cam()
            dR = np.linalg.inv(spec.mount)[:3, :3] @ true[:3, :3]
            angle = math.degrees(np.arccos((np.trace(dR) - 1) / 2))
            assert angle == pytest.approx(math.sqrt(3) * 0.4, abs=1e-6)  # 0.4 deg about each axis
        env.reset(seed=8, options=None)
        env.unwrapped.randomize = None
        env.reset(seed=8)
        assert u.sim.terrain.friction.scale == 1.0
        assert not np.any(u.pipeline.cameras[0].mount_error - np.eye(4))
    finally:
        env.close()


@pytest.mark.skipif(not gl_status()[0], reason=f"no OpenGL context here: {gl_status()[1]}")
def test_the_grounds_albedo_and_contrast_scale_its_image():
    """Ground seen by the downward camera (no sun, sky light only): mean x albedo, spread x contrast."""
    sim = RoverSim(flat_scenario(), renderer="gl")
    try:
        sim.reset(0.0, 0.0, 0.0)
        cam = DownwardCamera(sim)
        sim.ambient, sim.haze = 0.5, 0.0  # no direct sun: no shadow, even light

        def ground(albedo, contrast):
            sim.terrain.set_look("gravel", albedo, contrast)
            img = cam.capture().image.astype(np.float64).mean(axis=2)
            return img[20:-20, 20:-20]

        base, bright, flat = ground(1.0, 1.0), ground(1.2, 1.0), ground(1.0, 0.5)
        assert bright.mean() / base.mean() == pytest.approx(1.2, rel=0.02)
        assert flat.std() / base.std() == pytest.approx(0.5, rel=0.05)
        assert flat.mean() == pytest.approx(base.mean(), rel=0.02)
    finally:
        sim.close()


def test_tinyrenderer_draws_the_drawn_albedo_on_the_near_ground():
    """The cameras' near ground is TinyRenderer's detail chunks: they carry the ground's albedo."""
    # the images as rendered (a field camera's auto-exposure would bring both to its target)
    kw = {"renderer": "tiny", "camera_effects": "ideal"}
    env = gym.make("Rover-v0", **kw, randomize={"albedo": (0.5, 0.5), "textures": ("concrete",)})
    off = gym.make("Rover-v0", **kw, randomize={"albedo": (1.0, 1.0), "textures": ("concrete",)})
    try:
        means = []
        for e in (env, off):
            e.reset(seed=5)
            e.step(np.zeros(3, np.float32))
            means.append(float(e.unwrapped.pipeline.last_images["downward"].mean()))
        print(f"downward image mean at albedo 0.5: {means[0]:.1f}, at 1: {means[1]:.1f}")
        assert means[0] / means[1] == pytest.approx(0.5, abs=0.06)
    finally:
        env.close()
        off.close()
