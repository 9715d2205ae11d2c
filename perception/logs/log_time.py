"""Times of a robot log's messages: header stamps, with the log's receive times as the witness.

Two things can be wrong with a message's time in a real log: its header stamp (a driver's
clock glitches for one message, or is set back or forward and stays there), or its receive
time (the recorder stalls and catches up in a burst, its host's clock steps, messages arrive
late). Receive delays are never negative, so a stream's *base* offset (receive time less stamp)
is its smallest one; stalls and jitter only raise offsets for a while. The stamps are the clock;
the receive times vouch for them.

:func:`place` looks at a whole stream (the stamps and receive times of a topic, read before its
images are decoded) and places every message on the log's time line:

- **order**: messages received close together whose stamps are inverted, and whose offsets
  agree, are put back in stamp order (a recorder or transport that swapped them, receive delays
  that scattered them); close: within three periods, or the spread of the stream's receive
  delays where that is wider. One recorded twice (the same stamp and content) is read once;
- **accepted**: a stamp that moves forward and agrees with the receive time (its step within
  :data:`STAMP_TOLERANCE` of the receive time's step, or its offset within it of the base), or
  steps like the recent stamps (at most 2.5 periods) while the receive time hiccups;
- **unsure**: an accepted stamp that steps over a gap (more than 2.5 periods) the receive time
  does not show: the message keeps its time, the pair across the gap is not trusted;
- **flagged**: a stamp that goes backward, repeats, or jumps while the receive time does not,
  or one out of line with the messages before and after it (the messages after continue from
  the last good one). It gets a time between its accepted neighbours' and the caller makes its
  row invalid;
- **a new clock**: a flagged stamp that the next messages (five at least) continue from, where
  the stream's base offset after it differs from the base before it: by more than twice the
  spread of the recent delays for a stamp that went back, by more than the tolerance for one
  that ran ahead of the receive time (a clock set back or forward that stays there). A
  stamp that moved forward no further than the receive time (a drop-out while the recorder
  stalled, or while its clock stepped), one that moved forward while the recorder wrote a burst
  (receive steps far below the stamp steps: the receive time says nothing then) or a base that
  comes back is no jump: the stamps are kept. After a jump the stamps are shifted by the change
  of the base offsets, so the time line stays continuous;
- the time line is the stamp clock in effect at the end of the stream (after a start-up clock
  correction, the corrected one), so that streams on one clock (a camera and an IMU) share it
  whatever each of them dropped;
- stamps that do not move for most of the stream (a driver that never sets them) give way to the
  receive times, with a warning.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Largest disagreement between a stamp step and the receive time's step, or between a
#: message's clock offset (receive time less stamp) and the recent messages', for the receive
#: time to vouch for the stamp [s]. Transport and recording delays stay well below it.
STAMP_TOLERANCE = 0.5
#: How far ahead the base offset after a suspected clock jump is looked for: messages, and
#: seconds of receive time (a recorder stall's burst must drain within it).
_JUMP_WINDOW = (100, 5.0)


@dataclass(frozen=True)
class Placed:
    """A message placed on the log's time line.

    Attributes:
        item: The message (anything with ``stamp`` and ``recv`` [s]).
        t: Its time on the log's time line [s]; for a flagged message a time between its
            accepted neighbours', or NaN where there is none (before the first accepted one).
        why: Why its stamp is flagged ("" if it is not).
        anchor: The message starts a new clock segment: the pair across the jump is unknown,
            and the messages after it are timed from it.
    """

    item: Any
    t: float
    why: str = ""
    anchor: bool = False


def in_stamp_order(
    items: Sequence[Any], same: Callable[[Any, Any], bool] | None = None, tolerance: float = STAMP_TOLERANCE
) -> list[Any]:
    """``items`` (in the log's receive order) with close neighbours put back in stamp order.

    Two messages swap when their stamps are inverted, they were received within a window of
    each other and their clock offsets agree: a recorder or a transport that swapped them, or
    receive delays that scatter them. The window is three of the stream's periods, or the
    spread of its receive delays where that is wider (:func:`_delay_spread`); the offsets must
    agree within 3.5 periods (and ``tolerance`` [s]) or that spread. Others keep their order,
    for :func:`place` to judge: on a stream with steady delays a clock set back by a fraction
    of a second is not shuffled into the frames before it. A message recorded twice (the same
    stamp, and ``same(a, b)`` true) is dropped, with one warning for all of them.

    Args:
        items: Objects with ``stamp`` and ``recv`` [s].
        same: Whether two messages of one stamp are one message recorded twice.
        tolerance: See :data:`STAMP_TOLERANCE` [s].
    """
    out = list(items)
    s = np.array([float(x.stamp) for x in out])
    r = np.array([float(x.recv) for x in out])
    ok = np.isfinite(s) & np.isfinite(r)
    steps = np.diff(np.sort(s[ok]))
    steps = steps[steps > 0]
    period = float(np.median(steps)) if len(steps) else 0.0
    spread = _delay_spread(r[ok] - s[ok])
    window = max(3.0 * period, spread)
    agree = max(min(tolerance, 3.5 * period), spread)
    for i in range(1, len(out)):  # insertion steps, each bounded by the receive window
        j = i
        while j > 0:
            a, b = out[j - 1], out[j]
            sa, sb, ra, rb = float(a.stamp), float(b.stamp), float(a.recv), float(b.recv)
            close = 0 <= rb - ra < window and abs((rb - sb) - (ra - sa)) <= agree
            if not (sb < sa and close):
                break
            out[j - 1], out[j] = b, a
            j -= 1
    if same is None:
        return out
    kept: list[Any] = []
    dropped = 0
    for x in out:
        if kept and x.stamp == kept[-1].stamp and same(x, kept[-1]):
            dropped += 1
            continue
        kept.append(x)
    if dropped:
        log.warning("%d messages recorded twice (the same stamp and content) are read once", dropped)
    return kept


def _delay_spread(offsets: np.ndarray) -> float:
    """How widely a stream's receive delays spread [s]: 3.5 times the median delay above the base.

    The base is the 10th percentile of the offsets of the 21 messages around each (a glitched
    stamp or two, or a clock jump, disturb only their neighbours); for delays spread evenly
    over [0, J] this gives about 1.4 J. At most 5 s.
    """
    if len(offsets) < 5:
        return 0.0
    from scipy.ndimage import percentile_filter

    delay = offsets - percentile_filter(offsets, 10, size=21, mode="nearest")
    return min(3.5 * float(np.median(np.maximum(delay, 0.0))), 5.0)


class _Line:
    """The running state of :func:`place`: the last accepted message and the stream's base offset.

    The base is the smallest clock offset (receive time less stamp) of the accepted messages
    since the last clock jump: receive delays are never negative, so stalls and jitter never
    lower it. Ten accepted messages in a row whose offsets agree within 0.1 s but sit above the
    base by more than the tolerance are a receive clock that stepped forward: the base moves up
    to them (a stall's burst, whose offsets fall message by message, is not one).
    """

    def __init__(self, s: np.ndarray, r: np.ndarray, tol: float) -> None:
        self.s, self.r, self.tol = s, r, tol
        steps = np.diff(s)
        steps = steps[np.isfinite(steps) & (steps > 0)]
        self.period = float(np.median(steps)) if len(steps) else math.inf
        self.last: int | None = None  # the last accepted message
        self.prev: int | None = None  # the one before it
        self.steps: list[float] = []  # the last accepted stamp steps [s]
        self.floor = math.inf  # the base offset [s]
        self.high: list[float] = []  # offsets of the accepted messages above the base, in a row
        self.spread: list[float] = []  # offsets of the last accepted messages
        self.shift = 0.0  # added to the current segment's stamps [s]

    def offset(self, i: int) -> float:
        return float(self.r[i] - self.s[i])

    def normal(self, ds: float) -> bool:
        """A stamp step like the stream's own lately (a frame period, or a few dropped)."""
        period = float(np.median(self.steps)) if len(self.steps) >= 3 else self.period
        return 0 < ds <= 2.5 * period + 1e-3

    def dev(self, i: int) -> float:
        """How far message ``i``'s clock offset is from the base [s] (0 before there is one)."""
        return abs(self.offset(i) - self.floor) if math.isfinite(self.floor) else 0.0

    def follows(self, a: int, b: int) -> bool:
        """Message ``b``'s stamp continues message ``a``'s clock."""
        ds, dr = self.s[b] - self.s[a], self.r[b] - self.r[a]
        return ds > 0 and (abs(ds - dr) <= self.tol or self.normal(ds))

    def base(self, idx: list[int]) -> float:
        """The base offset of messages ``idx``: their second smallest (robust to one odd one) [s]."""
        o = sorted(self.offset(i) for i in idx)
        return o[1] if len(o) > 2 else o[0]

    def bursting(self) -> bool:
        """The last accepted message came in a burst: its receive step far below its stamp step."""
        if self.last is None or self.prev is None:
            return False
        ds = self.s[self.last] - self.s[self.prev]
        dr = self.r[self.last] - self.r[self.prev]
        return bool(ds > 0 and dr < 0.25 * ds)

    def noise(self) -> float:
        """How far above the base the recent accepted messages' offsets spread (90th percentile) [s]."""
        if len(self.spread) < 5 or not math.isfinite(self.floor):
            return self.tol
        return float(np.percentile(np.asarray(self.spread) - self.floor, 90))

    def accept(self, i: int, t: np.ndarray, ti: float, step: bool = True) -> None:
        if self.last is not None and step:
            self.steps = [*self.steps[-6:], float(self.s[i] - self.s[self.last])]
        t[i] = ti
        self.prev, self.last = self.last, i
        o = self.offset(i)
        self.spread = [*self.spread[-29:], o]
        if o <= self.floor + self.tol:
            self.floor = min(self.floor, o)
            self.high.clear()
            return
        self.high.append(o)
        if len(self.high) >= 10:
            recent = self.high[-10:]
            level = max(recent) - min(recent) <= min(self.tol, 0.1)
            draining = all(b < a for a, b in zip(recent, recent[1:]))  # a burst: each later one lower
            if level and not draining:  # the receive clock stepped forward
                self.floor = min(recent)
                self.high.clear()

    def restart(self, base: float) -> None:
        """A new clock segment with this base offset."""
        self.floor = base
        self.high.clear()
        self.spread.clear()


def place(items: Sequence[Any], tolerance: float = STAMP_TOLERANCE, name: str = "") -> list[Placed]:
    """Every message of a stream placed on the log's time line (see the module's rules).

    Args:
        items: The stream's messages in order (:func:`in_stamp_order`), each with ``stamp`` and
            ``recv`` [s].
        tolerance: See :data:`STAMP_TOLERANCE` [s].
        name: The stream (a topic), for the warnings.

    Returns:
        One :class:`Placed` per item, in the same order. Accepted messages have strictly
        increasing times; flagged ones lie between their accepted neighbours'.
    """
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance: {tolerance!r} s; give a positive time")
    n = len(items)
    s = np.array([float(x.stamp) for x in items], dtype=np.float64)
    r = np.array([float(x.recv) for x in items], dtype=np.float64)
    if n >= 3:
        ds = np.diff(s)
        if np.mean(ds[np.isfinite(ds)] == 0) > 0.5 and np.all(np.diff(r) >= 0):
            log.warning(
                "%s: the header stamps do not change over most of the stream; the receive times are used",
                name or "log",
            )
            s = r.copy()
    line = _Line(s, r, tolerance)
    t = np.full(n, math.nan)
    why = [""] * n
    anchor = [False] * n
    ok = np.isfinite(s) & np.isfinite(r)
    good = [i for i in range(n) if ok[i]]
    for k, i in enumerate(good):
        ahead = good[k + 1 : k + 3]
        if line.last is None:
            # the line starts at the first message the next ones do not disown
            if len(ahead) >= 2 and not line.follows(i, ahead[0]) and line.follows(ahead[0], ahead[1]):
                why[i] = f"header stamp {s[i]:.6f} s disagrees with the next messages'"
                continue
            line.accept(i, t, s[i])
            continue
        a = line.last
        ds, dr = s[i] - s[a], r[i] - r[a]
        accept = ds > 0 and (abs(ds - dr) <= tolerance or line.dev(i) <= tolerance or line.normal(ds))
        if accept and ahead:
            j = ahead[0]
            if (
                not line.normal(ds)
                and line.follows(a, j)
                and not line.follows(i, j)
                and line.dev(i) > line.dev(j)
            ):
                accept = False  # an odd stamp step; the next message follows the last good one: a glitch
        if accept:
            unsure = not line.normal(ds) and abs(ds - dr) > max(2.0 * line.noise(), 0.05)
            line.accept(i, t, s[i] + line.shift)
            if unsure:  # a gap the receive time does not show: the frame stands, the pair across does not
                why[i] = f"header stamp steps {ds:.3f} s where the receive time steps {dr:.3f} s: unsure pair"
                anchor[i] = True
            continue
        if ds > 0 and line.dev(i) <= tolerance:
            why[i] = f"header stamp {s[i]:.6f} s is out of line with the messages before and after it"
        elif ds == 0:
            why[i] = f"header stamp {s[i]:.6f} s repeats the last good message's"
        elif ds < 0:
            why[i] = f"header stamp {s[i]:.6f} s goes back {-ds:.3f} s from the last good message's"
        else:
            why[i] = f"header stamp steps {ds:.3f} s where the receive time steps {dr:.3f} s"
        if not ahead or line.follows(a, ahead[0]) or not line.follows(i, ahead[0]):
            continue  # an isolated glitch: the next message follows the last good one (or none)
        # the next messages continue from this stamp: a new clock, unless the base offset comes back
        chain = [i]
        for j in good[k + 1 :]:
            if len(chain) >= _JUMP_WINDOW[0] or r[j] - r[i] > _JUMP_WINDOW[1]:
                break
            if line.follows(chain[-1], j):
                chain.append(j)
        if len(chain) < 5:
            continue  # too few messages after it to tell a new clock from a glitch: flagged
        base_after = line.base(chain)
        jump = base_after - (line.floor if math.isfinite(line.floor) else line.offset(a))
        if ds > 0 and (abs(jump) <= tolerance or ds - dr <= tolerance or line.bursting()):
            # the stamps moved forward, no further than the receive time (a drop-out while the
            # recorder stalled or its clock stepped), or while the recorder wrote a burst (its
            # receive times say nothing), or the base came back: the stamps hold
            why[i] = ""
            line.accept(i, t, s[i] + line.shift)
            if abs(jump) > tolerance:
                line.restart(base_after)
            continue
        if ds <= 0 and jump <= max(2.0 * line.noise(), 0.01):
            continue  # going back, the base moved less than the delays' spread: out of order, no new clock
        old = line.shift
        new = old + jump
        if not s[i] + new > t[a]:  # keep the line moving forward
            new = t[a] + max(dr, line.period if math.isfinite(line.period) else 1e-3) - s[i]
        line.shift = new
        line.restart(base_after)
        line.accept(i, t, s[i] + new, step=False)
        why[i] += ": the clock jumps here"
        anchor[i] = True
        log.warning(
            "%s: the header clock jumps at stamp %.6f s; the stamps from there on are shifted by %+.3f s "
            "(the change of the base receive delay)", name or "log", s[i], new - old,
        )  # fmt: skip
    t -= line.shift  # the time line is the clock in effect at the end of the stream
    _fill_flagged(t, why, r, anchor)
    for i in range(n):
        if not ok[i]:
            why[i] = f"stamp {items[i].stamp!r} s or receive time {items[i].recv!r} s is not a finite time"
    return [Placed(items[i], float(t[i]), why[i], anchor[i]) for i in range(n)]


def _fill_flagged(t: np.ndarray, why: list[str], r: np.ndarray, anchor: list[bool]) -> None:
    """Times of the flagged messages: evenly between their placed neighbours'.

    After the last placed message, on the receive clock while it moves forward. Anchors keep the
    times their stamps give.
    """
    acc = [i for i in range(len(t)) if (anchor[i] or not why[i]) and math.isfinite(t[i])]
    for a, b in zip([None, *acc], [*acc, None]):
        lo = (a + 1) if a is not None else 0
        hi = b if b is not None else len(t)
        gap = [i for i in range(lo, hi) if why[i] and not anchor[i]]
        if not gap or a is None:
            continue  # before the first accepted message there is no time line yet
        if b is None:  # after the last accepted one: on the receive clock, kept increasing
            prev = t[a]
            for i in gap:
                ti = t[a] + (r[i] - r[a])
                t[i] = ti if ti > prev else math.nan
                prev = t[i] if math.isfinite(t[i]) else prev
            continue
        for m, i in enumerate(gap, start=1):  # evenly between the two accepted times
            t[i] = t[a] + (t[b] - t[a]) * m / (len(gap) + 1)
