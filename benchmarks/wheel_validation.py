"""The wheel–soil model against published single-wheel test-bed measurements.

Pavlov and Johnson's test bed (CMU Robomechanics, github.com/robomechanics/3d-terramechanics):
a K10-mini wheel (r 58 mm, b 50 mm), grousered (5 mm grousers, tips 10 % of the rim) and smooth,
towed at 10 mm/s through their sand at slips from -1 to 0.9, slip angle 0. The measurements are
the means of three trials, in ``benchmarks/data/cmu_single_wheel_beta0.csv`` (averaged from the
repository's ``raw-data-processing/all_{grouser,smooth}_data.mat``). The model runs with their
published soil parameters (soil presets ``cmu_testbed_grousered`` and ``cmu_testbed_smooth``;
their slip-sinkage coefficients refit to these means by ``benchmarks/wheel_fit.py``), each run
at its measured load, to the steady state. The means at a slip angle of 15 degrees
(``cmu_single_wheel_beta15.csv``, averaged the same way) are held out of that fit and reported
as a check.

    python benchmarks/wheel_validation.py [--bed] [--plot docs/images/wheel_validation.png]

``--bed`` runs each slip on the simulated test bed (``rover wheel-test``'s, in PyBullet, a metre
of travel) instead of solving the model's steady state directly.

Prints a table per wheel and the errors over the slips -0.5 to 0.9: DP/W's mean absolute error
and the sinkage's relative error.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from rover_env.config.soil import load_soil
from rover_env.sim.terramechanics import WheelSpec, steady_state
from rover_env.sim.wheel_test import run_wheel_test

DATA = Path(__file__).parent / "data" / "cmu_single_wheel_beta0.csv"
#: The same test bed at a slip angle of 15 degrees, held out of the coefficients' fit.
HELD_OUT = Path(__file__).parent / "data" / "cmu_single_wheel_beta15.csv"
WHEELS = {
    "grousered": (
        "cmu_testbed_grousered",
        WheelSpec(radius=0.058, width=0.05, grouser_height=0.005, tip_ratio=0.1),
    ),
    "smooth": ("cmu_testbed_smooth", WheelSpec(radius=0.058, width=0.05)),
}
SCORED = (-0.5, 0.9)  # the slips the acceptance scores (inclusive, to rounding)


def load_rows(path: Path = DATA) -> dict[str, dict[str, np.ndarray]]:
    """The measurements per wheel: columns of the CSV as arrays."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    out: dict[str, dict[str, np.ndarray]] = {}
    for wheel in sorted({r["wheel"] for r in rows}):
        mine = [r for r in rows if r["wheel"] == wheel]
        out[wheel] = {k: np.array([float(r[k]) for r in mine]) for k in mine[0] if k != "wheel"}
    return out


