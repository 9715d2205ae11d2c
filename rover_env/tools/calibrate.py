"""Calibration routines that run in the simulator and write files the estimators read.

``sweep_steering`` is the kinematics paper's steering calibration: the axles are steered through
a range of angles, the fisheye image of each pose gives the tie-rod distance ratio of eq. (5), and
the (ratio, lambda) table becomes a :class:`perception.kinematics.markers.SteeringCalibration`.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from perception.kinematics.markers import (
    MarkerConfig,
    SteeringCalibration,
    assign_markers,
    measure_axles,
    segment_magenta,
    steering_ratio,
)
from rover_env.config.cameras import FisheyeCameraConfig
from rover_env.sensors.cameras import FisheyeCamera
from rover_env.sim.geometry import AXLES, WHEELS
from rover_env.sim.simulation import RoverSim

log = logging.getLogger(__name__)


def sweep_steering(
    sim: RoverSim,
    limit_deg: float = 24.0,
    steps: int = 49,
    camera: FisheyeCamera | None = None,
    markers: MarkerConfig | None = None,
) -> SteeringCalibration:
    """Steer both axles through +-``limit_deg`` and fit lambda against the distance ratio (eq. 5).

    The rover is lifted clear of the ground and its steering joints are set directly (roll and
    travel at rest), as a calibration stand would hold it; the ratio is measured in the rendered
    fisheye image exactly as the estimator measures it.

    Args:
        sim: The simulation (its rover is moved; reset it afterwards).
        limit_deg: Largest axle steering of the sweep [deg]; the ratio must stay monotonic.
        steps: Poses in the sweep.
        camera: The fisheye (default: 640x480, no shadows).
        markers: Marker segmentation.

    Raises:
        RuntimeError: A pose where the 8 markers were not all found.
        CalibrationError: The ratio is not monotonic over the sweep.
    """
    cam = camera or FisheyeCamera(sim, FisheyeCameraConfig(shadows=False))
    cfg = markers or MarkerConfig()
    g = sim.geometry
    model = g.kinematic_model(cam.T_body_cam)
    sim.hold_on_stand(0.1, {f"{j}_{a}": 0.0 for a in AXLES for j in ("roll", "travel")})
    depth = np.full(2, -g.axle_z)
    T_cb = np.linalg.inv(model.T_body_cam)
    lams = np.radians(np.linspace(-limit_deg, limit_deg, steps))
    ratios = np.zeros((2, steps))
    for n, lam in enumerate(lams):
        delta = g.ackermann_angles(lam, lam)
        sim.hold_on_stand(0.0, {f"steer_{w}": delta[k] for k, w in enumerate(WHEELS)})
        cent, _, _ = segment_magenta(cam.capture().image, cfg)
        pred = model.marker_positions((0.0, 0.0), depth, delta)
        pix = {m: cam.model.world2cam(T_cb[:3, :3] @ p + T_cb[:3, 3]) for m, p in pred.items()}
        found = assign_markers(pix, cent, cfg.gate_frac * cam.model.image_size[0])
        if len(found) < 8:
            raise RuntimeError(
                f"steering sweep: at lambda = {math.degrees(lam):.1f} deg only {sorted(found)} found"
            )
        meas = measure_axles(model, cam.model, {m: cent[j] for m, j in found.items()}, (0.0, 0.0), depth)
        p = meas.points
        ratios[0, n] = steering_ratio(p["A1"], p["A2"], p["B1"], p["B2"])
        ratios[1, n] = steering_ratio(p["C1"], p["C2"], p["D1"], p["D2"])
    log.info("steering sweep: %d poses over +-%.1f deg", steps, limit_deg)
    return SteeringCalibration.fit(ratios, [lams, lams])


def write_steering_calibration(path: str | Path, sim: RoverSim, **kwargs) -> Path:
    """Run :func:`sweep_steering` and save the table to ``path`` (YAML)."""
    return sweep_steering(sim, **kwargs).save(path)
