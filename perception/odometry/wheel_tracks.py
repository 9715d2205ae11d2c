"""The ground the wheels have touched: its height where a downward camera sees it again.

A camera under the body sees the ground between the wheels, a few decimetres off the plane of
their contacts; on rough ground that plane misses the ground in view by a centimetre or more,
a tenth of a fisheye's height above it, and the scale of its odometry by as much. The wheels
themselves touch the ground: where a wheel has rolled, the ground's height is that of its
contact. :class:`WheelTracks` keeps each wheel's contacts (from the kinematics) as a polyline
moved with the body (the odometry's own motion between frames), and gives the height of the
track under any body-frame point on it: the odometry's scale then rests on ground of known
height in view (:class:`perception.odometry.fisheye.FisheyeOdometry`).

Frames: body frame (x forward, y left, z up); points [m], times [s].
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["WheelTracks", "wheel_contacts"]

#: A track's drift is taken as at most this per metre of travel [m/m] (one wrong contact aside) ...
MAX_DRIFT = 0.02
#: ... and fades by this factor each frame it is not measured again.
DRIFT_DECAY = 0.95


def wheel_contacts(wheel_frames, wheel_radius: float, ground_plane) -> np.ndarray:
    """(n, 3) body-frame points where the wheels touch the ground [m].

    Each wheel's lowest point toward the ground: its centre moved one radius along the ground
    plane's downward normal, less the normal's part along the wheel's axle (a cambered wheel
    touches on its rim).

    Args:
        wheel_frames: (R, centre) of each wheel in the body frame, the axle along R's y
            (:meth:`perception.models.rover.RoverKinematicModel.wheel_frames`).
        wheel_radius: [m].
        ground_plane: (a, b, c) of z = a x + b y + c, body frame [-, -, m] (the normal's tilt).
    """
    a, b, _ = (float(v) for v in ground_plane)
    n = np.array([a, b, -1.0]) / math.sqrt(1.0 + a * a + b * b)  # downward normal
    out = []
    for R, centre in wheel_frames:
        axle = np.asarray(R)[:, 1]
        down = n - (n @ axle) * axle
        down /= np.linalg.norm(down)
        out.append(np.asarray(centre, dtype=np.float64) + wheel_radius * down)
    return np.array(out).reshape(-1, 3)


class WheelTracks:
    """Each wheel's contacts over the last ``max_age`` seconds, in the current body frame.

    Args:
        half_width: Half the tread's width [m]: a point within this of a track's centre line,
            across it, lies on the track.
        max_age: Contacts older than this are forgotten [s] (the motion that carries them
            forward accumulates error).
        min_age: Contacts younger than this are not used (the wheel still stands on them,
            its image covers the ground about them) [s].
        max_travel: Contacts that the body has travelled farther than this from are forgotten
            [m] (a track behind the rear wheels is out of view).
        spacing: A frame's contacts are kept only once the body has travelled this far from the
            last kept ones [m] (the tracks are interpolated between them).
    """

    def __init__(
        self,
        half_width: float,
        max_age: float = 2.0,
        min_age: float = 0.1,
        max_travel: float = 1.0,
        spacing: float = 0.03,
    ) -> None:
        if not (half_width > 0 and math.isfinite(half_width)):
            raise ValueError(f"half_width: {half_width!r} m must be > 0")
        if not (0 <= min_age < max_age and math.isfinite(max_age)):
            raise ValueError(f"min_age: {min_age!r}, max_age: {max_age!r}; need 0 <= min_age < max_age")
        if not (max_travel > 0 and spacing >= 0 and math.isfinite(max_travel + spacing)):
            raise ValueError(f"max_travel: {max_travel!r} m must be > 0 and spacing: {spacing!r} m >= 0")
        self.half_width = float(half_width)
        self.max_age = float(max_age)
        self.min_age = float(min_age)
        self.max_travel = float(max_travel)
        self.spacing = float(spacing)
        self.clear()

    def clear(self) -> None:
        """Forget every track (after a frame whose motion is unknown)."""
        self._points: list[np.ndarray] = []  # per wheel (m, 3), oldest first
        self._drift: np.ndarray = np.zeros(0)  # per wheel: the track's height error per metre of travel
        self._times: np.ndarray = np.zeros(0)  # (m,) the contacts' times, shared by the wheels
        self._travel: np.ndarray = np.zeros(0)  # (m,) the body's travel since each contact [m]

    def __len__(self) -> int:
        """The number of contacts kept per wheel."""
        return len(self._times)

    def add(self, t: float, contacts: np.ndarray) -> None:
        """The wheels' contacts (n, 3) at ``t`` [s], body frame [m], in the same wheel order each time."""
        c = np.asarray(contacts, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(c)):
            return
        if self._points and len(self._points) != len(c):
            self.clear()
        if not self._points:
            self._points = [p[None, :] for p in c]
            self._drift = np.zeros(len(c))
        else:
            self._close(float(t), c)
            if self._travel[-1] < self.spacing:  # too near the last kept
                return
            self._points = [np.vstack([p, q[None, :]]) for p, q in zip(self._points, c, strict=True)]
        self._times = np.append(self._times, float(t))
        self._travel = np.append(self._travel, 0.0)
        keep = (self._times >= float(t) - self.max_age) & (self._travel <= self.max_travel)
        if not keep.all():
            self._points = [p[keep] for p in self._points]
            self._times, self._travel = self._times[keep], self._travel[keep]

    def move(self, R: np.ndarray, D: np.ndarray) -> None:
        """The body moved: turned by ``R`` and displaced by ``D`` (both in the old body frame).

        A point P of the old frame is R^T (P - D) in the new one.
        """
        R, D = np.asarray(R, dtype=np.float64), np.asarray(D, dtype=np.float64).reshape(3)
        self._points = [(p - D) @ R for p in self._points]
        self._travel = self._travel + float(np.linalg.norm(D))

    def tracks(self, t: float) -> list[np.ndarray]:
        """Each wheel's contacts at least ``min_age`` old at ``t`` [s]: (m, 3) body-frame points."""
        old = self._times <= t - self.min_age
        return [p[old] for p in self._points]

    def _close(self, t: float, contacts: np.ndarray) -> None:
        """A wheel on another's track closes the loop: the track's height there is the wheel's contact.

        The motion that carried the track errs in height roughly in proportion to the travel
        (the rotation's and the vertical translation's errors add up); the rear wheels follow
        the front wheels' tracks (double Ackermann about the middle), so each contact on an
        older track gives that track's drift per metre, taken out in :meth:`heights_at`.
        """
        z, d, travel, track = self._nearest(contacts[:, :2], t)
        closed = np.zeros(len(self._drift), bool)
        for j in range(len(contacts)):  # wheel j's contact on track i (another wheel's)
            i = int(track[j])
            if i >= 0 and i != j and d[j] <= self.half_width and travel[j] > 0.2:
                new = float(np.clip((z[j] - contacts[j, 2]) / travel[j], -MAX_DRIFT, MAX_DRIFT))
                self._drift[i] = 0.5 * (self._drift[i] + new)  # (one contact's error halved)
                closed[i] = True
        self._drift[~closed] *= DRIFT_DECAY  # a drift not measured again fades

    def heights_at(self, xy: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tracks' heights under body-frame points (n, 2) [m] at time ``t`` [s].

        Returns:
            (z, on, travel): (n,) the height of the track at each point [m] (NaN off every
            track), whether the point lies on one (within ``half_width`` across the centre
            line, between two contacts at least ``min_age`` old), and the body's travel since
            the newer of those two contacts [m] (what the track's error grows with).
        """
        z, d, travel, track = self._nearest(np.asarray(xy, dtype=np.float64).reshape(-1, 2), t)
        if len(self._drift) == 0:  # no tracks
            return z, np.zeros(len(z), bool), travel
        on = d <= self.half_width
        z = np.where(on, z - self._drift[np.maximum(track, 0)] * travel, np.nan)
        return z, on, np.where(on, travel, np.nan)

    def _nearest(self, p: np.ndarray, t: float):
        """The nearest track segment to each point (n, 2).

        Returns its height under the point, the distance across it, the travel since it was laid
        and its track (-1: none within reach), each (n,).
        """
        n = len(p)
        z, d = np.full(n, np.nan), np.full(n, np.inf)
        travel, track = np.full(n, np.nan), np.full(n, -1)
        old = np.flatnonzero(self._times <= t - self.min_age)
        if len(old) < 2 or n == 0 or not self._points:
            return z, d, travel, track
        a = np.vstack([q[old[:-1]] for q in self._points])  # segments between consecutive contacts
        b = np.vstack([q[old[1:]] for q in self._points])
        seg_track = np.repeat(np.arange(len(self._points)), len(old) - 1)
        seg_travel = np.tile(self._travel[old[1:]], len(self._points))
        # only the points near a segment and the segments near a point (a quick cut by boxes)
        reach = self.half_width + 1e-9
        lo, hi = np.minimum(a[:, :2], b[:, :2]) - reach, np.maximum(a[:, :2], b[:, :2]) + reach
        near = np.flatnonzero(np.all((p >= lo.min(axis=0)) & (p <= hi.max(axis=0)), axis=1))
        if len(near) == 0:
            return z, d, travel, track
        q = p[near]
        ab = b[:, :2] - a[:, :2]
        L2 = np.einsum("ij,ij->i", ab, ab)
        ok = (L2 > 1e-10) & np.all((lo <= q.max(axis=0)) & (hi >= q.min(axis=0)), axis=1)
        if not ok.any():
            return z, d, travel, track
        a, b, ab, L2 = a[ok], b[ok], ab[ok], L2[ok]
        ap = q[:, None, :] - a[None, :, :2]  # (m, s, 2)
        u = np.einsum("nsk,sk->ns", ap, ab) / L2
        across = np.abs(ap[..., 0] * ab[None, :, 1] - ap[..., 1] * ab[None, :, 0]) / np.sqrt(L2)
        across = np.where((u >= 0.0) & (u <= 1.0), across, np.inf)
        j = np.argmin(across, axis=1)
        m = np.arange(len(q))
        d[near] = across[m, j]
        z[near] = a[j, 2] + u[m, j] * (b[j, 2] - a[j, 2])
        travel[near] = seg_travel[ok][j]
        track[near] = np.where(np.isfinite(d[near]), seg_track[ok][j], -1)
        return z, d, travel, track
