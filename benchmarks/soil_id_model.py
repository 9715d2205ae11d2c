"""The soil identification's per-wheel model, fitted to the Wong-Reece model's steady states.

``perception.fusion.soil`` takes a wheel's drawbar pull over load as

    DP / W = (1 - eps) T / (r W) - a z / r

(T its torque, W its load, z its sinkage, r its radius), ``eps`` one figure for all soils and
``a`` the soil's, identified on board. This fits ``eps`` (driving and braking apart) and each
soil's ``a`` to the steady states of the rover's wheel (r = 0.115 m, b = 0.08 m) on five soil
presets, loads 70-140 N, and prints the fit's error per soil; with ``--power`` the relative
sinkage's exponent is fitted too (z / r)^p, which comes out close to 1.

Run: python benchmarks/soil_id_model.py [--power]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import least_squares

from rover_env.config.soil import load_soil
from rover_env.sim.geometry import RoverGeometry
from rover_env.sim.terramechanics import WheelSpec, steady_state

SOILS = ("cmu_testbed_smooth", "toyoura", "lunar_regolith", "dry_sand", "mars_simulant")
LOADS = (70.0, 90.0, 104.0, 120.0, 140.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--power", action="store_true", help="fit the sinkage's exponent too")
    args = ap.parse_args(argv)
    g = RoverGeometry()
    wheel = WheelSpec(radius=g.wheel_radius, width=g.wheel_width)
    r = wheel.radius
    for label, slips in (("driving", np.linspace(0.02, 0.8, 21)), ("braking", np.linspace(-0.6, -0.03, 15))):
        data = {}
        for name in SOILS:
            L, S = np.meshgrid(LOADS, slips, indexing="ij")
            ss = steady_state(load_soil(name), wheel, L, S, n_theta=48)
            data[name] = (
                (ss.torque / (r * L)).ravel(),
                (ss.drawbar_pull / L).ravel(),
                (ss.sinkage / r).ravel(),
            )

        def residual(p, data=data):
            eps, power = p[0], (p[1] if args.power else 1.0)
            a = p[2:] if args.power else p[1:]
            return np.concatenate(
                [(1 - eps) * t - ak * z**power - d for ak, (t, d, z) in zip(a, data.values(), strict=True)]
            )

        start = [0.1, 1.0] if args.power else [0.1]
        fit = least_squares(residual, start + [0.5] * len(SOILS))
        p = fit.x
        res = residual(p).reshape(len(SOILS), -1)
        a = p[2:] if args.power else p[1:]
        head = f"{label}: eps = {p[0]:.3f}" + (f", sinkage exponent {p[1]:.2f}" if args.power else "")
        print(head + f" (slips {slips[0]:.2f} to {slips[-1]:.2f}, loads {LOADS[0]:.0f}-{LOADS[-1]:.0f} N)")
        print("| soil | a | DP/W error rms | max |")
        print("|---|---:|---:|---:|")
        for name, ak, e in zip(SOILS, a, res, strict=True):
            print(f"| {name} | {ak:.3f} | {np.sqrt(np.mean(e**2)):.4f} | {np.abs(e).max():.4f} |")
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
