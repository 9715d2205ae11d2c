"""Allan deviation of inertial sensor output and the fit of its three classic noise terms.

The overlapping Allan variance (IEEE Std 952-1997, annex C) of a rate signal sampled every
``dt`` seconds, and a least-squares fit of

    sigma^2(tau) = N^2 / tau + (2 ln 2 / pi) B^2 + K^2 tau / 3

with N the angle (gyro) or velocity (accelerometer) random walk [unit / sqrt(Hz)], B the bias
instability [unit] (the flat floor of the curve is 0.664 B) and K the rate (acceleration) random
walk [unit/s/sqrt(Hz)]. Units follow the signal: rad/s for a gyro, m/s^2 for an accelerometer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: sigma^2 of bias instability B on the flat part of the Allan curve: (2 ln 2 / pi) B^2.
FLICKER_AVAR = 2.0 * math.log(2.0) / math.pi


@dataclass(frozen=True)
class AllanFit:
    """The three noise terms fitted to an Allan curve (units of the signal).

    Attributes:
        random_walk: N, white-noise density [unit/sqrt(Hz)] (sigma at tau = 1 s).
        bias_instability: B [unit]; the curve's floor is 0.664 B.
        bias_random_walk: K [unit/s/sqrt(Hz)] (sigma at tau = 3 s of the +1/2 slope).
    """

    random_walk: float
    bias_instability: float
    bias_random_walk: float


def octave_taus(n: int, dt: float, max_fraction: float = 0.1) -> np.ndarray:
    """Cluster times dt * 2^k [s] up to ``max_fraction`` of the record (``n`` samples)."""
    if not (n >= 2 and dt > 0 and math.isfinite(dt)):
        raise ValueError(f"n={n!r}, dt={dt!r}: need at least 2 samples and a positive, finite dt")
    m = 2 ** np.arange(0, int(math.log2(max(1.0, max_fraction * n))) + 1)
    return m * dt


def allan_deviation(
    rate: np.ndarray, dt: float, taus: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of ``rate`` (n,) or (n, axes) sampled every ``dt`` [s].

    Args:
        rate: Samples [unit]; each column is one axis.
        dt: Sample period [s].
        taus: Cluster times [s], multiples of ``dt`` (default :func:`octave_taus`).

    Returns:
        (taus [s], deviations (len(taus),) or (len(taus), axes) [unit]).

    Raises:
        ValueError: non-finite samples, too few of them, or a tau outside the record.
    """
    x = np.asarray(rate, dtype=np.float64)
    squeeze = x.ndim == 1
    x = x.reshape(len(x), -1)
    n = len(x)
    if n < 3:
        raise ValueError(f"rate: {n} samples; the Allan deviation needs at least 3")
    if not np.all(np.isfinite(x)):
        raise ValueError("rate: contains NaN or infinite samples; remove or flag them first")
    taus = octave_taus(n, dt) if taus is None else np.asarray(taus, dtype=np.float64)
    ms = np.rint(taus / dt).astype(np.int64)
    if np.any(ms < 1) or np.any(2 * ms >= n):
        raise ValueError(f"taus: each must be between dt and half the record ({n * dt / 2:g} s)")
    # the angle (integral of the rate) at every sample; clusters are its differences
    theta = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0) * dt])
    out = np.empty((len(ms), x.shape[1]))
    for i, m in enumerate(ms):
        tau = m * dt
        d = theta[2 * m :] - 2.0 * theta[m:-m] + theta[: -2 * m]
        out[i] = np.sqrt(np.mean(d * d, axis=0) / (2.0 * tau * tau))
    return ms * dt, (out[:, 0] if squeeze else out)


def fit_allan(taus: np.ndarray, adev: np.ndarray, duration: float | None = None) -> AllanFit:
    """Fit N, B and K to one axis's Allan curve by least squares in relative terms.

    Each sigma^2 is weighted by its own inverse and, given the record's ``duration`` [s], by the
    square root of the number of clusters it averages (duration / tau): the relative error of an
    Allan variance falls as one over that root. The three squared coefficients are kept
    non-negative.
    """
    from scipy.optimize import nnls

    t = np.asarray(taus, dtype=np.float64)
    v = np.asarray(adev, dtype=np.float64) ** 2
    if t.shape != v.shape or t.ndim != 1 or len(t) < 3:
        raise ValueError("taus, adev: one curve of at least 3 points, the same length")
    if not (np.all(np.isfinite(v)) and np.all(v > 0)):
        raise ValueError("adev: every deviation must be finite and positive")
    w = 1.0 / v if duration is None else np.sqrt(float(duration) / t) / v
    A = np.column_stack([1.0 / t, np.full_like(t, FLICKER_AVAR), t / 3.0]) * w[:, None]
    coef, _ = nnls(A, v * w)
    n2, b2, k2 = coef
    return AllanFit(math.sqrt(n2), math.sqrt(b2), math.sqrt(k2))
