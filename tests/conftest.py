import os
import tempfile

# Generated assets (textures, meshes, URDFs) go to a per-session cache, not the user's home.
os.environ.setdefault("ROVER_CACHE_DIR", os.path.join(tempfile.gettempdir(), "rover_env_test"))

from rover_env.scenario import (  # noqa: E402
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
