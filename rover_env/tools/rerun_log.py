"""Missions logged to Rerun (``rerun-sdk``, the ``rerun`` extra) for interactive inspection.

One :class:`RerunLog` writes a ``.rrd`` file (open it with ``rerun FILE.rrd``). Per control step,
on the ``sim_time`` timeline [s], under the run's prefix:

- ``world/truth`` and ``world/estimate``: the true and the dead-reckoned body position [m]
  (world frame), and at the end both whole paths and the course as line strips;
- ``twist/<v_x|v_y|omega>/<truth|estimate>`` [m/s, rad/s], ``slip/<wheel>/<truth|estimate>``
  [-], ``joints/<axle_roll|steering>_<axle>/<truth|estimate>`` [rad];
- ``cameras/downward`` and ``cameras/fisheye``: the images perception was given (every
  ``image_every``-th step).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from perception.models.drive_geometry import WHEELS

AXLES = ("F", "R")


def _rerun():
    try:
        import rerun as rr
    except ImportError:
        raise ImportError(
            "--rerun needs the Rerun SDK: pip install 'rover-vision[rerun]' (or pip install rerun-sdk)"
        ) from None
    return rr


class RerunLog:
    """A Rerun recording written to ``path``.

    Args:
        path: The ``.rrd`` file (replaced).
        image_every: Log the camera images every n-th step (they dominate the file's size).
    """

    def __init__(self, path: str | Path, image_every: int = 3) -> None:
        rr = _rerun()
        self.rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("rover-vision")
        self.rec.save(str(self.path))
        self.image_every = max(1, int(image_every))
        self._prefix = ""
        self._step = 0
        self._truth: list = []
        self._estimate: list = []

    def start_run(self, prefix: str, course_xy=None) -> None:
        """Begin a run under ``prefix`` (e.g. the controller's name), with its course [m]."""
        self._prefix = prefix.strip("/")
        self._step = 0
        self._truth, self._estimate = [], []
        if course_xy is not None:
            pts = np.column_stack([np.asarray(course_xy, dtype=float), np.zeros(len(course_xy))])
            self.rec.log(
                self._path("world/course"), self.rr.LineStrips3D([pts], colors=[(60, 60, 60)]), static=True
            )

    def _path(self, name: str) -> str:
        return f"{self._prefix}/{name}" if self._prefix else name

    def _scalar(self, name: str, value: float) -> None:
        if np.isfinite(value):
            self.rec.log(self._path(name), self.rr.Scalars(float(value)))

    def log_step(self, info: dict, images: dict | None = None) -> None:
        """One control step from ``env.step``'s ``info`` (and perception's latest images)."""
        rr = self.rr
        self.rec.set_time("sim_time", duration=float(info["t"]))
        gt = info["ground_truth"]
        est = info.get("estimate")
        p = np.asarray(gt["pose"][:3], dtype=float)
        self._truth.append(p)
        self.rec.log(self._path("world/truth"), rr.Points3D([p], colors=[(40, 90, 220)], radii=0.08))
        if est is not None:
            q = np.asarray(est["pose"][:3], dtype=float)
            self._estimate.append(q)
            self.rec.log(self._path("world/estimate"), rr.Points3D([q], colors=[(220, 60, 40)], radii=0.06))
        for i, name in enumerate(("v_x", "v_y", "omega")):
            self._scalar(f"twist/{name}/truth", gt["twist"][i])
            if est is not None:
                self._scalar(f"twist/{name}/estimate", est["twist"][i])
        for i, w in enumerate(WHEELS):
            self._scalar(f"slip/{w}/truth", gt["slip_ratio"][i])
            if est is not None:
                self._scalar(f"slip/{w}/estimate", est["slip_ratio"][i])
        for key in ("axle_roll", "steering"):
            for i, a in enumerate(AXLES):
                self._scalar(f"joints/{key}_{a}/truth", gt[key][i])
                if est is not None:
                    self._scalar(f"joints/{key}_{a}/estimate", est[key][i])
        if images and self._step % self.image_every == 0:
            for name, img in images.items():
                if img is not None:  # JPEG: a tenth of the raw pixels' size
                    self.rec.log(self._path(f"cameras/{name}"), rr.Image(img).compress(jpeg_quality=85))
        self._step += 1

    def end_run(self) -> None:
        """Log the run's whole true and estimated paths as static line strips."""
        rr = self.rr
        if len(self._truth) > 1:
            self.rec.log(self._path("world/truth_path"), rr.LineStrips3D([np.array(self._truth)],
                         colors=[(40, 90, 220)]), static=True)  # fmt: skip
        if len(self._estimate) > 1:
            self.rec.log(self._path("world/estimate_path"), rr.LineStrips3D([np.array(self._estimate)],
                         colors=[(220, 60, 40)]), static=True)  # fmt: skip

    def close(self) -> None:
        """Flush and close the file."""
        self.rec.flush()
        self.rec.disconnect()
