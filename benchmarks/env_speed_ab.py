"""Environment speed of two source trees side by side: this checkout against another commit.

Each round runs one environment in a fresh process from each tree, in turn (A, B, B, A, ...),
so both see the same machine load; each process drives ``--steps`` control steps of a steady turn
after a warm-up, on one core. Prints the median milliseconds per step of each tree and their
ratio per mission. Make the other tree with ``git worktree add /tmp/before COMMIT``.

Run: LP_NUM_THREADS=1 python benchmarks/env_speed_ab.py /tmp/before [--rounds 5] [--steps 120]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]

# runs in the tree under test: its own rover_env and its own benchmarks/env_speed.py's ``run``
# (10 warm-up steps, then ``steps`` timed), whatever the environment has installed
PROBE = r"""
import json, sys
sys.path[:0] = [sys.argv[1], sys.argv[1] + "/benchmarks"]
import cv2
cv2.setNumThreads(1)
import rover_env
assert rover_env.__file__.startswith(sys.argv[1]), rover_env.__file__
from env_speed import run
print(json.dumps(run(sys.argv[2], sys.argv[3], "train", int(sys.argv[5]), sys.argv[4])))
"""


def probe(tree: Path, env_id: str, source: str, renderer: str, steps: int) -> float:
    """Milliseconds per step of ``env_id`` in a fresh process importing ``tree``'s package."""
    env = dict(os.environ, LP_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(tree))
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(tree), env_id, source, renderer, str(steps)],
        capture_output=True, text=True, env=env, cwd=tree, check=False,
    )  # fmt: skip
    if out.returncode != 0:
        raise RuntimeError(f"{tree}: {env_id}: {out.stderr.strip()[-600:]}")
    return float(json.loads(out.stdout.strip().splitlines()[-1])["ms"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path, help="the other source tree (a git worktree of the earlier commit)")
    ap.add_argument("--envs", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0"])
    ap.add_argument("--sources", nargs="+", default=["estimated", "ground_truth"])
    ap.add_argument("--renderer", default="gl", choices=["gl", "tiny"])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=120)
    args = ap.parse_args(argv)
    trees = {"before": args.before.resolve(), "now": HERE}
    print(f"{args.rounds} rounds, {args.steps} steps each, renderer {args.renderer}, one core per process\n")
    print("| mission | observation | before [ms/step] | now [ms/step] | now / before |")
    print("|---|---|---:|---:|---:|")
    ratios = []
    for env_id in args.envs:
        for source in args.sources:
            ms: dict[str, list[float]] = {k: [] for k in trees}
            for r in range(args.rounds):
                order = list(trees) if r % 2 == 0 else list(reversed(trees))
                for k in order:
                    ms[k].append(probe(trees[k], env_id, source, args.renderer, args.steps))
            b, n = statistics.median(ms["before"]), statistics.median(ms["now"])
            ratios.append(n / b)
            print(f"| {env_id} | {source} | {b:.2f} | {n:.2f} | {n / b:.3f} |", flush=True)
    print(f"\ngeometric mean of the ratios: {statistics.geometric_mean(ratios):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