def compare(
    wheel: str, meas: dict[str, np.ndarray], bed: bool = False, slip_angle_deg: float = 0.0
) -> dict[str, np.ndarray]:
    """Model DP/W and sinkage at each measured slip and load of ``wheel`` (``bed``: simulated)."""
    soil_name, spec = WHEELS[wheel]
    soil = load_soil(soil_name)
    if bed:
        rows = [
            run_wheel_test(soil, spec, w, [s])[0] for s, w in zip(meas["slip"], meas["load_N"], strict=True)
        ]
        return {
            "dp_over_w": np.array([r.drawbar_pull_N / r.load_N for r in rows]),
            "sinkage_m": np.array([r.sinkage_m for r in rows]),
            "converged": np.array([abs(r.load_N / w - 1.0) < 0.01 for r, w in zip(rows, meas["load_N"])]),
        }
    r = steady_state(soil, spec, meas["load_N"], meas["slip"], slip_angle_deg=slip_angle_deg)
    return {"dp_over_w": r.drawbar_pull / meas["load_N"], "sinkage_m": r.sinkage, "converged": r.converged}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plot", type=Path, help="write the side-by-side plot here (PNG)")
    ap.add_argument("--bed", action="store_true", help="run each slip on the simulated test bed")
    args = ap.parse_args(argv)
    data = load_rows()
    results = {}
    for wheel, meas in data.items():
        sim = compare(wheel, meas, bed=args.bed)
        results[wheel] = sim
        scored = (meas["slip"] >= SCORED[0] - 0.01) & (meas["slip"] <= SCORED[1] + 0.01)
        dp_err = np.abs(sim["dp_over_w"] - meas["dp_over_w"])
        z_err = sim["sinkage_m"] / meas["sinkage_m"] - 1.0
        how = "simulated test bed" if args.bed else "steady state"
        print(f"\n### {wheel} wheel (soil preset {WHEELS[wheel][0]}, {how})\n")
        print(
            "| slip | load [N] | DP/W measured | DP/W model | sinkage measured [mm]"
            " | sinkage model [mm] | sinkage error |"
        )
        print("|---:|---:|---:|---:|---:|---:|---:|")
        for i in range(len(meas["slip"])):
            mark = "" if scored[i] else " (not scored)"
            print(
                f"| {meas['slip'][i]:+.2f}{mark} | {meas['load_N'][i]:.1f} | {meas['dp_over_w'][i]:+.3f}"
                f" | {sim['dp_over_w'][i]:+.3f} | {1e3 * meas['sinkage_m'][i]:.1f}"
                f" | {1e3 * sim['sinkage_m'][i]:.1f} | {100 * z_err[i]:+.0f} % |"
            )
        print(
            f"\nslips {SCORED[0]} to {SCORED[1]}: DP/W mean absolute error {dp_err[scored].mean():.3f};"
            f" sinkage relative error mean {100 * np.abs(z_err[scored]).mean():.0f} %,"
            f" largest {100 * np.abs(z_err[scored]).max():.0f} %;"
            f" all converged: {bool(sim['converged'].all())}"
        )
    print("\nHeld out of the coefficients' fit (benchmarks/wheel_fit.py): slip angle 15 degrees\n")
    for wheel, meas in load_rows(HELD_OUT).items():
        sim = compare(wheel, meas, slip_angle_deg=15.0)
        scored = (meas["slip"] >= SCORED[0] - 0.01) & (meas["slip"] <= SCORED[1] + 0.01)
        dp_err = np.abs(sim["dp_over_w"] - meas["dp_over_w"])[scored]
        z_err = np.abs(sim["sinkage_m"] / meas["sinkage_m"] - 1.0)[scored]
        print(
            f"{wheel}: DP/W mean absolute error {dp_err.mean():.3f}; sinkage relative error mean"
            f" {100 * z_err.mean():.0f} %, largest {100 * z_err.max():.0f} %"
        )
    if args.plot:
        _plot(data, results, args.plot)
        print(f"\nplot: {args.plot}")
    return 0


def _plot(data, results, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(9, 6.5), sharex=True)
    for col, wheel in enumerate(sorted(data)):
        meas, sim = data[wheel], results[wheel]
        soil_name, spec = WHEELS[wheel]
        s_fine = np.linspace(-0.95, 0.95, 77)
        load = float(np.median(meas["load_N"]))
        fine = steady_state(load_soil(soil_name), spec, load, s_fine)
        ax = axes[0, col]
        ax.errorbar(
            meas["slip"],
            meas["dp_over_w"],
            yerr=meas["dp_over_w_sd"],
            fmt="o",
            color="k",
            label="measured (3 trials)",
        )
        ax.plot(
            meas["slip"], sim["dp_over_w"], "s", color="C1", mfc="none", label="model at the measured load"
        )
        ax.plot(s_fine, fine.drawbar_pull / load, "-", color="C1", lw=1, label=f"model, {load:.1f} N")
        ax.set_title(f"{wheel} wheel")
        ax.set_ylabel("drawbar pull / load")
        ax.axvspan(-1.0, SCORED[0], color="0.92")
        ax.grid(alpha=0.3)
        ax = axes[1, col]
        ax.errorbar(
            meas["slip"], 1e3 * meas["sinkage_m"], yerr=1e3 * meas["sinkage_sd_m"], fmt="o", color="k"
        )
        ax.plot(meas["slip"], 1e3 * sim["sinkage_m"], "s", color="C1", mfc="none")
        ax.plot(s_fine, 1e3 * fine.sinkage, "-", color="C1", lw=1)
        ax.set_ylabel("sinkage [mm]")
        ax.set_xlabel("slip")
        ax.axvspan(-1.0, SCORED[0], color="0.92")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(
        "Single-wheel test bed: Pavlov and Johnson's measurements and this model (grey: not scored)",
        fontsize=10,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
