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
  driving, 0.033 braking); ``a`` is the soil's resistance per unit of relative sinkage, which
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
  in ``a``, ``b0`` and ``b1``; they are solved by Bayesian least squares, a measurement's
  weight falling by e over ``memory`` metres of travel. The accelerometer's bias reads as a
  pull too; a drive that only goes forward cannot tell it from the resistance, and it is
  counted in the curve's spread (``accel_bias_std``).
- **The curve**: the fresh driving wheels' T / (r W) against slip is fitted by a saturating
  thrust, ``tau0 + A (1 - exp(-s / B))``, and their relative sinkage by a quadratic in slip;
  DP/W(s) follows. The loads come from the mass, the specific force and the body's height
  (the load it moves between the axles); each axle's is shared equally by its wheels (the
  axles roll freely).

Outputs (:class:`SoilCurveEstimate`): the DP/W curve over slips 0-0.95 with its standard
deviation, each wheel's DP/W at its slip (driving slips only: braking is not identified), the
slips of largest DP/W and largest tractive efficiency DP (1 - s) / (T / r), and a quality over
the slips 0.05-0.7: 1 where the curve's standard deviation is at most ``quality_std``, 0 where
it is twice that or more, linear between, averaged.

Frames: body frame (x forward, y left, z up); the wheels' tracks in the frame of the
dead-reckoned pose.
Wheel order FL, FR, RL, RR.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from perception.models.validation import ConfigError

__all__ = ["SoilCurveEstimate", "SoilIdConfig", "SoilIdentifier", "SLIPS"]

