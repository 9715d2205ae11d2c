"""Physics on deformable soil against rigid ground, side by side, and memory over many resets.

    python benchmarks/soil_speed.py [--soil toyoura] [--blocks 8] [--resets 2000]

Two simulations of the same rover in one process, one thread: rigid flat ground, and the same
ground under a soil patch (all four wheels on soil, ruts on). Both drive at 0.4 m/s; blocks of
480 physics substeps alternate between them and the medians are compared. Then one soil
simulation is reset ``--resets`` times (a short drive after each) and its resident memory is
sampled: the rut map and the soil state are fixed in size, so it must not grow.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from conftest import flat_scenario  # noqa: E402

from rover_env.config.scenario import FrictionPatch  # noqa: E402
from rover_env.sim.simulation import RoverSim  # noqa: E402


def _sim(soil: str | None) -> RoverSim:
    patches = []
    if soil is not None:
        patches = [FrictionPatch(mu=0.5, center=(10.0, 0.0), size=(40.0, 20.0), soil=soil)]
    sim = RoverSim(flat_scenario(mu=1.0, patches=patches))
    sim.reset(0.0, 0.0, 0.0)
    sim.rover.command(np.full(4, 0.4 / sim.geometry.wheel_radius), 0.0, 0.0)
    return sim


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--soil", default="toyoura")
    ap.add_argument("--blocks", type=int, default=8, help="alternating blocks of 480 substeps each")
    ap.add_argument("--resets", type=int, default=2000)
    args = ap.parse_args(argv)
    sims = {"rigid": _sim(None), "soil": _sim(args.soil)}
    for sim in sims.values():
        sim.step(1.0)  # warm up (and compile)
    times: dict[str, list[float]] = {k: [] for k in sims}
    for _ in range(args.blocks):
        for name, sim in sims.items():
            t0 = time.perf_counter()
            for _ in range(480):
                sim.step(1 / 240)
            times[name].append((time.perf_counter() - t0) / 480 * 1e6)
    rigid, soil = np.median(times["rigid"]), np.median(times["soil"])
    print(f"| ground | us per substep (median of {args.blocks} blocks of 480) | steps/s |")
    print("|---|---:|---:|")
    print(f"| rigid | {rigid:.0f} | {1e6 / rigid:.0f} |")
    print(f"| soil ({args.soil}, ruts) | {soil:.0f} | {1e6 / soil:.0f} |")
    print(f"\nsoil / rigid steps per second: {rigid / soil:.2f}")
    sims["rigid"].close()
    sim = sims["soil"]
    rss = []
    for k in range(args.resets):
        sim.reset(float(k % 7), 0.0, 0.0)
        sim.rover.command(np.full(4, 0.4 / sim.geometry.wheel_radius), 0.0, 0.0)
        sim.step(0.05)
        if k % max(1, args.resets // 10) == 0 or k == args.resets - 1:
            rss.append((k + 1, _rss_mb()))
    sim.close()
    print(f"\nresident memory over {args.resets} resets of the soil simulation [MB]:")
    print(" ".join(f"{k}: {m:.0f}" for k, m in rss))
    print(f"growth from the second sample to the last: {rss[-1][1] - rss[1][1]:+.1f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
