"""The soil's pull curve identified on board (perception.fusion.soil), on synthetic drives.

The drives are made with a known soil: each wheel's thrust T/(rW) = tau0 + A (1 - exp(-s/B)),
its sinkage z/r = z0 + z1 s + z2 s^2, its resistance a z/r on fresh soil and b0 + b1 T/(rW) in a
rut; the accelerometer reads the pulls' sum over the mass. The identifier must give back the
soil's DP/W curve, its best slips, and which wheels run in ruts.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.fusion.soil import SLIPS, SoilIdConfig, SoilIdentifier
from perception.models.validation import ConfigError

R, MASS, AX, H, TRACK = 0.115, 42.6, 0.4, 0.265, 0.62
EPS = SoilIdConfig().thrust_loss
BODY = np.array([[AX, TRACK / 2], [AX, -TRACK / 2], [-AX, TRACK / 2], [-AX, -TRACK / 2]])


class Soil:
    """A soil with a pronounced pull peak (resistance growing fast with slip-sinkage)."""

    tau0, A, B = 0.10, 0.45, 0.30
    z = (0.18, 0.02, 0.20)
    a = 0.8
    b0, b1 = 0.05, -0.12

    def tau(self, s):
        return self.tau0 + self.A * (1.0 - np.exp(-np.asarray(s) / self.B))

    def zeta(self, s):
        s = np.asarray(s)
        return self.z[0] + self.z[1] * s + self.z[2] * s * s

    def dpw(self, s):
        return (1.0 - EPS) * self.tau(s) - self.a * self.zeta(s)


def drive(
    soil: Soil,
    steps: int = 600,
    crab: float = 0.0,
    noise: float = 0.0,
    seed: int = 0,
    bias: float = 0.0,
    backward: bool = False,
    **cfg,
):
    """A drive whose leading wheels sweep slip 0-0.8 while the trailing ones balance them.

    Straight, or crabbing at ``crab`` [rad] (every wheel on fresh soil); ``backward``: backing
    up, the rear wheels leading, the torques and the slips negative as the slip filter gives
    them. The accelerometer reads ``bias`` [m/s^2] along body x and y.
    """
    rng = np.random.default_rng(seed)
    c = SoilIdConfig(**cfg)
    sid = SoilIdentifier(R, MASS, AX, H, c)
    g = 9.81
    speed, dt = 0.25, 1.0 / 30.0
    sign = -1.0 if backward else 1.0
    direction = sign * np.array([math.cos(crab), math.sin(crab)])  # of travel, body frame
    lead, trail = ([2, 3], [0, 1]) if backward else ([0, 1], [2, 3])
    pos = np.zeros(2)
    for k in range(steps):
        u = (k / 300.0) % 1.0
        s_lead = 0.8 * (2 * u if u < 0.5 else 2 - 2 * u)
        W = np.full(4, MASS * g / 4)  # level, steady: no load moved between the axles
        pull = W[0] * soil.dpw(s_lead)
        # the trailing wheels hold the rover steady: their pull cancels the leading ones'; on
        # fresh soil they resist a z/r, in the leading wheels' ruts (once they reach them,
        # driving straight) b0 + b1 tau
        z_t = soil.zeta(0.0) + 0.03
        in_rut = abs(crab) < 0.05 and speed * dt * k >= 2 * AX - c.rut_clearance
        tau_t = math.nan
        for eps_t in (EPS, c.thrust_loss_braking):  # the one whose sign of tau it takes
            if in_rut:  # pull = (1 - eps) tau W - (b0 + b1 tau) W
                tau_t = (-pull / W[2] + soil.b0) / (1.0 - eps_t - soil.b1)
            else:
                tau_t = (-pull / W[2] + soil.a * z_t) / (1.0 - eps_t)
            if (tau_t >= 0) == (eps_t == EPS):
                break
        tau, z, s = np.zeros(4), np.zeros(4), np.zeros(4)
        tau[lead], z[lead], s[lead] = soil.tau(s_lead), soil.zeta(s_lead) * R, s_lead
        tau[trail], z[trail], s[trail] = tau_t, z_t * R, -0.1
        T = sign * tau * R * W
        s = sign * s
        f = np.array([bias, bias, g])
        if noise:
            T = T * (1 + noise * rng.standard_normal(4))
            z = z + 0.004 * noise / 0.03 * rng.standard_normal(4)
            s = s + noise * rng.standard_normal(4)
            f = f + 0.05 * rng.standard_normal(3)
        pos = pos + speed * dt * direction
        sid.add(speed * dt, s, np.ones(4, bool), T, z, f, speed * direction, BODY + pos)
    return sid


def test_straight_drive_identifies_the_curve_and_its_peak():
    soil = Soil()
    sid = drive(soil)
    assert sid.fresh.tolist() == [True, True, False, False]  # the rear wheels in the front ones' ruts
    est = sid.estimate()
    truth = soil.dpw(SLIPS)
    judged = (SLIPS >= 0.05) & (SLIPS <= 0.7)
    assert np.max(np.abs(est.pull_ratio[judged] - truth[judged])) < 0.02
    assert est.slip_best_pull == pytest.approx(SLIPS[np.argmax(truth)], abs=0.05)
    eff = np.where(truth > 0, truth * (1 - SLIPS) / soil.tau(SLIPS), -np.inf)
    assert est.slip_best_efficiency == pytest.approx(SLIPS[np.argmax(eff)], abs=0.05)
    assert est.resistance[0] == pytest.approx(soil.a, rel=0.05)
    assert est.quality == pytest.approx(1.0)


def test_an_accelerometer_bias_reads_as_resistance_and_is_counted_in_the_spread():
    """0.1 m/s^2 of bias reads as 4 N of pull: not told from the resistance going forward, so counted."""
    soil = Soil()
    judged = (SLIPS >= 0.05) & (SLIPS <= 0.7)
    blind = drive(soil, bias=0.1).estimate()
    told = drive(soil, bias=0.1, accel_bias_std=0.1).estimate()
    err = np.abs(told.pull_ratio[judged] - soil.dpw(SLIPS)[judged])
    assert 0.01 < err.max() < 0.05
    # the spread says so: m * bias / (the two fresh wheels' load) = 42.6 * 0.1 / 209 = 0.020
    assert np.all(err < 2.0 * told.pull_ratio_std[judged])
    assert np.all(told.pull_ratio_std[judged] > 0.02)
    assert np.all(told.pull_ratio_std[judged] > blind.pull_ratio_std[judged] + 0.005)
    # crabbing, four fresh wheels carry the bias: half the spread
    crab = drive(soil, crab=0.3, bias=0.1, accel_bias_std=0.1).estimate()
    assert np.median(crab.pull_ratio_std[judged]) < np.median(told.pull_ratio_std[judged]) - 0.003


def test_backing_up_the_rear_wheels_lead_and_the_curve_is_the_same():
    soil = Soil()
    sid = drive(soil, backward=True)
    assert sid.fresh.tolist() == [False, False, True, True]  # the front wheels in the rear ones' ruts
    # the slip filter's signs backing up: driving backwards negative, braking positive
    est = sid.estimate(np.array([0.1, 0.1, -0.3, -0.5]), np.ones(4, bool))
    judged = (SLIPS >= 0.05) & (SLIPS <= 0.7)
    assert np.max(np.abs(est.pull_ratio[judged] - soil.dpw(SLIPS)[judged])) < 0.02
    # the rear wheels drive (backwards) at 0.3 and 0.5; the front ones brake: not identified
    assert est.wheel_pull_ratio[2:] == pytest.approx(soil.dpw(np.array([0.3, 0.5])), abs=0.02)
    assert np.isnan(est.wheel_pull_ratio[:2]).all()


def test_crabbing_puts_every_wheel_on_fresh_soil():
    soil = Soil()
    sid = drive(soil, crab=0.3)
    assert sid.fresh.all()
    est = sid.estimate()
    judged = (SLIPS >= 0.05) & (SLIPS <= 0.7)
    assert np.max(np.abs(est.pull_ratio[judged] - soil.dpw(SLIPS)[judged])) < 0.03


def test_noisy_measurements_stay_within_the_stated_spread():
    soil = Soil()
    est = drive(soil, noise=0.03, seed=3).estimate()
    judged = (SLIPS >= 0.05) & (SLIPS <= 0.7)
    err = np.abs(est.pull_ratio[judged] - soil.dpw(SLIPS)[judged])
    assert err.max() < 0.05
    assert np.all(err < 3.0 * est.pull_ratio_std[judged] + 0.01)


def test_wheel_pull_ratio_is_read_at_each_wheels_slip_and_only_when_driving():
    soil = Soil()
    sid = drive(soil)
    est = sid.estimate(np.array([0.3, 0.5, -0.2, np.nan]), np.array([True, True, True, False]))
    assert est.wheel_pull_ratio[0] == pytest.approx(soil.dpw(0.3), abs=0.02)
    assert est.wheel_pull_ratio[1] == pytest.approx(soil.dpw(0.5), abs=0.02)
    assert np.isnan(est.wheel_pull_ratio[2:]).all()  # braking is not identified; unknown slip


def test_bunched_slips_give_no_curve():
    """A drive at one slip says nothing of the curve's shape: no curve, NaN fields, quality 0."""
    sid = SoilIdentifier(R, MASS, AX, H)
    soil = Soil()
    W = MASS * 9.81 / 4
    for k in range(300):
        tau = soil.tau(0.1)
        T = np.array([tau, tau, tau, tau]) * R * W
        z = np.full(4, soil.zeta(0.1) * R)
        sid.add(0.01, np.full(4, 0.1), np.ones(4, bool), T, z, [0, 0, 9.81], [0.3, 0.0], BODY + [0.01 * k, 0])
    est = sid.estimate()
    assert not est.identified and math.isnan(est.slip_best_pull) and est.quality == 0.0


def test_without_torques_or_accelerometer_nothing_is_identified():
    soil = Soil()
    for missing in ("torque", "force"):
        sid = SoilIdentifier(R, MASS, AX, H)
        for k in range(600):
            s_f = 0.8 * (k % 300) / 300
            T = None if missing == "torque" else np.full(4, soil.tau(s_f) * R * 100)
            f = None if missing == "force" else [0, 0, 9.81]
            xy = BODY + [0.01 * k, 0]
            sid.add(0.01, [s_f, s_f, 0, 0], np.ones(4, bool), T, np.full(4, 0.02), f, [0.3, 0], xy)
        assert not sid.estimate().identified


def test_bad_arguments_are_named():
    with pytest.raises(ConfigError, match="mass"):
        SoilIdentifier(R, 0.0, AX)
    with pytest.raises(ConfigError, match="memory"):
        SoilIdConfig(memory=-1.0)
    sid = SoilIdentifier(R, MASS, AX)
    with pytest.raises(ValueError, match="distance"):
        sid.add(math.nan, np.zeros(4), np.ones(4, bool), None, np.zeros(4), None, [0, 0], BODY)
