"""The soil's pull curve, identified on board: drawbar pull over load against slip.

What a wheel on soil can pull at a slip, its drawbar pull over its load (DP/W), is the thrust of
the soil's shear less the resistance of the soil it compacts. The motors' torques give the
first, per wheel; nothing on board measures the second per wheel. This module separates them
with a model of the wheel in soil and the one force sensor on board that sees the pulls, the
accelerometer, which reads their sum:

- **Per wheel** (a semi-empirical reduction of Wong and Reece's rigid wheel; the figures below
  are fitted to the model's steady states of five soils, ``docs/soil_estimation.md``):

      DP / W = (1 - eps) T / (r W) - a z / r

  T the wheel's torque [N m], r its radius, W its load [N], z its sinkage [m]. ``eps`` is the
  part of the shear's torque that does not push forward (the contact arc's slope: 0.118
  driving, 0.03 braking); ``a`` is the soil's resistance per unit of relative sinkage, which
  depends on the soil (0.29-0.37 on sands, 0.91 on the CMU test bed's soil) and is identified.
  Over loads 70-140 N and slips 0.02-0.8 this holds to 0.005-0.015 rms (0.02-0.034 at worst).
- **A wheel in another's rut** (the rear wheels of a rover driving straight) pulls on soil that
  is pressed and sheared already; its resistance is taken as ``b0 + b1 T / (r W)`` of its load,
  ``b0`` and ``b1`` identified with a prior (:class:`SoilIdConfig`). Which wheels are in a rut
  comes from the wheels' own tracks: a wheel whose centre passes within ``rut_clearance`` of
  the track another wheel left over the last ``track_memory`` metres is in its rut (a rover
  crabbing, or turning so that its tracks part, has all four wheels on fresh soil).
- **The rover's balance**: the pulls sum to the mass times the specific force along the travel
  (the accelerometer's, gravity included: a climb reads as the pull it takes). Each control
  step with the four torques, the loads and the fresh wheels' sinkages is one linear equation
  in ``a``, ``b0`` and ``b1``; they are solved by Bayesian least squares over the last
  ``memory`` metres of travel.
- **The curve**: the fresh driving wheels' T / (r W) against slip is fitted by a saturating
  thrust, ``tau0 + A (1 - exp(-s / B))``, and their relative sinkage by a quadratic in slip;
  DP/W(s) follows. The loads come from the mass, the specific force and the body's height
  (the load it moves between the axles); each axle's is shared equally by its wheels (the
  axles roll freely).

Outputs (:class:`SoilCurveEstimate`): the DP/W curve over slips 0-0.95 with its standard
deviation, each wheel's DP/W at its slip (driving slips only: braking is not identified), the
slips of largest DP/W and largest tractive efficiency DP (1 - s) / (T / r), and a quality: the
share of the slips 0.05-0.7 where the curve's standard deviation is at most
``quality_std``.

Frames: body frame (x forward, y left, z up); the wheels' tracks in the odometry frame.
Wheel order FL, FR, RL, RR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from perception.models.validation import ConfigError

__all__ = ["SoilCurveEstimate", "SoilIdConfig", "SoilIdentifier", "SLIPS"]

#: The slips the curve is given at [-].
SLIPS = np.linspace(0.0, 0.95, 96)
#: The slips the quality is judged over [-].
_JUDGED = (SLIPS >= 0.05 - 1e-9) & (SLIPS <= 0.7 + 1e-9)
#: The thrust's saturation slips tried [-].
_B_GRID = np.geomspace(0.04, 2.0, 40)


@dataclass(frozen=True)
class SoilIdConfig:
    """Figures of the soil identification (:mod:`perception.fusion.soil`).

    Attributes:
        thrust_loss: ``eps`` of a driving wheel [-] (fitted to the Wong-Reece model's steady
            states of five soils, loads 70-140 N, slips 0.02-0.8).
        thrust_loss_braking: ``eps`` of a braking wheel [-] (slips -0.6 to -0.03).
        resistance_prior: Mean and standard deviation of the prior on ``a`` [-] (wide: the
            balance identifies it).
        rut_resistance_prior: Mean and standard deviation of ``b0`` [-]: a wheel in a rut
            resists with 0-0.08 of its load in the model's second passes.
        rut_torque_prior: Mean and standard deviation of ``b1`` [-] (-0.2 to 0 there).
        force_std: Standard deviation of one step's balance [N]: the accelerometer's noise
            over a step, the wheels' and the body's inertia, and the model's error.
        memory: Travel over which the measurements count [m] (the soil may change).
        track_memory: Travel over which a wheel's track counts as a rut [m].
        rut_clearance: A wheel is in a rut where its centre passes within this of another
            wheel's track [m] (about a wheel's width).
        track_step: The tracks keep a point every this much travel [m].
        min_speed: Below this ground speed nothing is measured [m/s].
        min_samples: Fresh driving samples (wheel-steps) and balance steps needed before a
            curve is given.
        min_slip_span: The fresh driving wheels' slips must span this much [-].
        quality_std: The curve's standard deviation at which a slip counts as identified [-].
        refit_travel: The curve is refitted after this much travel [m].
        gap_slope: The curve's standard deviation grows by this per unit of slip away from the
            nearest measured slip [-] (about the curves' slope at mid-slip).
        model_std: The per-wheel model's own error in DP/W [-] (its rms over the five soils'
            steady states, 0.005-0.015), added to the fits' spread.
    """

    thrust_loss: float = 0.118
    thrust_loss_braking: float = 0.03
    resistance_prior: tuple[float, float] = (0.5, 1.0)
    rut_resistance_prior: tuple[float, float] = (0.04, 0.04)
    rut_torque_prior: tuple[float, float] = (-0.1, 0.1)
    force_std: float = 6.0
    memory: float = 30.0
    track_memory: float = 3.0
    rut_clearance: float = 0.06
    track_step: float = 0.01
    min_speed: float = 0.03
    min_samples: int = 30
    min_slip_span: float = 0.2
    quality_std: float = 0.025
    refit_travel: float = 0.1
    gap_slope: float = 0.5
    model_std: float = 0.015

    def __post_init__(self) -> None:
        for name in (
            "force_std",
            "memory",
            "track_memory",
            "rut_clearance",
            "track_step",
            "quality_std",
            "refit_travel",
            "gap_slope",
            "model_std",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"SoilIdConfig.{name}: {v!r}; give a positive number")
        for name in ("thrust_loss", "thrust_loss_braking", "min_speed", "min_slip_span"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v < 1):
                raise ConfigError(f"SoilIdConfig.{name}: {v!r}; give a number in [0, 1)")
        for name in ("resistance_prior", "rut_resistance_prior", "rut_torque_prior"):
            m, s = getattr(self, name)
            if not (math.isfinite(m) and math.isfinite(s) and s > 0):
                raise ConfigError(f"SoilIdConfig.{name}: {(m, s)!r}; give (mean, std > 0)")
        if self.min_samples < 3:
            raise ConfigError(f"SoilIdConfig.min_samples: {self.min_samples!r}; give at least 3")


@dataclass
class SoilCurveEstimate:
    """The identified pull curve (see the module docstring).

    Attributes:
        slips: The slips the curve is given at, :data:`SLIPS` [-].
        pull_ratio: DP/W at each of them [-]; NaN before the first identification.
        pull_ratio_std: Its standard deviation [-].
        wheel_pull_ratio: (4,) DP/W at each wheel's slip (NaN: not identified, slip unknown or
            braking) [-].
        slip_best_pull: The slip of the largest DP/W [-] (NaN: not identified).
        slip_best_efficiency: The slip of the largest tractive efficiency [-] (NaN: none).
        quality: Share of the slips 0.05-0.7 where the standard deviation is at most
            ``quality_std`` [0, 1].
        resistance: The identified ``a`` and its standard deviation [-].
        travel: The travel the measurements span [m].
    """

    slips: np.ndarray = field(default_factory=lambda: SLIPS.copy())
    pull_ratio: np.ndarray = field(default_factory=lambda: np.full(SLIPS.shape, np.nan))
    pull_ratio_std: np.ndarray = field(default_factory=lambda: np.full(SLIPS.shape, np.inf))
    wheel_pull_ratio: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    slip_best_pull: float = math.nan
    slip_best_efficiency: float = math.nan
    quality: float = 0.0
    resistance: tuple[float, float] = (math.nan, math.inf)
    travel: float = 0.0

    @property
    def identified(self) -> bool:
        """Whether a curve has been identified."""
        return bool(np.isfinite(self.pull_ratio).any())


def _thrust_fit(s: np.ndarray, tau: np.ndarray):
    """The saturating thrust through (s, tau): (B, (tau0, A), covariance, residual variance)."""
    best = None
    for B in _B_GRID:
        X = np.stack([np.ones_like(s), 1.0 - np.exp(-s / B)], axis=1)
        c, *_ = np.linalg.lstsq(X, tau, rcond=None)
        sse = float(np.sum((X @ c - tau) ** 2))
        if best is None or sse < best[0]:
            best = (sse, B, c, X)
    assert best is not None
    sse, B, c, X = best
    var = sse / max(len(s) - 3, 1)
    cov = var * np.linalg.pinv(X.T @ X)
    return B, c, cov, var


class SoilIdentifier:
    """Identifies the soil's pull curve from a rover's torques, slips, sinkages and accelerometer.

    Args:
        wheel_radius: [m]. wheel_width: [m].
        mass: The rover's mass [kg] (> 0).
        axle_x: Distance of each axle from the body's centre [m] (the wheelbase is twice it).
        cg_height: Height of the centre of mass above the ground [m] (0: no load moved between
            the axles).
        config: :class:`SoilIdConfig`.
    """

    def __init__(
        self,
        wheel_radius: float,
        wheel_width: float,
        mass: float,
        axle_x: float,
        cg_height: float = 0.0,
        config: SoilIdConfig | None = None,
    ) -> None:
        for name, v in (
            ("wheel_radius", wheel_radius),
            ("wheel_width", wheel_width),
            ("mass", mass),
            ("axle_x", axle_x),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"SoilIdentifier: {name}={v!r}; give a positive number")
        if not (math.isfinite(cg_height) and cg_height >= 0):
            raise ConfigError(f"SoilIdentifier: cg_height={cg_height!r}; give a height >= 0 [m]")
        self.r, self.width, self.mass = float(wheel_radius), float(wheel_width), float(mass)
        self.axle_x, self.h = float(axle_x), float(cg_height)
        self.config = config or SoilIdConfig()
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new drive)."""
        self.travel = 0.0
        # fresh driving wheel-steps: slip, T/(rW), z/r (NaN: not measured), travel
        self._samples: list[tuple[float, float, float, float]] = []
        # balance steps: y, x_a, x_b0, x_b1, travel
        self._rows: list[tuple[float, float, float, float, float]] = []
        # the tracks: points (x, y) in the odometry frame, the wheel, the travel
        self._track_xy = np.zeros((0, 2))
        self._track_wheel = np.zeros(0, dtype=np.int64)
        self._track_travel = np.zeros(0)
        self._last_track = -math.inf
        self._fitted_at = -math.inf
        self._fit: tuple | None = None
        #: (4,) whether each wheel was on fresh soil (on no other wheel's track) at the last step.
        self.fresh = np.ones(4, dtype=bool)
        self.last = SoilCurveEstimate()

    def loads(self, specific_force) -> np.ndarray:
        """(4,) the wheels' loads [N] from the body-frame specific force [m/s^2].

        The four carry the mass times the specific force along body z; the pull along body x,
        acting at the ground ``cg_height`` below the centre of mass, moves load to the rear.
        """
        f = np.asarray(specific_force, dtype=np.float64)
        shift = self.mass * f[0] * self.h / (2.0 * self.axle_x)
        front = 0.5 * self.mass * f[2] - shift
        rear = 0.5 * self.mass * f[2] + shift
        return np.array([front, front, rear, rear]) / 2.0

    def _in_ruts(self, centres_xy: np.ndarray) -> np.ndarray:
        """(4,) whether each wheel's centre is on another wheel's recent track."""
        out = np.zeros(4, dtype=bool)
        if not len(self._track_xy):
            return out
        d2 = np.sum((self._track_xy[None, :, :] - centres_xy[:, None, :]) ** 2, axis=2)
        other = self._track_wheel[None, :] != np.arange(4)[:, None]
        near = (d2 <= self.config.rut_clearance**2) & other
        return near.any(axis=1)

    def _lay_tracks(self, centres_xy: np.ndarray) -> None:
        c = self.config
        if self.travel - self._last_track < c.track_step:
            return
        self._last_track = self.travel
        keep = self._track_travel >= self.travel - c.track_memory
        self._track_xy = np.concatenate([self._track_xy[keep], centres_xy])
        self._track_wheel = np.concatenate([self._track_wheel[keep], np.arange(4)])
        self._track_travel = np.concatenate([self._track_travel[keep], np.full(4, self.travel)])

    def add(
        self,
        distance: float,
        slip,
        slip_valid,
        torque,
        sinkage,
        specific_force,
        velocity,
        centres_xy,
    ) -> None:
        """One control step's measurements.

        Args:
            distance: Ground travelled since the last call [m] (>= 0).
            slip: (4,) slip ratios [-].
            slip_valid: (4,) whether each is measured.
            torque: (4,) wheel torques [N m] (None or NaN: not measured).
            sinkage: (4,) sinkages [m] (NaN: not measured).
            specific_force: (3,) the step's mean specific force, body frame [m/s^2] (None or
                NaN: no accelerometer).
            velocity: (2,) the body's ground velocity (v_x, v_y), body frame [m/s].
            centres_xy: (4, 2) the wheels' centres in the odometry frame [m].
        """
        c = self.config
        if not (math.isfinite(distance) and distance >= 0):
            raise ValueError(f"distance: {distance!r}; give the travel since the last step, >= 0 [m]")
        self.travel += distance
        xy = np.asarray(centres_xy, dtype=np.float64).reshape(4, 2)
        ruts = self._in_ruts(xy) if np.all(np.isfinite(xy)) else np.ones(4, dtype=bool)
        self.fresh = ~ruts
        if np.all(np.isfinite(xy)):
            self._lay_tracks(xy)
        v = np.asarray(velocity, dtype=np.float64)
        speed = float(np.hypot(v[0], v[1])) if np.all(np.isfinite(v)) else 0.0
        if torque is None or specific_force is None or speed < c.min_speed:
            return
        T = np.asarray(torque, dtype=np.float64)
        f = np.asarray(specific_force, dtype=np.float64)
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(f))):
            return
        W = self.loads(f)
        if np.any(W <= 0.0):
            return  # a wheel off the ground: no balance to read
        s = np.asarray(slip, dtype=np.float64)
        ok = np.asarray(slip_valid, dtype=bool) & np.isfinite(s)
        z = np.asarray(sinkage, dtype=np.float64) / self.r
        sign = -1.0 if v[0] < 0.0 else 1.0  # reversing: the torques drive the other way
        tau = sign * T / (self.r * W)
        fresh = ~ruts
        for i in np.flatnonzero(fresh & ok & (s >= 0.0) & (tau > 0.0)):
            self._samples.append((float(s[i]), float(tau[i]), float(z[i]), self.travel))
        # the balance along the travel: the pulls sum to the mass times the specific force
        u = v / speed
        f_u = float(f[0] * u[0] + f[1] * u[1])
        eps = np.where(tau >= 0.0, c.thrust_loss, c.thrust_loss_braking)
        y = float(np.sum((1.0 - eps) * tau * W)) - self.mass * f_u
        if fresh.any():
            zf = z[fresh]
            if not np.isfinite(zf).any():
                return
            zf = np.where(np.isfinite(zf), zf, np.nanmedian(zf))
            x_a = float(np.sum(W[fresh] * zf))
        else:
            x_a = 0.0
        x_b0 = float(np.sum(W[ruts]))
        x_b1 = float(np.sum(W[ruts] * tau[ruts]))
        self._rows.append((y, x_a, x_b0, x_b1, self.travel))

    def _forget(self) -> None:
        start = self.travel - self.config.memory
        if self._samples and self._samples[0][3] < start:
            self._samples = [x for x in self._samples if x[3] >= start]
        if self._rows and self._rows[0][4] < start:
            self._rows = [x for x in self._rows if x[4] >= start]

    def _resistance(self) -> tuple[np.ndarray, np.ndarray]:
        """(a, b0, b1) and their covariance from the balance rows and the priors."""
        c = self.config
        R = np.array(self._rows)
        X, y = R[:, 1:4], R[:, 0]
        prior = np.array([c.resistance_prior, c.rut_resistance_prior, c.rut_torque_prior])
        P = np.diag(1.0 / prior[:, 1] ** 2)
        A = X.T @ X / c.force_std**2 + P
        b = X.T @ y / c.force_std**2 + P @ prior[:, 0]
        cov = np.linalg.inv(A)
        return cov @ b, cov

    def estimate(self, slip=None, slip_valid=None) -> SoilCurveEstimate:
        """The identified curve, and DP/W at each wheel's ``slip`` (4,) where ``slip_valid``.

        Refitted after ``refit_travel`` of travel; NaN fields until ``min_samples`` fresh
        driving samples spanning ``min_slip_span`` of slip and as many balance steps are in.
        """
        c = self.config
        if self.travel - self._fitted_at >= c.refit_travel:
            self._fitted_at = self.travel
            self._forget()
            self._fit = self._identify()
        out = SoilCurveEstimate()
        if self._fit is not None:
            dpw, std, tau, p, cov_a = self._fit
            out.pull_ratio, out.pull_ratio_std = dpw, std
            drive = SLIPS > 0.0
            out.slip_best_pull = float(SLIPS[np.argmax(dpw)])
            with np.errstate(divide="ignore", invalid="ignore"):
                eff = np.where(drive & (tau > 0) & (dpw > 0), dpw * (1.0 - SLIPS) / tau, -np.inf)
            if np.isfinite(eff).any() and eff.max() > 0:
                out.slip_best_efficiency = float(SLIPS[np.argmax(eff)])
            out.quality = float(np.mean(std[_JUDGED] <= c.quality_std))
            out.resistance = (float(p[0]), float(math.sqrt(cov_a)))
            out.travel = float(self.travel - (self._samples[0][3] if self._samples else self.travel))
            if slip is not None:
                s = np.asarray(slip, dtype=np.float64)
                ok = np.isfinite(s) & (s >= 0.0) & (s <= SLIPS[-1])
                if slip_valid is not None:
                    ok &= np.asarray(slip_valid, dtype=bool)
                out.wheel_pull_ratio = np.where(ok, np.interp(np.where(ok, s, 0.0), SLIPS, dpw), np.nan)
        self.last = out
        return out

    def _identify(self):
        """(DP/W, its std, the thrust T/(rW), (a, b0, b1), var a) over :data:`SLIPS`, or None."""
        c = self.config
        if len(self._samples) < c.min_samples or len(self._rows) < c.min_samples:
            return None
        S = np.array(self._samples)
        s, tau, z = S[:, 0], S[:, 1], S[:, 2]
        if np.ptp(s) < c.min_slip_span:
            return None
        B, ct, cov_t, _ = _thrust_fit(s, tau)
        g = 1.0 - np.exp(-SLIPS / B)
        G = np.stack([np.ones_like(SLIPS), g], axis=1)
        tau_c = G @ ct
        var_tau = np.einsum("ij,jk,ik->i", G, cov_t, G)
        has_z = np.isfinite(z)
        if has_z.sum() < c.min_samples:
            return None
        Z = np.stack([np.ones(has_z.sum()), s[has_z], s[has_z] ** 2], axis=1)
        cz, *_ = np.linalg.lstsq(Z, z[has_z], rcond=None)
        var_z_res = float(np.sum((Z @ cz - z[has_z]) ** 2)) / max(has_z.sum() - 3, 1)
        cov_z = var_z_res * np.linalg.pinv(Z.T @ Z)
        Q = np.stack([np.ones_like(SLIPS), SLIPS, SLIPS**2], axis=1)
        zeta = Q @ cz
        var_zeta = np.einsum("ij,jk,ik->i", Q, cov_z, Q)
        p, cov = self._resistance()
        a, var_a = float(p[0]), float(cov[0, 0])
        dpw = (1.0 - c.thrust_loss) * tau_c - a * zeta
        var = (1.0 - c.thrust_loss) ** 2 * var_tau + zeta**2 * var_a + a * a * var_zeta
        # away from the slips measured the fits interpolate or extrapolate: their spread grows
        # with the distance to the nearest measured slip (about the curves' slope at mid-slip)
        measured = np.unique(np.round(s, 3))
        k = np.clip(np.searchsorted(measured, SLIPS), 1, len(measured) - 1)
        gap = np.minimum(np.abs(SLIPS - measured[k - 1]), np.abs(SLIPS - measured[k]))
        if len(measured) == 1:
            gap = np.abs(SLIPS - measured[0])
        std = np.sqrt(var + c.model_std**2 + (c.gap_slope * gap) ** 2)
        return dpw, std, tau_c, p, var_a
