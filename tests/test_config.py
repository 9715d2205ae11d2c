"""Scenario files, geometry and configuration validation (no simulator)."""

import math

import numpy as np
import pytest

from rover_env import ConfigError, RoverGeometry, list_scenarios, load_scenario
from rover_env.sim.rover import axle_steering_from_wheels
from rover_env.task.course import WaypointCourse


def test_presets_load_and_cover_the_required_cases():
    names = list_scenarios()
    assert len(names) >= 4
    cfgs = [load_scenario(n) for n in names]
    assert any(c.terrain.kind == "rough" for c in cfgs)
    low = [c for c in cfgs if any(p.mu <= 0.3 for p in c.friction.patches)]
    assert low, "no preset with low-friction patches"
    # the patch lies on the course of at least one preset
    from rover_env.sim.terrain import FrictionMap

    def on_course(c):
        pts = np.vstack([c.start.position, c.course.waypoints])
        fm = FrictionMap(c.friction)
        for a, b in zip(pts[:-1], pts[1:]):
            for t in np.linspace(0, 1, 200):
                p = a + t * (b - a)
                if fm.mu_at(*p) <= 0.3:
                    return True
        return False

    assert any(on_course(c) for c in low)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (
            "name: x\ncourse: {waypoints: [[1, 0]]}\nsun: {azimuth_deg: 1, elevaton_deg: 5}\n",
            "unknown key 'sun.elevaton_deg'",
        ),
        ("name: x\n", "missing required key 'course'"),
        ("name: x\ncourse: {waypoints: [[1, 0]]}\nduration: fast\n", "duration: expected a number"),
        (
            "name: x\ncourse: {waypoints: [[1, 0]]}\nfriction: {default_mu: 3.0}\n",
            "friction.default_mu: 3.0 is out of range",
        ),
        (
            "name: x\ncourse: {waypoints: [[1, 0]]}\nfriction: {patches: [{mu: 0.2}]}\n",
            "missing required key 'friction.patches[0].center'",
        ),
        ("name: x\ncourse: {waypoints: [[100, 0]]}\n", "course.waypoints[0]"),
        ("name: x\ncourse: {waypoints: [[1, 0]]}\nterrain: {texture: nothere.png}\n", "neither a preset"),
        (
            "name: x\ncourse: {waypoints: [[1, 0]]}\nterrain: {kind: bumpy}\n",
            "terrain.kind: 'bumpy' is not one of",
        ),
        ("name: [x\n", "not valid YAML"),
    ],
)
def test_bad_scenario_files_name_file_and_key(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    assert str(path) in str(err.value)
    assert needle in str(err.value)


def test_missing_file_and_unknown_preset():
    with pytest.raises(ConfigError, match="file not found"):
        load_scenario("/nonexistent/scenario.yaml")
    with pytest.raises(ConfigError, match="presets: "):
        load_scenario("atlantis")


def test_user_texture_path_is_resolved_relative_to_the_file(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "ground.png"), np.full((32, 32, 3), 128, np.uint8))
    path = tmp_path / "s.yaml"
    path.write_text("name: x\ncourse: {waypoints: [[1, 0]]}\nterrain: {texture: ground.png}\n")
    assert load_scenario(path).terrain.texture == str(tmp_path / "ground.png")


def test_geometry_validation():
    with pytest.raises(ConfigError, match="wheel_radius"):
        RoverGeometry(wheel_radius=-0.1)
    with pytest.raises(ConfigError, match="steer_limit"):
        RoverGeometry(steer_limit=math.radians(59))
    # camera mounts
    with pytest.raises(ConfigError, match="fisheye_origin: .* not under the body"):
        RoverGeometry(fisheye_origin=(0.6, 0.0, -0.12))
    with pytest.raises(ConfigError, match=r"fisheye_origin\[2\]"):
        RoverGeometry(fisheye_origin=(0.0, 0.0, 0.05))  # inside the body
    with pytest.raises(ConfigError, match=r"mast_camera_position\[0\]"):
        RoverGeometry(mast_camera_position=(0.2, 0.0, 0.535))  # above the body, not the ground
    with pytest.raises(ConfigError, match=r"mast_camera_position\[2\]"):
        RoverGeometry(mast_camera_position=(0.95, 0.0, 0.05))


@pytest.mark.parametrize("lam_deg", [-30.0, -12.0, 5.0, 30.0])
def test_ackermann_wheels_share_one_turn_centre(lam_deg):
    g = RoverGeometry()
    lam = math.radians(lam_deg)
    delta = g.ackermann_angles(lam, -lam)
    radius = g.turning_radius(lam) * np.sign(lam)  # ICR at (0, R)
    icr = np.array([0.0, radius])
    for (x, y, _), d in zip(g.wheel_positions_body(), delta):
        heading = np.array([math.cos(d), math.sin(d)])
        # the wheel heading is perpendicular to the ray from the ICR to the wheel
        assert heading @ (np.array([x, y]) - icr) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(axle_steering_from_wheels(g, delta), [lam, -lam], atol=1e-12)
    speeds = g.drive.wheel_speeds(1.0, lam, -lam)
    dists = np.linalg.norm(g.wheel_positions_body()[:, :2] - icr, axis=1)
    np.testing.assert_allclose(speeds, dists / abs(radius), rtol=1e-12)


def test_fiducials_are_complete_and_symmetric():
    g = RoverGeometry()
    names = {f.name for f in g.fiducials()}
    assert names == {"A1", "A2", "B1", "B2", "C1", "C2", "D1", "D2", "W_FL", "W_FR", "W_RL", "W_RR"}
    a1, a2 = g.fiducial("A1"), g.fiducial("A2")
    assert a1.position[1] == -a2.position[1] > 0
    assert a1.position[2] == 0.0  # on the roll axis height: stays in the axle's plane
    b1 = np.array(g.fiducial("B1").position)
    assert b1[0] < 0 and b1[1] < 0  # front tie-rod end behind and inside the kingpin
    assert np.hypot(b1[0], b1[1]) == pytest.approx(g.steering_arm_length)
    assert b1[2] == -g.tie_rod_drop  # the tie-rod plane lies below the beam


def test_course_features_and_progress():
    from rover_env.config.scenario import CourseConfig

    course = WaypointCourse(CourseConfig(waypoints=((10.0, 0.0), (10.0, 10.0)), tolerance=0.5))
    course.reset(np.array([0.0, 0.0]))
    f = course.features(np.array([4.0, 1.0]), math.pi / 2)
    assert f.progress == pytest.approx(4.0)
    assert f.cross_track == pytest.approx(1.0)
    assert f.heading_error == pytest.approx(-math.pi / 2)
    assert f.distance == pytest.approx(math.hypot(6.0, 1.0))
    assert f.bearing == pytest.approx(math.atan2(-1.0, 6.0) - math.pi / 2)
    assert course.update(np.array([9.7, 0.2]))
    assert course.index == 1
    f = course.features(np.array([9.0, 3.0]), 0.0)
    assert f.progress == pytest.approx(13.0)
    assert f.cross_track == pytest.approx(1.0)
