import os
import tempfile

import pytest

# Generated assets (textures, meshes, URDFs) go to a per-session cache, not the user's home.
os.environ.setdefault("ROVER_CACHE_DIR", os.path.join(tempfile.gettempdir(), "rover_env_test"))

from rover_env.config.scenario import (  # noqa: E402
    CourseConfig,
    FrictionMapConfig,
    ScenarioConfig,
    TerrainConfig,
)


def flat_scenario(mu: float = 1.0, patches=(), size=(60.0, 60.0)) -> ScenarioConfig:
    return ScenarioConfig(
        name="test_flat",
        course=CourseConfig(waypoints=((20.0, 0.0),)),
        terrain=TerrainConfig(kind="flat", size=size, texture="concrete", texture_px=64),
        friction=FrictionMapConfig(default_mu=mu, patches=tuple(patches)),
    )


def rough_scenario(roughness=0.04, wavelength=1.5, seed=3) -> ScenarioConfig:
    return ScenarioConfig(
        name="test_rough",
        course=CourseConfig(waypoints=((10.0, 0.0),)),
        terrain=TerrainConfig(
            kind="rough",
            size=(30.0, 30.0),
            cell=0.1,
            roughness=roughness,
            wavelength=wavelength,
            seed=seed,
            texture="regolith",
            texture_px=64,
        ),
        friction=FrictionMapConfig(default_mu=1.0),
    )


TINY_SCENARIO = (
    "name: tiny\n"
    "course: {waypoints: [[2.5, 0.0], [3.5, 1.0]], tolerance: 0.5, speed: 0.8}\n"
    "terrain: {kind: flat, size: [12.0, 12.0], texture: gravel, texture_px: 128}\n"
    "friction: {patches: [{center: [1.5, 0.0], size: [1.0, 2.0], mu: 0.15}]}\n"
    "start: {jitter_position: 0.2, jitter_yaw_deg: 5.0}\n"
    "duration: 12.0\n"
)


@pytest.fixture
def tiny_scenario(tmp_path) -> str:
    """A 4 m course over a small flat terrain with a mu 0.15 patch, as a YAML path."""
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY_SCENARIO)
    return str(path)
