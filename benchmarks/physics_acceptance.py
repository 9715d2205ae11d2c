"""Print the rover-world acceptance numbers (the tests assert the same quantities).

Run: python benchmarks/physics_acceptance.py
"""

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from conftest import flat_scenario, rough_scenario  # noqa: E402
from test_physics import drive, drive_slalom_integrating_twist, fit_circle  # noqa: E402

from rover_env.config.scenario import FrictionPatch  # noqa: E402
from rover_env.sim.simulation import RoverSim  # noqa: E402

sim = RoverSim(flat_scenario(mu=1.0))
sim.reset(0.0, 0.0, 0.0)
drive(sim, 1.0, 0.0, 0.0)
sim.step(1.5)
worst = max(float(np.abs((sim.step(1 / 30), sim.ground_truth())[1].slip_ratio).max()) for _ in range(60))
print(f"constant 1 m/s, mu 1.0: max |slip ratio| over 2 s = {worst:.4f}")
for deg in (10.0, 20.0):
    lam = math.radians(deg)
    sim.reset(10.0, 10.0, 0.0)
    drive(sim, 0.3, lam, -lam)
    sim.step(2.0)
    pts = np.array([(sim.step(1 / 30), sim.ground_truth().pose[:2])[1] for _ in range(240)])
    _, r, rms = fit_circle(pts)
    exp = sim.geometry.turning_radius(lam)
    print(
        f"turn lambda={deg:.0f} deg: radius {r:.4f} m vs geometry {exp:.4f} m "
        f"({100 * (r / exp - 1):+.2f} %), circle-fit RMS residual {1000 * rms:.2f} mm"
    )
sim.close()

patch = FrictionPatch(mu=0.1, center=(1.95, 0.0), size=(3.0, 4.0))
sim = RoverSim(flat_scenario(mu=1.0, patches=[patch]))
sim.reset(0.0, 0.0, 0.0)
drive(sim, 2.0, 0.0, 0.0)
best = None
for _ in range(120):
    sim.step(1 / 240)
    gt = sim.ground_truth()
    on = np.isclose(gt.friction, 0.1)
    if on[:2].all() and not on[2:].any():
        if best is None or gt.slip_ratio[:2].min() > best.slip_ratio[:2].min():
            best = gt
print(
    f"mu 0.1 patch under the front wheels, full drive: slip FL FR RL RR = "
    f"{np.round(best.slip_ratio, 3).tolist()} at t = {best.t:.3f} s"
)
sim.close()

sim = RoverSim(rough_scenario())
gt = sim.reset(-8.0, 0.0, 0.0)
drive(sim, 0.5, 0.0, 0.0)
psi, dh = [], []
for _ in range(450):
    sim.step(1 / 30)
    gt = sim.ground_truth()
    rot = np.array(sim.client.getMatrixFromQuaternion(gt.pose[3:].tolist())).reshape(3, 3)
    c = np.array([s[4] for s in sim.client.getLinkStates(sim.rover.body_id, sim.rover.wheel_links)])
    z = (np.column_stack([c[:, :2], sim.terrain.height_at(c[:, 0], c[:, 1])]) - gt.pose[:3]) @ rot
    psi.append(gt.axle_roll.copy())
    dh.append([z[0, 2] - z[1, 2], z[2, 2] - z[3, 2]])
psi, dh = np.array(psi), np.array(dh)
for k, name in enumerate("FR"):
    print(
        f"rough terrain, axle {name}: corr(psi, height difference) = "
        f"{np.corrcoef(psi[:, k], dh[:, k])[0, 1]:.3f}, max |psi| = "
        f"{math.degrees(np.abs(psi[:, k]).max()):.1f} deg"
    )
sim.close()

# integrated body twist against the true pose over a 20 m slalom
sim = RoverSim(flat_scenario(mu=1.0))
err, dist, _, _ = drive_slalom_integrating_twist(sim)
print(
    f"twist integrated at 30 Hz over {dist:.1f} m: end-point error {100 * err:.2f} cm "
    f"({100 * err / dist:.3f} % of distance)"
)
sim.close()
