"""The rollouts of tests/test_same_behaviour.py at two checkouts of the package, compared bit for bit.

Each tree's packages make every case's rollout in a process of its own (``--tree``: a checkout,
e.g. ``git worktree add /tmp/before REV``); then the two sets of arrays are compared exactly.
A refactoring that claims "behaviour unchanged" shows it here with 0 arrays differing.

    LP_NUM_THREADS=1 python benchmarks/same_behaviour.py --before /tmp/before --after .
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ROLL = """
import importlib.util, sys
tree, out, test = sys.argv[1], sys.argv[2], sys.argv[3]
sys.path.insert(0, tree)
import numpy as np, rover_env
assert rover_env.__file__.startswith(tree), rover_env.__file__
spec = importlib.util.spec_from_file_location("sb", test)
sb = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sb)
data = {}
for case in sb.CASES:
    for k, v in sb.rollout(*case).items():
        data[f"{sb._key(*case)}::{k}"] = v
np.savez_compressed(out, **data)
"""


def rollouts(tree: Path, out: Path) -> dict[str, np.ndarray]:
    test = ROOT / "tests" / "test_same_behaviour.py"  # this checkout's cases, on either tree
    subprocess.run([sys.executable, "-c", ROLL, str(tree.resolve()), str(out), str(test)], check=True)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="a checkout of the earlier version")
    ap.add_argument("--after", type=Path, default=ROOT, help="a checkout of the later version")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        a = rollouts(args.before, Path(tmp) / "before.npz")
        b = rollouts(args.after, Path(tmp) / "after.npz")
    if sorted(a) != sorted(b):
        print(f"the arrays differ in their names: {sorted(set(a) ^ set(b))[:10]}")
        return 1
    differ = [k for k in a if a[k].shape != b[k].shape or not np.array_equal(a[k], b[k], equal_nan=True)]
    print(f"{len(a)} arrays of {len({k.split('::')[0] for k in a})} cases; {len(differ)} differ")
    for k in differ[:20]:
        print(f"  {k}: largest difference {float(np.nanmax(np.abs(a[k] - b[k]))):.3g}")
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
