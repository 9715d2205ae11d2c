"""Times of a robot log's messages: header stamps, with the log's receive times as the witness.

Two things can be wrong with a message's time in a real log: its header stamp (a camera driver's
clock glitches for one frame, or is set back or forward and stays there), or its receive time
(the recorder stalls and catches up, its host's clock steps, messages arrive in bursts). The
stamps are the primary clock; the receive times only vouch for them:

- :func:`in_stamp_order` puts messages a recorder stored slightly out of order back in stamp
  order, where their clock offsets (receive time less stamp) agree;
- :class:`StampClock` places each message on the log's time line. A stamp that moves forward
  by what the receive time moved (within :data:`STAMP_TOLERANCE`), or by a step like the
  recent ones while the receive time hiccups, is accepted. A stamp that goes backward, repeats,
  or jumps while the receive time does not is *flagged*, unless the messages after it continue
  from it: then the clock jumped there, and the stamps from then on are shifted onto the time
  line by the jump measured on the receive clock.

Both take any objects with ``stamp`` and ``recv`` attributes [s] (image frames, IMU samples).
"""

from __future__ import annotations

import heapq
import logging
import math
import statistics
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Largest disagreement between a message's clock offset (receive time less stamp) and the
#: recent messages' before the receive time stops vouching for its stamp [s]. Transport and
#: recording delays stay well below it.
STAMP_TOLERANCE = 0.5
#: Largest stamp step accepted without the receive time's support before the message period is
#: known (the first few messages) [s].
MAX_BLIND_STEP = 5.0
#: Messages whose offsets make the running median.
_HISTORY = 15


@dataclass(frozen=True)
class Placed:
    """A message placed on the log's time line.

    Attributes:
        item: The message (anything with ``stamp`` and ``recv`` [s]).
        t: Its time on the log's time line [s]; for a flagged message an estimate from its receive
            time that lies between its neighbours' times, or NaN where there is none.
        why: Why its stamp is flagged ("" if it is not).
        anchor: The message starts a new clock segment: its time is an estimate (the pair
            across the jump is unknown), and the messages after it are timed from it.
    """

    item: Any
    t: float
    why: str = ""
    anchor: bool = False


