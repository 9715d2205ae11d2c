"""``rover wheel-test``: the single-wheel test bed, its CSV and its plot."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from perception.logs.outputs import OutputFolder
from rover_env.config.soil import load_soil
from rover_env.sim.terramechanics import WheelSpec
from rover_env.sim.wheel_test import WheelTestRow, check_wheel_test, run_wheel_test, wheel_test_table

PRODUCTS = ("wheel_test.csv", "wheel_test.png")


def write_plot(rows: list[WheelTestRow], path: str | Path, title: str) -> None:
    """Drawbar pull over load, and sinkage, against slip (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = [r.slip for r in rows]
    fig, (a, b) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    a.plot(s, [r.drawbar_pull_N / r.load_N for r in rows], "o-")
    a.axhline(0.0, color="0.5", lw=0.8)
    a.set_ylabel("drawbar pull / load")
    a.grid(alpha=0.3)
    b.plot(s, [1e3 * r.sinkage_m for r in rows], "o-")
    b.set_ylabel("sinkage [mm]")
    b.set_xlabel("slip")
    b.grid(alpha=0.3)
    a.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace, progress: Callable[[float], None] | None = None) -> list[WheelTestRow]:
    """Run the test bed from the parsed ``rover wheel-test`` arguments; its CSV and plot into ``args.out``.

    Every input is checked, and the test's steady states with it, before the output folder is
    made; the CSV and the plot are committed together when the run has succeeded.
    """
    soil = load_soil(args.soil)
    wheel = WheelSpec(
        radius=args.radius,
        width=args.width,
        grousers=args.grousers,
        grouser_height=args.grouser_height,
        **({} if args.grouser_thickness is None else {"grouser_thickness": args.grouser_thickness}),
    )
    check_wheel_test(soil, wheel, args.load, args.slips, args.speed, args.distance)  # before the folder
    with OutputFolder(args.out, PRODUCTS, args.overwrite) as out:
        rows = run_wheel_test(
            soil, wheel, args.load, args.slips, speed=args.speed, distance=args.distance, progress=progress
        )
        out.write_text("wheel_test.csv", wheel_test_table(rows))
        title = (
            f"soil {soil.name}, r {args.radius} m, b {args.width} m, load {args.load} N, "
            f"{args.grousers} grousers x {args.grouser_height} m, {args.speed} m/s"
        )
        with out.writing("wheel_test.png") as tmp:
            write_plot(rows, tmp, title)
        out.commit()
    return rows
