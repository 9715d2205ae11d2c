"""Fit the slip-sinkage coefficients of the test-bed soils to the wheel's own steady state.

Pavlov and Johnson fitted their stress-shape coefficients (a0, a1, b0, b1; Ishigami's
theta_m and theta_r laws) to the forces their model gives *at the measured sinkage*. That fit
does not make the model carry the load there: solved for the sinkage that carries each measured
load, their coefficients sink the wheels up to 36 % (grousered, light braking) and 69 % (smooth,
90 % slip) deeper than measured. This script refits, per wheel, the coefficients of the
slip-sinkage law (a0, a1, b0, b1, n_slip, n_skid) to the steady state the simulation uses:
the sinkage solved for the measured load, and the drawbar pull there. The soil's own
parameters (k, n0, c, phi, K, from plate and shear tests) stay Pavlov and Johnson's.

Objective (Nelder-Mead from their coefficients), over the slip-angle-0 means:
sum over slips -0.5..0.9 of (DP/W error / 0.05)^2 + (sinkage relative error / 0.25)^2, plus
half of the sinkage term at the locked and nearly locked slips (-1, -0.7), whose drawbar pull
(bulldozing) the model does not capture. The same is done for each ``--powers`` of the skid
law, ``n = n0 + n_skid |s|^p``; the slip-angle-15 degree means are held out of the fit and
reported as a check.

    python benchmarks/wheel_fit.py [--powers 1 1.5 2]

Prints, per power and wheel, the coefficients and the errors at slip angles 0 and 15 degrees.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from rover_env.config.soil import load_soil
from rover_env.sim.terramechanics import steady_state

try:  # run as a script (python benchmarks/wheel_fit.py) or imported from the repository root
    from wheel_validation import SCORED, WHEELS, load_rows
except ImportError:  # pragma: no cover
    from benchmarks.wheel_validation import SCORED, WHEELS, load_rows

DATA = Path(__file__).parent / "data"
FREE = ("peak_a0", "peak_a1", "rear_b0", "rear_b1", "n_slip", "n_skid")


def errors(soil, spec, meas, slip_angle_deg=0.0):
    """Model DP/W minus measured, model/measured sinkage - 1, and the scored mask."""
    r = steady_state(soil, spec, meas["load_N"], meas["slip"], slip_angle_deg=slip_angle_deg, n_theta=48)
    dp = r.drawbar_pull / meas["load_N"] - meas["dp_over_w"]
    z = r.sinkage / meas["sinkage_m"] - 1.0
    scored = (meas["slip"] >= SCORED[0] - 0.01) & (meas["slip"] <= SCORED[1] + 0.01)
    return dp, z, scored


def fit(wheel: str, power: float, meas):
    """The fitted soil of ``wheel`` with the skid law's ``power``; the optimiser's result."""
    soil_name, spec = WHEELS[wheel]
    base = replace(load_soil(soil_name), n_skid_power=power)
    x0 = np.array([getattr(base, k) for k in FREE])

    def soil_of(x):
        return replace(base, **{k: float(v) for k, v in zip(FREE, x, strict=True)})

    def objective(x):
        try:
            soil = soil_of(x)
        except ValueError:  # outside the soil's valid ranges (ConfigError)
            return 1e6
        dp, z, scored = errors(soil, spec, meas)
        return float(
            np.sum((dp[scored] / 0.05) ** 2)
            + np.sum((z[scored] / 0.25) ** 2)
            + 0.5 * np.sum((z[~scored] / 0.25) ** 2)
        )

    options = {"maxiter": 1500, "xatol": 1e-4, "fatol": 1e-4}
    res = minimize(objective, x0, method="Nelder-Mead", options=options)
    return soil_of(res.x), res


def _summary(dp, z, scored):
    return (
        f"DP/W MAE {np.abs(dp[scored]).mean():.3f},"
        f" sinkage error mean {100 * np.abs(z[scored]).mean():.0f} %,"
        f" largest {100 * np.abs(z[scored]).max():.0f} %"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--powers", type=float, nargs="+", default=[1.0, 1.5, 2.0])
    args = ap.parse_args(argv)
    beta0 = load_rows(DATA / "cmu_single_wheel_beta0.csv")
    beta15 = load_rows(DATA / "cmu_single_wheel_beta15.csv")
    for power in args.powers:
        print(f"\n## skid law power {power:g}\n")
        total = 0.0
        for wheel in sorted(beta0):
            soil, res = fit(wheel, power, beta0[wheel])
            total += res.fun
            spec = WHEELS[wheel][1]
            coeffs = ", ".join(f"{k} {getattr(soil, k):.4f}" for k in FREE)
            print(f"{wheel}: objective {res.fun:.2f}; {coeffs}")
            print("  slip angle 0 (fitted):    " + _summary(*errors(soil, spec, beta0[wheel])))
            print("  slip angle 15 (held out): " + _summary(*errors(soil, spec, beta15[wheel], 15.0)))
            dp, z, _ = errors(soil, spec, beta0[wheel])
            print(
                "  slip angle 0, sinkage model/measured [mm]: "
                + "  ".join(
                    f"{s:+.2f}: {1e3 * m * (1 + e):.1f}/{1e3 * m:.1f}"
                    for s, m, e in zip(beta0[wheel]["slip"], beta0[wheel]["sinkage_m"], z, strict=True)
                )
            )
        print(f"total objective {total:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
