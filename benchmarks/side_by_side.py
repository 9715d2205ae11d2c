"""Side by side: the per-field MAE of two `observation_errors.py` outputs (TinyRenderer, GL).

Run: python benchmarks/side_by_side.py TINY.md GL.md [--title "train preset"]
(each file is the printed output of ``python benchmarks/observation_errors.py --renderer R``).
Prints, per field and mission, "tiny -> gl (gl / tiny)".
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

HEAD = re.compile(r"^### (\S+) ")
ROW = re.compile(r"^\| (\w+) \| ([0-9.e+-]+|nan) \| ([0-9.e+-]+|nan) \|$")


def read(path: Path) -> dict[str, dict[str, float]]:
    """{mission: {field: MAE}} of one output."""
    out: dict[str, dict[str, float]] = {}
    mission = None
    for line in path.read_text().splitlines():
        if m := HEAD.match(line):
            mission = m.group(1)
            out[mission] = {}
        elif mission is not None and (m := ROW.match(line)):
            out[mission][m.group(1)] = float(m.group(2))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tiny", type=Path)
    ap.add_argument("gl", type=Path)
    ap.add_argument("--title", default="")
    args = ap.parse_args(argv)
    tiny, gl = read(args.tiny), read(args.gl)
    missions = [m for m in tiny if m in gl]
    fields = [f for f in tiny[missions[0]] if f in gl[missions[0]]]
    print(f"{args.title}, MAE TinyRenderer -> GL (ratio GL/tiny)\n")
    print("| field | " + " | ".join(missions) + " |")
    print("|---|" + "---:|" * len(missions))
    for f in fields:
        cells = []
        for m in missions:
            a, b = tiny[m][f], gl[m][f]
            ratio = f"{b / a:.2f}" if a > 0 else "-"
            cells.append(f"{a:.4f} → {b:.4f} ({ratio})")
        print(f"| {f} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
