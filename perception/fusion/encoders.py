"""Wheel rates from incremental encoders: their counters unwrapped, averaged over a window, checked.

An encoder's counter wraps at ``2 ** counter_bits`` counts; between two readings it is
unwrapped to the nearest change, which is unambiguous while a wheel turns less than half the
counter's range between them (:meth:`EncoderRates.add` refuses a gap longer than that at the
fastest wheel rate). The counts are summed over windows of at least ``window`` seconds; each
window gives a mean rate per wheel with the quantisation's standard deviation
(``2 pi / counts_per_rev / dt / sqrt(6)``: the difference of two readings, each uniform over a
count).

What is not a reading is left out, never read as a rate of zero: a sample of the wrong shape
(:class:`ValueError`, naming the sensor), counts that are not whole numbers within the counter,
a sample older than the last, a gap of more than ``max_gap`` periods (the window restarts after
it), and a wheel whose counter stands still while the fisheye sees it turn (:meth:`check_stuck`:
a stuck encoder, left out until its counter moves again).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Wheels per rover.
N_WHEELS = 4


@dataclass
class EncoderWindow:
    """One window's mean wheel rates.

    Attributes:
        t: End of the window [s] (the rates apply at ``t - dt / 2``).
        dt: Its length [s].
        rate: (4,) mean spin rates [rad/s], forward positive.
        valid: (4,) which wheels' rates were measured (a stuck or bad counter's are not).
        std: (4,) the rates' standard deviation from the quantisation [rad/s].
    """

    t: float
    dt: float
    rate: np.ndarray
    valid: np.ndarray
    std: np.ndarray


class EncoderRates:
    """An encoder sensor's counters turned into windowed wheel rates (see the module docstring).

    Args:
        name: The sensor's name, for messages.
        counts_per_rev: Counts per wheel revolution [-].
        counter_bits: The counter wraps at ``2 ** counter_bits`` counts.
        period: Its sample period [s].
        window: Shortest window a rate is averaged over [s].
        max_rate: The fastest a wheel turns [rad/s] (how long a gap can be unwrapped).
        max_gap: Most sample periods between two readings within a window.
        stuck_after: How long a counter must stand still while the fisheye sees its wheel turn
            before it counts as stuck [s].
    """

    def __init__(
        self,
        name: str,
        counts_per_rev: int,
        counter_bits: int,
        period: float,
        window: float = 1.0 / 30.0,
        max_rate: float = 50.0,
        max_gap: float = 3.0,
        stuck_after: float = 0.3,
    ) -> None:
        self.name = name
        #: The counter's range [counts].
        self.wrap = float(2 ** int(counter_bits))
        self.period = float(period)
        self.window = float(window)
        self.max_rate = float(max_rate)
        self.max_gap = float(max_gap)
        self.stuck_after = float(stuck_after)
        self._count_rad = 2.0 * math.pi / float(counts_per_rev)
        # the longest time between readings that still unwraps: under half the counter's range
        self._max_unwrap_s = 0.5 * self.wrap * self._count_rad / self.max_rate
        self.reset()

    def reset(self) -> None:
        """Forget the counters (a new start)."""
        self._last: np.ndarray | None = None
        self._t_last = -math.inf
        self._start_t = -math.inf
        self._sum = np.zeros(N_WHEELS)
        self._still_since = np.full(N_WHEELS, math.nan)
        #: Which wheels' counters count as stuck now.
        self.stuck = np.zeros(N_WHEELS, dtype=bool)
        #: Samples left out (not whole counts within the counter, out of order, after a gap).
        self.rejected = 0

    def add(self, counts, t: float) -> EncoderWindow | None:
        """One reading at ``t`` [s]; a window's rates if this reading completes one, else None.

        Raises:
            ValueError: The sample is not four counts (the rig's sensor is not wheel encoders).
        """
        c = np.asarray(counts, dtype=np.float64).reshape(-1)
        if c.shape != (N_WHEELS,):
            raise ValueError(
                f"{self.name}: a wheel-encoder sample is (4,) counts FL, FR, RL, RR; got shape {c.shape}"
            )
        wrap = self.wrap
        if not (np.all(np.isfinite(c)) and np.all(c == np.round(c)) and np.all((c >= 0) & (c < wrap))):
            self.rejected += 1
            self._restart()
            return None
        if t <= self._t_last:
            self.rejected += 1  # late: out of order, not used
            return None
        gap = t - self._t_last
        if self._last is None or gap > self.max_gap * self.period + 1e-9 or gap > self._max_unwrap_s:
            if self._last is not None:
                self.rejected += 1
            self._restart(c, t)
            return None
        half = 0.5 * wrap
        step = np.mod(c - self._last + half, wrap) - half  # the nearest change [counts]
        self._sum += step
        moving = step != 0.0
        self._still_since = np.where(
            moving, math.nan, np.where(np.isnan(self._still_since), self._t_last, self._still_since)
        )
        self.stuck &= ~moving  # a counter that moves again is read again
        self._last, self._t_last = c, float(t)
        dt = t - self._start_t
        if dt < self.window - 1e-9:
            return None
        rate = self._sum * self._count_rad / dt
        std = np.full(N_WHEELS, self._count_rad / dt / math.sqrt(6.0))
        out = EncoderWindow(float(t), float(dt), rate, ~self.stuck, std)
        self._sum = np.zeros(N_WHEELS)
        self._start_t = float(t)
        return out

    def check_stuck(self, fisheye_rate, fisheye_valid, t: float, min_rate: float = 1.0) -> None:
        """Mark wheels stuck whose counter stood still for ``stuck_after`` while the fisheye saw them turn.

        Args:
            fisheye_rate: (4,) the fisheye's wheel rates [rad/s].
            fisheye_valid: (4,) which of them it measured.
            t: Their time [s].
            min_rate: The slowest turning the fisheye must see [rad/s].
        """
        seen = np.asarray(fisheye_valid, bool) & (
            np.abs(np.nan_to_num(np.asarray(fisheye_rate, float))) > min_rate
        )
        still = np.isfinite(self._still_since) & (
            t - np.nan_to_num(self._still_since, nan=t) >= self.stuck_after
        )
        self.stuck |= seen & still

    def _restart(self, counts: np.ndarray | None = None, t: float = -math.inf) -> None:
        self._last = counts
        self._t_last = t if counts is not None else self._t_last
        self._start_t = t
        self._sum = np.zeros(N_WHEELS)
