"""Mission videos: H.264 in MP4 (plays in browsers), with an overlay of the state.

:class:`VideoWriter` encodes RGB frames with PyAV's libx264 (yuv420p, ``+faststart``), about a
fifth of the size of OpenCV's MPEG-4 Part 2 at the same quality. :func:`draw_overlay` writes the
time, the true and estimated speed, each wheel's slip (estimated and true) and the estimator's
quality in a dark band at the frame's top left.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

#: Height of one overlay text line [px] at scale 1; the band's geometry follows from it.
_LINE = 18
OVERLAY_ORIGIN = (6, 6)  # top-left corner of the band [px]


class VideoWriter:
    """H.264 MP4 writer of RGB uint8 frames.

    Args:
        path: The ``.mp4`` file.
        fps: Frame rate [Hz].
        size: (width, height) [px]; both are made even (yuv420p needs it) by cropping.
        crf: x264's constant rate factor (lower: better and larger; 23 is x264's default).
        preset: x264's speed preset.

    Raises:
        OSError: The file cannot be written, or PyAV has no H.264 encoder.
    """

    def __init__(
        self, path: str | Path, fps: float, size: tuple[int, int], crf: int = 26, preset: str = "veryfast"
    ) -> None:
        import av

        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps: {fps!r}; give a frame rate > 0 [Hz]")
        self.path = Path(path)
        self.width, self.height = (int(v) // 2 * 2 for v in size)
        try:
            self._container: Any = av.open(str(self.path), mode="w", options={"movflags": "+faststart"})
            rate = int(round(fps)) if abs(fps - round(fps)) < 1e-9 else round(fps * 1000) / 1000
            from fractions import Fraction

            self._stream = self._container.add_stream("libx264", rate=Fraction(rate).limit_denominator(1000))
        except (av.FFmpegError, ValueError, OSError) as exc:
            raise OSError(f"could not open an H.264 video writer for {self.path} ({exc})") from None
        self._stream.width, self._stream.height = self.width, self.height
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": str(int(crf)), "preset": preset}
        self.frames = 0

    def write(self, rgb: np.ndarray) -> None:
        """Append one RGB uint8 frame (H, W, 3); larger frames are cropped to the stream's size."""
        import av

        img = np.ascontiguousarray(np.asarray(rgb)[: self.height, : self.width, :3])
        if img.shape != (self.height, self.width, 3) or img.dtype != np.uint8:
            want = (self.height, self.width, 3)
            raise ValueError(f"frame: {img.shape} {img.dtype}; expected {want} uint8")
        for packet in self._stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder and close the file."""
        if self._container is None:
            return
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        self._container = None

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def overlay_lines(t: float, info: dict) -> list[str]:
    """The overlay's text for one step from ``env.step``'s ``info`` (true and, if any, estimated state)."""
    gt = info["ground_truth"]
    est = info.get("estimate")
    speed = f"t {t:6.1f} s   v_x {gt['twist'][0]:+5.2f} m/s"
    lines = [speed + (f" (est {est['twist'][0]:+5.2f})" if est else "")]
    s_true = np.asarray(gt["slip_ratio"], dtype=float)
    if est is not None:
        s_est = np.asarray(est["slip_ratio"], dtype=float)
        lines.append("slip est " + " ".join(f"{v:+.2f}" for v in s_est) + "  FL FR RL RR")
        lines.append("slip true " + " ".join(f"{v:+.2f}" for v in s_true))
        q = info.get("quality", {})
        lines.append(
            f"quality odo {q.get('odometry', 0.0):.2f}  kin {q.get('kinematics', 0.0):.2f}  "
            f"slip {q.get('slip', 0.0):.2f}"
        )
    else:
        lines.append("slip " + " ".join(f"{v:+.2f}" for v in s_true) + "  FL FR RL RR (true)")
    mu = info.get("wheel_contact", {}).get("friction")
    if mu is not None:
        lines.append("mu under wheels " + " ".join(f"{v:.2f}" for v in np.asarray(mu, dtype=float)))
    return lines


def overlay_box(n_lines: int, scale: float = 0.45) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) [px] of the band that holds ``n_lines`` lines of text."""
    x0, y0 = OVERLAY_ORIGIN
    return x0, y0, x0 + int(430 * scale / 0.45), y0 + int((_LINE * n_lines + 8) * scale / 0.45)


def draw_overlay(rgb: np.ndarray, lines: list[str], scale: float = 0.45) -> np.ndarray:
    """``rgb`` with ``lines`` of white text on a dark, 70 % opaque band at its top left (in place)."""
    x0, y0, x1, y1 = overlay_box(len(lines), scale)
    x1, y1 = min(x1, rgb.shape[1]), min(y1, rgb.shape[0])
    band = rgb[y0:y1, x0:x1]
    band[:] = (band.astype(np.float32) * 0.3).astype(np.uint8)
    step = int(_LINE * scale / 0.45)
    for i, text in enumerate(lines):
        org = (x0 + 5, y0 + step * (i + 1))
        cv2.putText(rgb, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return rgb


def stack_videos(clips: list[Path], labels: list[str], path: str | Path, fps: float | None = None) -> Path:
    """One video of ``clips`` one above the other, each under its label (H.264, :class:`VideoWriter`).

    A clip that ends first holds its last frame. The clips must share their width.
    """
    import av

    containers = [av.open(str(c)) for c in clips]
    try:
        streams = [c.streams.video[0] for c in containers]
        rate = fps or float(streams[0].average_rate or 15)
        width = streams[0].codec_context.width
        bar = 22
        heights = [s.codec_context.height for s in streams]
        if any(s.codec_context.width != width for s in streams):
            raise ValueError(f"stack_videos: clips of widths {[s.codec_context.width for s in streams]}")
        decoders = [c.decode(s) for c, s in zip(containers, streams, strict=True)]
        last: list[np.ndarray] = [np.zeros((h, width, 3), np.uint8) for h in heights]
        ended = [False] * len(clips)
        with VideoWriter(path, rate, (width, sum(heights) + bar * len(clips))) as out:
            while True:
                for i, dec in enumerate(decoders):
                    if ended[i]:
                        continue
                    try:
                        last[i] = next(dec).to_ndarray(format="rgb24")
                    except StopIteration:
                        ended[i] = True
                if all(ended):
                    break
                rows = []
                for i, label in enumerate(labels):
                    head = np.full((bar, width, 3), 32, np.uint8)
                    text = label + ("   (finished)" if ended[i] else "")
                    cv2.putText(
                        head, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA
                    )
                    rows += [head, last[i]]
                out.write(np.vstack(rows))
    finally:
        for c in containers:
            c.close()
    return Path(path)