#: The slips the curve is given at [-].
SLIPS = np.linspace(0.0, 0.95, 96)
#: The slips the quality is judged over [-].
_JUDGED = (SLIPS >= 0.05 - 1e-9) & (SLIPS <= 0.7 + 1e-9)
#: Slip bins for what counts as measured: their width and centres [-] ...
_BIN = 0.025
_BINS = np.arange(0.0, 1.0, _BIN) + _BIN / 2
#: ... and the fine bins the samples are gathered in (five to a coarse one).
_FINE_BIN = _BIN / 5
_FINE = np.arange(0.0, 1.0, _FINE_BIN) + _FINE_BIN / 2
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
        accel_bias_std: Standard deviation of the accelerometer's bias along the travel
            [m/s^2] (its data sheet's offset and cross-axis gravity; the built-in estimator
            takes it from its IMU's model unless given a config). The bias reads as a
            pull: on a drive that only goes forward it cannot be told from the resistance
            (estimating it made the curve worse on the benchmark's drives), so it is not
            estimated but counted in the curve's spread, m * bias / (the fresh wheels' load).
        force_std: Standard deviation of one step's balance [N]: the accelerometer's noise
            over a step, the wheels' and the body's inertia, and the model's error.
        memory: Travel over which a measurement's weight falls by a factor e [m] (the soil
            may change).
        track_memory: Travel over which a wheel's track counts as a rut [m].
        rut_clearance: A wheel is in a rut where its centre passes within this of another
            wheel's track [m] (about a wheel's width).
        track_step: The tracks keep a point every this much travel [m].
        min_speed: Below this ground speed nothing is measured [m/s].
        min_samples: Fresh driving samples (wheel-steps), as many with a measured sinkage, and
            balance steps, weighted, needed before a curve is given.
        min_slip_span: The fresh driving wheels' slips must span this much [-].
        quality_std: The curve's standard deviation up to which a slip counts as identified
            [-]; from twice as much it counts as not identified at all.
        refit_travel: The curve is refitted after this much travel [m].
        gap_slope: The curve's standard deviation grows by this per unit of slip away from the
            nearest measured slip [-] (about the curves' slope at mid-slip).
        model_std: The per-wheel model's own error in DP/W [-] (its rms over the five soils'
            steady states, 0.005-0.015), added to the fits' spread.
        min_bin_samples: A slip counts as measured where its bin (0.025 wide) holds this
            many fresh driving samples.
    """

    thrust_loss: float = 0.118
    thrust_loss_braking: float = 0.033
    resistance_prior: tuple[float, float] = (0.5, 1.0)
    rut_resistance_prior: tuple[float, float] = (0.04, 0.04)
    rut_torque_prior: tuple[float, float] = (-0.1, 0.1)
    accel_bias_std: float = 0.0
    force_std: float = 6.0
    memory: float = 30.0
    track_memory: float = 2.0
    rut_clearance: float = 0.06
    track_step: float = 0.02
    min_speed: float = 0.03
    min_samples: int = 30
    min_slip_span: float = 0.2
    quality_std: float = 0.025
    refit_travel: float = 0.2
    gap_slope: float = 0.5
    model_std: float = 0.015
    min_bin_samples: int = 10

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
        if not (math.isfinite(self.accel_bias_std) and self.accel_bias_std >= 0):
            raise ConfigError(
                f"SoilIdConfig.accel_bias_std: {self.accel_bias_std!r}; give a spread >= 0 [m/s^2]"
            )
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
        wheel_pull_ratio: (4,) DP/W at each wheel's slip (NaN: not identified, slip unknown,
            braking or above 0.95) [-].
        slip_best_pull: The slip of the largest DP/W [-] (NaN: not identified).
        slip_best_efficiency: The slip of the largest tractive efficiency [-] (NaN: none).
        quality: Over the slips 0.05-0.7, 1 where the standard deviation is at most
            ``quality_std``, 0 from twice that, linear between, averaged [0, 1].
        resistance: The identified ``a`` and its standard deviation [-].
        travel: The travel since the first fresh driving sample [m] (NaN before it; older
            samples weigh less, ``SoilIdConfig.memory``).
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


class SoilIdentifier:
    """Identifies the soil's pull curve from a rover's torques, slips, sinkages and accelerometer.

    Args:
        wheel_radius: [m].
        mass: The rover's mass [kg] (> 0).
        axle_x: Distance of each axle from the body's centre [m] (the wheelbase is twice it).
        cg_height: Height of the centre of mass above the ground [m] (0: no load moved between
            the axles).
        config: :class:`SoilIdConfig`.
    """

    def __init__(
        self,
        wheel_radius: float,
        mass: float,
        axle_x: float,
        cg_height: float = 0.0,
        config: SoilIdConfig | None = None,
    ) -> None:
        for name, v in (
            ("wheel_radius", wheel_radius),
            ("mass", mass),
            ("axle_x", axle_x),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"SoilIdentifier: {name}={v!r}; give a positive number")
        if not (math.isfinite(cg_height) and cg_height >= 0):
            raise ConfigError(f"SoilIdentifier: cg_height={cg_height!r}; give a height >= 0 [m]")
        self.r, self.mass = float(wheel_radius), float(mass)
        self.axle_x, self.h = float(axle_x), float(cg_height)
        self.config = config or SoilIdConfig()
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new drive)."""
        self.travel = 0.0
        # fresh driving wheel-steps in fine slip bins, weighted down with travel: weight, sums
        # of slip, T/(rW) and its square; weight, sums of slip, z/r and its square where the
        # sinkage was measured
        self._bins = np.zeros((8, len(_FINE)))
        # the balance's normal equations in its six regressors (the driving wheels' load
        # moments in slip, the other fresh wheels' W z/r, and b0's and b1's), and their weight
        self._normal = np.zeros((6, 6))
        self._rhs = np.zeros(6)
        self._fresh_load = 0.0  # the balance steps' fresh wheels' loads, summed [N]
        self._balance_n = 0.0
        self._first = math.nan  # the travel at the first sample [m]
        # the tracks: points (x, y) in the dead-reckoned pose's frame, the wheel, the travel
        self._track_xy = np.zeros((0, 2))
        self._track_wheel = np.zeros(0, dtype=np.int64)
        self._track_travel = np.zeros(0)
        self._last_track = -math.inf
        self._fitted_at = -math.inf
        self._curve = SoilCurveEstimate()
        self._ruts = np.zeros(4, dtype=bool)
        self._direction = 1.0  # +1 driving forward, -1 backing up
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
            slip: (4,) slip ratios [-], signed as the slip filter gives them: positive for a
                wheel that drives forward, negative for one that drives backward.
            slip_valid: (4,) whether each is measured.
            torque: (4,) wheel torques [N m] (None or NaN: not measured).
            sinkage: (4,) sinkages [m] (NaN: not measured).
            specific_force: (3,) the step's mean specific force, body frame [m/s^2] (None or
                NaN: no accelerometer).
            velocity: (2,) the body's ground velocity (v_x, v_y), body frame [m/s].
            centres_xy: (4, 2) the wheels' centres in the frame of the dead-reckoned pose [m].
        """
        c = self.config
        if not (math.isfinite(distance) and distance >= 0):
            raise ValueError(f"distance: {distance!r}; give the travel since the last step, >= 0 [m]")
        self.travel += distance
        if distance > 0.0:  # the soil may change: older measurements count less
            keep = math.exp(-distance / c.memory)
            self._bins *= keep
            self._normal *= keep
            self._rhs *= keep
            self._balance_n *= keep
            self._fresh_load *= keep
        xy = np.asarray(centres_xy, dtype=np.float64).reshape(4, 2)
        if not np.isfinite(xy).all():
            ruts = np.ones(4, dtype=bool)  # unknown: no wheel taken for one on fresh soil
        elif self.travel - self._last_track >= c.track_step:  # the tracks move with travel only
            self._last_track = self.travel
            ruts = self._ruts = self._in_ruts(xy)
            self._lay_tracks(xy)
        else:
            ruts = self._ruts
        self.fresh = fresh = ~ruts
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
        # reversing, the torques and the slips drive the other way: taken along the travel
        self._direction = sign = -1.0 if v[0] < 0.0 else 1.0
        s = sign * np.asarray(slip, dtype=np.float64)
        ok = np.asarray(slip_valid, dtype=bool) & np.isfinite(s)
        z = np.asarray(sinkage, dtype=np.float64) / self.r
        tau = sign * T / (self.r * W)
        drives = fresh & ok & (s >= 0.0) & (s < 1.0) & (tau > 0.0)
        if drives.any():
            if math.isnan(self._first):
                self._first = self.travel
            k = np.minimum((s[drives] / _FINE_BIN).astype(np.int64), len(_FINE) - 1)
            zu = z[drives]
            has = np.isfinite(zu) * 1.0
            zu = np.where(has > 0, zu, 0.0)
            su, tu = s[drives], tau[drives]
            np.add.at(
                self._bins.T, k, np.stack([np.ones(k.size), su, tu, tu * tu, has, has * su, zu, zu * zu], 1)
            )
        # the balance along the travel: the pulls sum to the mass times the specific force
        u = v / speed
        f_u = float(f[0] * u[0] + f[1] * u[1])
        eps = np.where(tau >= 0.0, c.thrust_loss, c.thrust_loss_braking)
        y = float(np.sum((1.0 - eps) * tau * W)) - self.mass * f_u
        # the fresh wheels' resistance a z/r: a driving wheel's sinkage from the sinkage's fit
        # against slip (a noisy sinkage in the regressor would bias a low: its noise is a fair
        # part of its spread), kept as its load's moments in slip; the others' as measured
        other = fresh & ~drives
        x_other = 0.0
        if other.any():
            zo = z[other]
            seen = np.isfinite(zo)
            if not seen.all():  # not measured: the fresh wheels' median
                zs = z[fresh][np.isfinite(z[fresh])]
                if not zs.size:
                    return
                zo = np.where(seen, zo, np.median(zs))
            x_other = float(np.sum(W[other] * zo))
        wd, sd = W[drives], s[drives]
        # the moments of the driving wheels' loads in slip, the others' W z/r; b0, b1
        x = np.array(
            [
                float(wd.sum()),
                float(wd @ sd),
                float(wd @ (sd * sd)),
                x_other,
                float(np.sum(W[ruts])),
                float(np.sum(W[ruts] * tau[ruts])),
            ]
        )
        self._normal += np.outer(x, x)
        self._rhs += x * y
        self._balance_n += 1.0
        self._fresh_load += float(np.sum(W[fresh]))

    def _resistance(self, sinkage_fit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a, b0, b1) and their covariance, the driving wheels' z/r from ``sinkage_fit``."""
        c = self.config
        M = np.zeros((3, 6))
        M[0, :4] = (*sinkage_fit, 1.0)  # a's regressor: sum W (c0 + c1 s + c2 s^2) + the others'
        M[1:, 4:] = np.eye(2)
        prior = np.array([c.resistance_prior, c.rut_resistance_prior, c.rut_torque_prior])
        P = np.diag(1.0 / prior[:, 1] ** 2)
        A = M @ self._normal @ M.T / c.force_std**2 + P
        b = M @ self._rhs / c.force_std**2 + P @ prior[:, 0]
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
            self._curve = self._curve_estimate(self._identify())
        out = dataclasses.replace(self._curve, travel=float(self.travel - self._first))
        if slip is not None and out.identified:
            s = self._direction * np.asarray(slip, dtype=np.float64)
            ok = np.isfinite(s) & (s >= 0.0) & (s <= SLIPS[-1])
            if slip_valid is not None:
                ok &= np.asarray(slip_valid, dtype=bool)
            out.wheel_pull_ratio = np.where(
                ok, np.interp(np.where(ok, s, 0.0), SLIPS, out.pull_ratio), np.nan
            )
        self.last = out
        return out

    def _curve_estimate(self, fit) -> SoilCurveEstimate:
        """The curve's figures from :meth:`_identify`'s fit (None: an empty estimate)."""
        out = SoilCurveEstimate()
        if fit is None:
            return out
        dpw, std, tau, p, var_a = fit
        out.pull_ratio, out.pull_ratio_std = dpw, std
        out.slip_best_pull = float(SLIPS[np.argmax(dpw)])
        with np.errstate(divide="ignore", invalid="ignore"):
            eff = np.where((SLIPS > 0.0) & (tau > 0) & (dpw > 0), dpw * (1.0 - SLIPS) / tau, -np.inf)
        if eff.max() > 0:
            out.slip_best_efficiency = float(SLIPS[np.argmax(eff)])
        q = self.config.quality_std  # 1 within q, 0 from twice q, linear between
        out.quality = float(np.mean(np.clip(2.0 - std[_JUDGED] / q, 0.0, 1.0)))
        out.resistance = (float(p[0]), float(math.sqrt(var_a)))
        return out

    def _identify(self):
        """(DP/W, its std, the thrust T/(rW), (a, b0, b1), var a) over :data:`SLIPS`, or None."""
        c = self.config
        w, wz = self._bins[0], self._bins[4]
        if w.sum() < c.min_samples or self._balance_n < c.min_samples or wz.sum() < c.min_samples:
            return None
        # a slip counts as measured where its coarse bin holds enough samples (a few stray
        # samples of a transient do not make it measured)
        coarse = w.reshape(len(_BINS), -1).sum(axis=1)
        measured = _BINS[coarse >= c.min_bin_samples]
        if not len(measured) or np.ptp(measured) < c.min_slip_span:
            return None
        z_measured = _BINS[wz.reshape(len(_BINS), -1).sum(axis=1) >= c.min_bin_samples]
        if not len(z_measured) or np.ptp(z_measured) < c.min_slip_span:
            return None  # the sinkage seen over too narrow a span of slip for its quadratic
        B, ct, cov_t = self._thrust_fit()
        G = np.stack([np.ones_like(SLIPS), 1.0 - np.exp(-SLIPS / B)], axis=1)
        tau_c = G @ ct
        var_tau = np.einsum("ij,jk,ik->i", G, cov_t, G)
        cz, cov_z = self._sinkage_fit()
        Q = np.stack([np.ones_like(SLIPS), SLIPS, SLIPS**2], axis=1)
        zeta = Q @ cz
        var_zeta = np.einsum("ij,jk,ik->i", Q, cov_z, Q)
        p, cov = self._resistance(cz)
        a, var_a = float(p[0]), float(cov[0, 0])
        dpw = (1.0 - c.thrust_loss) * tau_c - a * zeta
        # the terms as if independent: a and the sinkage's fit are anti-correlated through the
        # balance, so this overstates the spread somewhat (B's uncertainty is left out)
        var = (1.0 - c.thrust_loss) ** 2 * var_tau + zeta**2 * var_a + a * a * var_zeta
        # away from the slips measured the fits interpolate or extrapolate: their spread grows
        # with the distance to the nearest measured slip
        gap = np.min(np.abs(SLIPS[:, None] - measured[None, :]), axis=1)
        # the accelerometer's bias, read as the fresh wheels' resistance
        bias = self.mass * c.accel_bias_std * self._balance_n / max(self._fresh_load, 1e-9)
        std = np.sqrt(var + c.model_std**2 + bias**2 + (c.gap_slope * gap) ** 2)
        return dpw, std, tau_c, p, var_a

    def _thrust_fit(self):
        """The saturating thrust through the bins: (B, (tau0, A), their covariance)."""
        w, ws, wt, wtt = self._bins[:4]
        on = w > 1e-9
        w, sm, tm = w[on], ws[on] / w[on], wt[on] / w[on]
        within = float(np.sum(wtt[on] - w * tm * tm))  # the spread inside the bins
        g = 1.0 - np.exp(-sm[None, :] / _B_GRID[:, None])  # (B, bins)
        s0, s1, s2 = w.sum(), g @ w, (g * g) @ w
        t0, t1 = float(w @ tm), (g * tm) @ w
        det = s0 * s2 - s1 * s1
        with np.errstate(divide="ignore", invalid="ignore"):
            c0 = (s2 * t0 - s1 * t1) / det
            c1 = (s0 * t1 - s1 * t0) / det
        sse = float(w @ (tm * tm)) - c0 * t0 - c1 * t1  # each B's least-squares residual
        sse = np.where(np.isfinite(sse) & (det > 1e-12 * s0 * s0), sse, np.inf)
        i = int(np.argmin(sse))
        var = max(float(sse[i]) + within, 0.0) / max(s0 - 3.0, 1.0)
        XtWX = np.array([[s0, s1[i]], [s1[i], s2[i]]])
        return float(_B_GRID[i]), np.array([c0[i], c1[i]]), var * np.linalg.pinv(XtWX)

    def _sinkage_fit(self):
        """The relative sinkage's quadratic in slip through the bins: (coefficients, covariance)."""
        wz, wzs, zs, zsq = self._bins[4:8]
        on = wz > 1e-9
        w, sm, zm = wz[on], wzs[on] / wz[on], zs[on] / wz[on]
        X = np.stack([np.ones_like(sm), sm, sm * sm], axis=1)
        XtWX = X.T @ (X * w[:, None])
        coef = np.linalg.pinv(XtWX) @ (X.T @ (w * zm))
        sse = float(w @ (X @ coef - zm) ** 2) + float(np.sum(zsq[on] - w * zm * zm))
        var = max(sse, 0.0) / max(float(w.sum()) - 3.0, 1.0)
        return coef, var * np.linalg.pinv(XtWX)