class StampClock:
    """Places messages on a time line from their header stamps, the receive times vouching.

    Args:
        tolerance: See :data:`STAMP_TOLERANCE` [s].
        name: What the messages are (a topic), for the warnings.
    """

    def __init__(self, tolerance: float = STAMP_TOLERANCE, name: str = "") -> None:
        if not (math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"tolerance: {tolerance!r} s; give a positive time")
        self.tolerance = tolerance
        self.name = name
        self._last: tuple[float, float, float] | None = None  # stamp, receive, time of the last accepted
        self._offsets: deque[float] = deque(maxlen=_HISTORY)  # receive less stamp, accepted messages
        self._steps: deque[float] = deque(maxlen=_HISTORY)  # stamp steps between accepted messages
        self.shift = 0.0  # added to the current segment's stamps [s]
        self.jumps = 0
        self.flagged = 0
        self.receive_only = False  # the stamps never move: the receive times are used instead

    # ------------------------------------------------------------------ rules
    def _normal_step(self) -> float:
        """The largest stamp step taken without the receive time's support [s]."""
        if len(self._steps) < 3:
            return MAX_BLIND_STEP
        return 2.5 * statistics.median(self._steps) + 1e-3

    def _vouched(self, stamp: float, recv: float) -> bool:
        """The receive time agrees with the stamp (the offset is the recent messages')."""
        return self._deviation(stamp, recv) <= self.tolerance

    def _deviation(self, stamp: float, recv: float) -> float:
        """How far a message's clock offset is from the recent messages' [s]."""
        return abs((recv - stamp) - statistics.median(self._offsets)) if self._offsets else 0.0

    def _continues(self, s0: float, r0: float, stamp: float, recv: float) -> bool:
        """A message at (stamp, recv) follows one at (s0, r0) on the same clock."""
        ds, dr = stamp - s0, recv - r0
        if ds <= 0:
            return False
        return (dr > 0 and abs(ds - dr) <= self.tolerance) or ds <= self._normal_step()

    def _accept(self, stamp: float, recv: float, t: float, step: bool = True) -> None:
        if self._last is not None and step:
            self._steps.append(stamp - self._last[0])
        self._last = (stamp, recv, t)
        self._offsets.append(recv - stamp)

    # ------------------------------------------------------------------ placing
    def run(self, items: Iterable[Any], lookahead: int = 2) -> Iterator[Placed]:
        """Each of ``items`` (in the log's order) placed on the time line, in the same order.

        Accepted messages have strictly increasing times. Flagged ones get a time between their
        neighbours' where one can be estimated (NaN otherwise); the caller makes their rows
        invalid.
        """
        it = iter(items)
        ahead: deque[Any] = deque()

        def fill() -> None:
            while len(ahead) < lookahead + 1:
                nxt = next(it, None)
                if nxt is None:
                    return
                ahead.append(nxt)

        fill()
        self._check_constant(list(ahead))
        while ahead:
            item = ahead.popleft()
            fill()
            yield self._place(item, list(ahead))

    def _check_constant(self, first: list) -> None:
        """Stamps that do not move over the first messages while the receive times do: use the latter."""
        if len(first) < 3:
            return
        stamps = {float(x.stamp) for x in first}
        recvs = [float(x.recv) for x in first]
        if len(stamps) == 1 and all(b > a for a, b in zip(recvs, recvs[1:])):
            self.receive_only = True
            log.warning(
                "%s: the header stamps do not change (%.6f s); the receive times are used instead",
                self.name or "log", stamps.pop(),
            )  # fmt: skip

    def _times(self, item) -> tuple[float, float]:
        recv = float(item.recv)
        return (recv if self.receive_only else float(item.stamp)), recv

    def _place(self, item, ahead: list) -> Placed:
        stamp, recv = self._times(item)
        if not (math.isfinite(stamp) and math.isfinite(recv)):
            self.flagged += 1
            return Placed(
                item, math.nan, f"stamp {stamp!r} s or receive time {recv!r} s is not a finite time"
            )
        nxt = [self._times(a) for a in ahead]
        if self._last is None:  # the first message: the line starts there unless the next ones disown it
            if (
                len(nxt) >= 2
                and not self._continues(stamp, recv, *nxt[0])
                and self._continues(*nxt[0], *nxt[1])
            ):
                self.flagged += 1
                return Placed(item, math.nan, f"header stamp {stamp:.6f} s disagrees with the next messages'")
            self._accept(stamp, recv, stamp)
            return Placed(item, stamp)
        s0, r0, t0 = self._last
        ds = stamp - s0
        ok = ds > 0 and (self._vouched(stamp, recv) or ds <= self._normal_step())
        if (
            ok
            and nxt
            and self._continues(s0, r0, *nxt[0])
            and not self._continues(stamp, recv, *nxt[0])
            and self._deviation(stamp, recv) > self._deviation(*nxt[0])
        ):
            ok = False  # the next message follows the last good one, not this: a glitch within tolerance
        if ok:
            t = stamp + self.shift
            self._accept(stamp, recv, t)
            return Placed(item, t)
        # the stamp is out of line: an isolated glitch, or the start of a new clock
        self.flagged += 1
        dr = recv - r0
        if ds > 0 and ok is False and self._vouched(stamp, recv):
            why = f"header stamp {stamp:.6f} s is out of line with the messages before and after it"
        elif ds == 0:
            why = f"header stamp {stamp:.6f} s repeats the last good message's"
        elif ds < 0:
            why = f"header stamp {stamp:.6f} s goes back {-ds:.3f} s from the last good message's"
        else:
            why = f"header stamp steps {ds:.3f} s where the receive time steps {dr:.3f} s"
        if nxt and not self._continues(s0, r0, *nxt[0]) and self._continues(stamp, recv, *nxt[0]):
            step = statistics.median(self._steps) if self._steps else 0.0
            t = t0 + (dr if dr > 0 else max(step, 1e-6))
            old, self.shift = self.shift, t - stamp
            self.jumps += 1
            self._accept(stamp, recv, t, step=False)
            self._offsets.clear()
            self._offsets.append(recv - stamp)
            log.warning(
                "%s: the header clock jumps at stamp %.6f s; the stamps from there on are shifted by %+.3f s "
                "onto the log's time line (measured on the receive clock)",
                self.name or "log", stamp, self.shift - old,
            )  # fmt: skip
            return Placed(item, t, f"{why}: the clock jumps here", anchor=True)
        # an isolated glitch: a time between its neighbours', from the receive clock
        t = t0 + dr if dr > 0 else math.nan
        if nxt and self._continues(s0, r0, *nxt[0]):
            t_next = nxt[0][0] + self.shift
            if not t0 < t < t_next:
                t = 0.5 * (t0 + t_next)
        return Placed(item, t, why)


