"""A simulated mission recorded as a log (`rover record`) and replayed (`rover replay --truth`).

For each mission, preset and seed: the log's size, and the built-in estimator's v_x, omega and
steering MAE against the truth in the loop (``estimates_in_loop.csv``) and on the log
(``rover replay``), after the first second. The replay's figures should be the loop's: the log
holds what the sensors delivered.

    LP_NUM_THREADS=1 python benchmarks/record_replay.py --missions Rover-v0 RoverRoughSlippery-v0 \\
        RoverShadows-v0 --presets train eval --seeds 0 1 --seconds 10 --controller slip_aware \\
        --out benchmarks/results/record_replay.md
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from perception.logs.truth import read_estimates, read_truth, score
from rover_env.tools.cli import main as rover

FIELDS = ("v_x", "omega", "steering_F")


def run(mission: str, preset: str, seed: int, seconds: float, controller: str, work: Path) -> dict:
    rec, rep = work / f"rec_{mission}_{preset}_{seed}", work / f"rep_{mission}_{preset}_{seed}"
    t0 = time.perf_counter()
    argv = ["record", mission, "--controller", controller, "--seconds", str(seconds), "--preset", preset]
    assert rover([*argv, "--seed", str(seed), "--out", str(rec)]) == 0
    t1 = time.perf_counter()
    argv = [
        "replay",
        str(rec / "log.mcap"),
        "--rig",
        str(rec / "rig.yaml"),
        "--truth",
        str(rec / "truth.csv"),
    ]
    assert rover([*argv, "--out", str(rep)]) == 0
    t2 = time.perf_counter()
    truth = read_truth(rec / "truth.csv")
    loop = {e.name: e.mae for e in score(read_estimates(rec / "estimates_in_loop.csv"), truth, skip=1.0)}
    again = {e.name: e.mae for e in score(read_estimates(rep / "estimates.csv"), truth, skip=1.0)}
    return {
        "mission": mission, "preset": preset, "seed": seed, "mb": (rec / "log.mcap").stat().st_size / 1e6,
        "seconds": float(truth["t_log"][-1] - truth["t_log"][0]), "loop": loop, "replay": again,
        "record_s": t1 - t0, "replay_s": t2 - t1,
    }  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--missions", nargs="+", default=["Rover-v0"])
    ap.add_argument("--presets", nargs="+", default=["train"], choices=["train", "eval"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--controller", default="slip_aware")
    ap.add_argument("--out", help="also write the table to this Markdown file")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in args.missions:
            for p in args.presets:
                for s in args.seeds:
                    rows.append(run(m, p, s, args.seconds, args.controller, Path(tmp)))
    head = (
        "| mission | preset | seed | s | log [MB] | MB/s | "
        + " | ".join(f"{f} MAE loop / replay" for f in FIELDS)
        + " | record, replay [s] |"
    )
    lines = [head, "|---|---|---:|---:|---:|---:|" + "---:|" * len(FIELDS) + "---:|"]
    for r in rows:
        cells = [f"{r['loop'][f]:.4f} / {r['replay'][f]:.4f}" for f in FIELDS]
        lines.append(
            f"| {r['mission']} | {r['preset']} | {r['seed']} | {r['seconds']:.1f} | {r['mb']:.1f} | "
            f"{r['mb'] / r['seconds']:.2f} | "
            + " | ".join(cells)
            + f" | {r['record_s']:.0f}, {r['replay_s']:.0f} |"
        )
    diff = [abs(r["loop"]["v_x"] - r["replay"]["v_x"]) for r in rows]
    lines.append("")
    lines.append(
        f"Largest |v_x MAE on the log - v_x MAE in the loop|: {max(diff):.5f} m/s over {len(rows)} logs."
    )
    text = "\n".join(lines)
    print(text)
    if args.out:
        cmd = "LP_NUM_THREADS=1 python benchmarks/record_replay.py " + " ".join(
            argv or __import__("sys").argv[1:]
        )
        Path(args.out).write_text(f"# rover record, then rover replay --truth\n\n`{cmd}`\n\n{text}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
