"""How much of a step's rendering is llvmpipe's own work, and how much the package's Python.

One environment (``obs_source="estimated"``, GL) drives a steady turn; the cameras' sampling time
per step (everything inside the two cameras' ``sample``: body posing, the shadow pass, the views,
read-back and the fisheye remap) is measured in three modes, interleaved in blocks of steps so
that a shared machine's load falls on all of them alike:

* ``all``: as the environment runs;
* ``no draws``: every ``VertexArray.render`` is a no-op, everything else unchanged. The difference
  to ``all`` is the drawing work alone (llvmpipe's vertex processing and rasterisation of the
  triangles, and the wait for it): no Python is removed;
* ``no shadow pass`` / ``no terrain`` / ``no rover``: one kind of draw skipped, for the split.

A bare moderngl program then renders the same passes (a 512 x 512 shadow map, four scissored views
into a 320 x 260 atlas, a 160 x 120 view, read-backs) with no triangles: llvmpipe's fixed cost.
The drawing work plus that fixed cost is a floor on rendering time with this scene on this CPU,
whatever the Python around it does.

Run: LP_NUM_THREADS=1 python benchmarks/render_floor.py [--env Rover-v0] [--steps 60] [--blocks 5]
"""

from __future__ import annotations

import argparse
import time

import cv2
import gymnasium as gym
import moderngl
import numpy as np

import rover_env  # noqa: F401  (registers the missions)
from rover_env.rendering import renderer_for
from rover_env.sensors import cameras

ACTION = np.array([0.5, 0.1, -0.1], dtype=np.float32)


def bare_floor(repeat: int = 300) -> float:
    """ms per train step of llvmpipe's passes with no triangles (clears, views, read-backs)."""
    ctx = moderngl.create_context(standalone=True, backend="egl")
    try:
        fis = ctx.framebuffer([ctx.texture((320, 260), 4)], ctx.depth_renderbuffer((320, 260)))
        down = ctx.framebuffer([ctx.texture((160, 120), 4)], ctx.depth_renderbuffer((160, 120)))
        smap = ctx.framebuffer(depth_attachment=ctx.depth_texture((512, 512)))

        def step():
            smap.use()
            smap.clear(depth=1.0)
            fis.use()
            fis.viewport = (0, 0, 320, 260)
            fis.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            for k in range(4):
                fis.viewport = (0, 65 * k, 320, 65)
                fis.scissor = (0, 65 * k, 100, 65)
            fis.scissor = None
            fis.read(components=3)
            down.use()
            down.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            down.read(components=4)

        for _ in range(20):
            step()
        t = time.perf_counter()
        for _ in range(repeat):
            step()
        return (time.perf_counter() - t) / repeat * 1e3
    finally:
        ctx.release()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="Rover-v0")
    ap.add_argument("--steps", type=int, default=60, help="steps per block")
    ap.add_argument("--blocks", type=int, default=5, help="blocks per mode")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.blocks < 1:
        ap.error("--steps and --blocks must be >= 1")
    cv2.setNumThreads(1)
    env = gym.make(args.env, obs_source="estimated", preset="train", renderer="gl")
    spent = [0.0]
    originals = {}
    for cls in (cameras.DownwardCamera, cameras.FisheyeCamera):
        originals[cls] = cls.sample

        def timed(self, _f=cls.sample):
            t = time.perf_counter()
            try:
                return _f(self)
            finally:
                spent[0] += time.perf_counter() - t

        cls.sample = timed
    render = moderngl.VertexArray.render
    try:
        env.reset(seed=0)
        backend = renderer_for(env.unwrapped.sim)
        if backend.__class__.__name__ != "GLRenderer":
            raise SystemExit("GL is not available here; this benchmark measures the GL renderer")
        for _ in range(10):
            env.step(ACTION)
        terrain = {id(v) for v in backend._terrain["vaos"].values()}
        kinds = {"terrain": terrain, "shadow": set(), "rover": set()}
        for groups in backend._bodies.values():
            for g in groups:
                kinds["shadow"].add(id(g.vaos["depth"]))
                kinds["rover"] |= {id(v) for k, v in g.vaos.items() if k != "depth"}
        modes = {
            "all": set(),
            "no draws": set().union(*kinds.values()),
            "no shadow pass": kinds["shadow"],
            "no terrain": kinds["terrain"],
            "no rover": kinds["rover"],
        }
        times = {m: [] for m in modes}
        for _ in range(args.blocks):
            for mode, skip in modes.items():

                def maybe(self, *a, _skip=skip, **k):
                    return None if id(self) in _skip else render(self, *a, **k)

                moderngl.VertexArray.render = maybe
                spent[0] = 0.0
                for _ in range(args.steps):
                    env.step(ACTION)
                times[mode].append(spent[0] / args.steps * 1e3)
    finally:
        moderngl.VertexArray.render = render
        for cls, f in originals.items():
            cls.sample = f
        env.close()
    med = {m: float(np.median(v)) for m, v in times.items()}
    bare = bare_floor()
    draws = med["all"] - med["no draws"]
    print(f"{args.env}, train preset, GL, {args.blocks} x {args.steps} steps per mode (median of blocks)")
    print("| camera sampling per step | ms |")
    print("|---|---:|")
    print(f"| as run | {med['all']:.2f} |")
    print(f"| no draw calls (posing, views, read-back, remap, Python) | {med['no draws']:.2f} |")
    print(f"| drawing work alone (difference) | {draws:.2f} |")
    for m in ("no shadow pass", "no terrain", "no rover"):
        print(f"| drawing saved by: {m} | {med['all'] - med[m]:.2f} |")
    print(f"| llvmpipe fixed cost of the same passes with no triangles (bare moderngl) | {bare:.2f} |")
    print(f"| floor: drawing work + fixed cost | {draws + bare:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