def in_stamp_order(
    items: Iterable[Any], tolerance: float = STAMP_TOLERANCE, same=None, max_held: int = 32
) -> Iterator[Any]:
    """``items`` (in the log's receive order) in header-stamp order, where the receive time vouches for it.

    An item whose clock offset (receive time less stamp) is within ``tolerance`` [s] of the
    recent items' median is held for ``tolerance`` seconds of stamp time and released in stamp
    order: items a recorder stored slightly out of order are put back in order. An item whose
    offset is not (a glitched stamp, a clock that jumped) passes through where it was received,
    for :class:`StampClock` to judge; three such items that agree with each other are a new
    clock, whose items are then ordered like the first's.

    Args:
        items: Objects with ``stamp`` and ``recv`` [s].
        tolerance: See :data:`STAMP_TOLERANCE` [s].
        same: ``same(a, b)`` says whether two items of the same stamp are one message recorded
            twice; the second is then dropped (counted in one warning).
        max_held: Most items held at once (a memory bound for large images at high rates).
    """
    held: list[tuple[float, int, Any]] = []
    offsets: deque[float] = deque(maxlen=_HISTORY)
    odd: list[float] = []  # offsets of the items since the last one that agreed
    last = None
    dropped = 0

    def release(item):
        nonlocal last, dropped
        if same is not None and last is not None and item.stamp == last.stamp and same(item, last):
            dropped += 1
            return False
        last = item
        return True

    for seq, item in enumerate(items):
        off = float(item.recv) - float(item.stamp)
        agrees = not offsets or abs(off - statistics.median(offsets)) <= tolerance
        if math.isfinite(off) and not agrees:
            odd.append(off)
            if len(odd) >= 3 and max(odd[-3:]) - min(odd[-3:]) <= tolerance:
                offsets.clear()
                offsets.extend(odd[-3:])  # a new clock: its items from here on are ordered
                agrees = True
        if not (math.isfinite(off) and agrees):
            while held:
                x = heapq.heappop(held)[2]
                if release(x):
                    yield x
            if release(item):
                yield item
            continue
        odd = []
        offsets.append(off)
        heapq.heappush(held, (float(item.stamp), seq, item))
        while held and (held[0][0] <= float(item.stamp) - tolerance or len(held) > max_held):
            x = heapq.heappop(held)[2]
            if release(x):
                yield x
    while held:
        x = heapq.heappop(held)[2]
        if release(x):
            yield x
    if dropped:
        log.warning("%d messages recorded twice (the same stamp and content) were read once", dropped)


def same_image(a, b) -> bool:
    """Two frames hold the same image (for :func:`in_stamp_order`'s ``same``)."""
    ia, ib = getattr(a, "image", None), getattr(b, "image", None)
    return ia is not None and ib is not None and ia.shape == ib.shape and bool(np.array_equal(ia, ib))
