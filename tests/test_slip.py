"""SlipEstimator on synthetic streams with known slip (no simulator)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from perception import SlipConfig, SlipEstimator, slip_events, slip_ratio, wheel_ground_velocity
from perception.fusion.slip import _ACC_BIAS, clipped_normal_std

R_WHEEL = 0.115
XY = np.array([[0.4, 0.3], [0.4, -0.3], [-0.4, 0.3], [-0.4, -0.3]])
DATA = Path(__file__).parent / "data"


def truth(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(twist, wheel steering, slip ratio) of a weaving drive with one slip event on FL."""
    twist = np.array([0.6 + 0.3 * math.sin(0.7 * t), 0.02 * math.sin(1.3 * t), 0.25 * math.sin(0.5 * t)])
    steer = np.array([0.15, 0.12, -0.15, -0.12]) * math.sin(0.5 * t)
    s = np.zeros(4)
    # FL spins out between 2 and 3.5 s (s up to 0.5), RR skids a little throughout
    s[0] = 0.5 * max(0.0, min(1.0, (t - 2.0) / 0.3, (3.5 - t) / 0.3))
    s[3] = -0.04
    return twist, steer, s


def wheel_rates(t: float) -> np.ndarray:
    twist, steer, s = truth(t)
    v_long, _ = wheel_ground_velocity(twist, XY, steer)
    # s = (a - v) / max(|a|, |v|): a = v / (1 - s) for s >= 0 (spin), a = v (1 + s) for s < 0
    a = np.where(s >= 0, v_long / (1 - s), v_long * (1 + s))
    return a / R_WHEEL


def interval_mean(f, t0: float, t1: float, n: int = 16) -> np.ndarray:
    ts = np.linspace(t0, t1, n)
    return np.mean([f(t) for t in ts], axis=0)


def run_stream(
    seconds=5.0,
    noise=True,
    seed=0,
    shuffle=False,
    blackout=None,
    lost=None,
    odom_cov=None,
    tell=False,
    config=None,
):
    """Odometry at 60 Hz and fisheye at 30 Hz, each an average over its frame interval.

    ``lost``: (wheel, t0, t1): that wheel's rate is not measured in frames within [t0, t1).
    ``odom_cov``: the odometry's noise covariance (default independent 0.01, 0.01, 0.02); with
    ``tell`` the filter is given it.
    """
    cov = np.diag([0.01, 0.01, 0.02]) ** 2 if odom_cov is None else np.asarray(odom_cov)
    chol = np.linalg.cholesky(cov)
    rng = np.random.default_rng(seed)
    est = SlipEstimator(XY, R_WHEEL, config)
    out = []
    fo, ff = 1 / 60, 1 / 30
    for k in range(1, int(seconds * 30) + 1):
        t = k * ff
        msgs = []
        for j in (2 * k - 1, 2 * k):  # the two downward-camera pairs ending within this frame
            to = j * fo
            if blackout and blackout[0] <= to < blackout[1]:
                continue
            z = interval_mean(lambda u: truth(u)[0], to - fo, to)
            if noise:
                z = z + chol @ rng.normal(size=3)
            msgs.append(("odom", to, z))
        if not (blackout and blackout[0] <= t < blackout[1]):
            z = interval_mean(wheel_rates, t - ff, t)
            if noise:
                z = z * (1 + rng.normal(0, 0.005, 4)) + rng.normal(0, 0.02, 4)
            msgs.append(("wheel", t, z))
        if shuffle:
            msgs = msgs[::-1]
        for kind, tm, z in msgs:
            if kind == "odom":
                est.add_odometry(tm, z, fo, quality=1.0, cov=cov if tell else None)
            else:
                ok = np.ones(4, bool)
                if lost and lost[1] <= tm < lost[2]:
                    ok[lost[0]] = False
                est.add_wheels(tm, z, ff, ok, steering=truth(tm)[1])
        out.append((t, est.estimate(t)))
    return out


def test_noise_free_slip_matches_the_definition():
    # without the zero-slip prior, which pulls RR's small skid toward 0
    est = SlipEstimator(XY, R_WHEEL, SlipConfig(event_hold=0.0, grip_std=0.0))
    t = 2.4
    twist, steer, s_true = truth(t)
    for _ in range(30):  # repeated exact measurements at the query time
        est.add_odometry(t, twist, 0.0)
        est.add_wheels(t, wheel_rates(t), 0.0, steering=steer)
    e = est.estimate(t)
    v_long, v_lat = wheel_ground_velocity(twist, XY, steer)
    np.testing.assert_allclose(e.slip_ratio, s_true, atol=1e-5)
    np.testing.assert_allclose(e.slip_ratio, slip_ratio(wheel_rates(t) * R_WHEEL, v_long), atol=1e-5)
    np.testing.assert_allclose(e.slip_angle, np.arctan2(v_lat, v_long), atol=1e-6)
    assert e.valid.all() and e.quality == 1.0
    assert e.events.tolist() == [True, False, False, False]  # FL at s = 0.5


def test_the_zero_slip_prior_removes_odometry_noise_and_leaves_a_spin_alone():
    """Odometry four times noisier than the default (0.04 m/s, as on rough ground), told to the filter.

    Without the prior the gripping wheels FR and RL (s = 0) read the odometry's noise as slip;
    with it (grip_std 0.03) their error is about half (0.0097 against 0.020). FL's spin to
    s = 0.5 is far outside the gate, so the prior leaves it alone: within 0.05 either way.
    """
    cov = np.diag([0.04, 0.04, 0.04]) ** 2
    calm, spin = {}, {}
    for grip in (0.0, 0.03):
        errs, spins = [], []
        for seed in range(4):
            cfg = SlipConfig(grip_std=grip)
            for t, e in run_stream(seed=seed, odom_cov=cov, tell=True, config=cfg):
                s_true = truth(t)[2]
                if t >= 1.0:
                    errs.extend(np.abs(e.slip_ratio[[1, 2]] - s_true[[1, 2]]))
                if 2.4 <= t <= 3.1:  # FL's plateau at 0.5
                    spins.append(e.slip_ratio[0] - s_true[0])
        calm[grip], spin[grip] = float(np.mean(errs)), float(np.mean(spins))
    assert calm[0.03] < 0.6 * calm[0.0], calm
    assert abs(spin[0.03]) < 0.05 and abs(spin[0.0]) < 0.05, spin


def test_twist_between_estimates_changes_nothing():
    """Dead reckoning asks for the twist at every tick; the estimates stay exactly those of a filter
    that is never asked, and the twist asked for at t is the estimate's at t."""
    rng = np.random.default_rng(5)
    plain, asked = SlipEstimator(XY, R_WHEEL), SlipEstimator(XY, R_WHEEL)
    ff = 1 / 30
    previous, fl_events = None, 0
    for k in range(1, 121):
        t = k * ff
        twist_before = asked.twist_at(t - ff)  # the tick's start, before this frame's measurements
        if previous is not None:
            np.testing.assert_array_equal(twist_before, previous)
        tw, steer, _ = truth(t - ff / 2)
        z_odo = tw + rng.normal(0, 0.01, 3)
        z_rate = interval_mean(wheel_rates, t - ff, t) + rng.normal(0, 0.02, 4)
        for est in (plain, asked):
            est.add_odometry(t, z_odo, ff)
            est.add_wheels(t, z_rate, ff, steering=steer)
        a, b = plain.estimate(t), asked.estimate(t)
        for name in ("twist", "wheel_rate", "slip_ratio", "slip_ratio_std", "events", "valid"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        previous, fl_events = b.twist, fl_events + int(b.events[0])
    assert fl_events > 10  # the stream went through FL's spin (2-3.5 s)


def test_imprecise_slip_is_not_valid_and_starts_no_event():
    """A spin (tread 0.6 m/s, ground 0.3 m/s: s = 0.5) under poor odometry (quality 0.05).

    Its standard deviation is above ``max_slip_std``: not valid, read as 0, no event. The
    zero-slip prior, which the four wheels spinning alike would pass through its gate, is not
    used where the odometry alone cannot resolve the slip. With precise odometry the same drive is
    valid slip and an event.
    """
    cfg = SlipConfig(event_hold=0.0)
    est = SlipEstimator(XY, R_WHEEL, cfg)
    twist, steer = np.array([0.3, 0.0, 0.0]), np.zeros(4)
    rng = np.random.default_rng(3)
    for k in range(1, 61):
        t = k / 30
        est.add_odometry(t, twist + rng.normal(0, 0.01, 3), 1 / 30, quality=0.05)
        est.add_wheels(t, np.full(4, 0.6 / R_WHEEL), 1 / 30, steering=steer)
    e = est.estimate(60 / 30)
    assert not e.valid.any() and not e.events.any() and e.quality == 0.0
    assert np.all(e.slip_ratio == 0.0) and np.all(np.isinf(e.slip_ratio_std))
    sharp = SlipEstimator(XY, R_WHEEL, cfg)
    for k in range(1, 61):
        t = k / 30
        sharp.add_odometry(t, twist, 1 / 30, quality=1.0)
        sharp.add_wheels(t, np.full(4, 0.6 / R_WHEEL), 1 / 30, steering=steer)
    e = sharp.estimate(60 / 30)
    assert e.valid.all() and e.events.all()
    np.testing.assert_allclose(e.slip_ratio, 0.5, atol=0.02)


def test_the_deviation_of_the_clipped_ratio_is_that_of_a_censored_normal():
    rng = np.random.default_rng(0)
    for mean, std in ((0.0, 0.1), (0.9, 0.1), (1.0, 0.3), (-1.2, 0.5), (-3.0, 0.2), (0.3, 2.0)):
        mc = np.clip(rng.normal(mean, std, 400_000), -1.0, 1.0).std()
        assert clipped_normal_std(np.array([mean]), np.array([std]))[0] == pytest.approx(mc, abs=2e-3)
    out = clipped_normal_std(np.array([0.5, 0.5, 0.5]), np.array([0.0, np.inf, np.nan]))
    assert out[0] == 0.0 and np.isinf(out[1]) and np.isnan(out[2])


def test_a_wheel_turning_against_the_ground_is_sure_slip_at_minus_one():
    """Tread -0.2 m/s, ground +0.3 m/s under poor odometry (quality 0.1): s = -1 whatever the noise.

    The first-order deviation of the unclipped ratio (-2.5) is about 0.3; that of the clipped
    ratio is nearly 0, so the slip is valid and an event.
    """
    cfg = SlipConfig(event_hold=0.0)
    est = SlipEstimator(XY, R_WHEEL, cfg)
    rng = np.random.default_rng(4)
    for k in range(1, 61):
        t = k / 30
        est.add_odometry(t, np.array([0.3, 0.0, 0.0]) + rng.normal(0, 0.01, 3), 1 / 30, quality=0.1)
        est.add_wheels(t, np.full(4, -0.2 / R_WHEEL), 1 / 30, steering=np.zeros(4))
    e = est.estimate(2.0)
    np.testing.assert_allclose(e.slip_ratio, -1.0)
    assert np.all(e.slip_ratio_std < 0.01) and e.valid.all() and e.events.all()


def test_noisy_stream_accuracy_and_events():
    out = run_stream(seconds=5.0, noise=True, seed=1)
    fisheye_period = 1 / 30
    err_slip, err_calm = [], []
    est_on, true_on = [], []
    for t, e in out:
        if t < 0.5:  # the filter's start-up
            continue
        s_true = truth(t)[2]
        assert e.valid.all()
        for i in range(4):
            (err_slip if abs(s_true[i]) > 0.1 else err_calm).append(abs(e.slip_ratio[i] - s_true[i]))
        est_on.append(e.events[0])
        true_on.append(s_true[0])
    assert np.mean(err_slip) <= 0.05, np.mean(err_slip)
    assert np.mean(err_calm) <= 0.03, np.mean(err_calm)
    # one event, starting and ending within two fisheye frames of the truth's
    est_on, true_on = np.array(est_on), slip_events(np.array(true_on))  # the same hysteresis
    times = np.array([t for t, _ in out if t >= 0.5])
    for edge in (1, -1):
        t_est = times[np.flatnonzero(np.diff(est_on.astype(int)) == edge) + 1]
        t_true = times[np.flatnonzero(np.diff(true_on.astype(int)) == edge) + 1]
        assert len(t_est) == len(t_true) == 1, (edge, t_est, t_true)
        assert 0.0 <= t_est[0] - t_true[0] <= 2 * fisheye_period + 1e-9, (edge, t_est, t_true)


def test_the_odometry_covariance_sets_the_weight_of_a_noisy_yaw_rate():
    """A yaw rate with 0.08 rad/s noise, v_y anti-correlated with it (a camera patch ahead of the
    body): told the covariance, the filter smooths it and the slip errors shrink."""
    sd = np.array([0.015, 0.08, 0.08])
    corr = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -0.95], [0.0, -0.95, 1.0]])
    cov = corr * np.outer(sd, sd)
    errs = {}
    for tell in (False, True):
        e = []
        for seed in range(3):
            for t, s in run_stream(odom_cov=cov, tell=tell, seed=seed):
                if t > 1.0:
                    e.append(np.abs(s.slip_ratio - truth(t)[2]))
        errs[tell] = float(np.mean(e))
    print(f"slip MAE, covariance not told {errs[False]:.4f}, told {errs[True]:.4f}")
    # (0.0150 and 0.0120; before the wheels' angular accelerations and the measured grip gate,
    # 0.0211 and 0.0138)
    assert errs[True] < 0.85 * errs[False] and errs[True] < 0.013
    with pytest.raises(ValueError, match="cov"):
        SlipEstimator(XY, R_WHEEL).add_odometry(0.1, [0.5, 0.0, 0.0], 1 / 60, cov=np.eye(2))


def test_arrival_order_within_a_step_does_not_matter():
    a = run_stream(seconds=2.0, noise=True, seed=3)
    b = run_stream(seconds=2.0, noise=True, seed=3, shuffle=True)
    for (_, ea), (_, eb) in zip(a, b, strict=True):
        np.testing.assert_allclose(ea.slip_ratio, eb.slip_ratio, atol=1e-12)
        np.testing.assert_allclose(ea.twist, eb.twist, atol=1e-12)


def test_blackout_gives_invalid_finite_slip_and_recovers():
    out = run_stream(seconds=4.0, noise=True, seed=2, blackout=(1.5, 2.2))
    during = [e for t, e in out if 1.5 + SlipConfig().max_age < t < 2.2]
    after = [e for t, e in out if t > 2.6]
    assert during and not any(e.valid.any() for e in during)
    assert all(np.all(np.isfinite(e.slip_ratio)) and e.quality == 0.0 for e in during)
    assert all(not e.events.any() for e in during)
    # uncertainty grows while nothing is measured
    assert during[-1].twist_std[0] > during[0].twist_std[0]
    assert all(e.valid.all() for e in after)


def test_a_wheel_lost_while_it_spins_up_is_carried_two_frames_then_not_reported():
    """FL's rate goes unmeasured from 2.05 s, while its slip ramps from 0.08 to 0.5 (until 2.3 s).

    Its angular acceleration carries its rate through two missed frames, the slip's deviation
    growing with the gap so that the error stays within 2.5 of them; from the third missed
    frame on it is not valid (``max_age``): no stale rate is reported."""
    out = run_stream(seconds=2.6, noise=True, seed=4, lost=(0, 2.05, 2.6))
    period = 1 / 30
    seen = 0
    for t, e in out:
        if not 2.05 <= t < 2.6:
            continue
        err = abs(e.slip_ratio[0] - truth(t)[2][0])
        if t >= 2.05 + 2 * period:  # the third frame missing: no longer valid
            assert not e.valid[0] and e.slip_ratio[0] == 0.0, t
        else:  # one or two missing: valid, behind the ramp (0.056 per frame) within its deviation
            assert e.valid[0] and err <= min(0.15, 2.5 * e.slip_ratio_std[0]), (t, err, e.slip_ratio_std[0])
            seen += 1
        assert e.valid[1:].all()  # the other wheels carry on
    assert seen == 2


def test_slip_events_hysteresis():
    s = np.array([0.0, 0.15, 0.25, 0.15, 0.11, 0.09, 0.15, -0.3, np.nan])
    assert slip_events(s).tolist() == [False, False, True, True, True, False, False, True, False]
    # two frames in a row above 0.2 before an event starts: a one-frame spike is none
    s = np.array([0.0, 0.3, 0.0, 0.25, 0.3, 0.15, 0.05])
    assert slip_events(s, min_frames=2).tolist() == [False, False, False, False, True, True, False]


def test_one_frame_spike_is_no_event_but_two_frames_are():
    est = SlipEstimator(XY, R_WHEEL)  # event_hold 0.03 s: two 30 Hz frames
    twist = np.array([0.5, 0.0, 0.0])
    seen = []
    for k, spin in enumerate([1.0, 1.0, 1.6, 1.0, 1.0, 1.6, 1.6, 1.6, 1.0, 1.0]):
        t = k / 30
        for _ in range(20):  # exact measurements: the filter follows at once
            est.add_odometry(t, twist, 0.0)
            est.add_wheels(t, np.full(4, spin * 0.5 / R_WHEEL), 0.0)
        seen.append(bool(est.estimate(t).events[0]))
    assert seen == [False, False, False, False, False, False, True, True, False, False]


def test_no_event_below_the_event_speed():
    """A locked wheel (s = -1) at 0.1 m/s is resolved but no event; at 0.3 m/s it is one."""
    c = SlipConfig(event_hold=0.0)
    for v, event in ((0.1, False), (0.3, True)):
        est = SlipEstimator(XY, R_WHEEL, c)
        for _ in range(30):
            est.add_odometry(1.0, [v, 0.0, 0.0], 0.0)
            est.add_wheels(1.0, np.zeros(4), 0.0)
        e = est.estimate(1.0)
        assert e.valid.all() and np.allclose(e.slip_ratio, -1.0)
        assert e.events.tolist() == [event] * 4
    s = np.array([[0.0, 1.0, 1.0, 0.3, 0.3, 0.0]]).T
    speed = np.array([[0.3, 0.1, 0.1, 0.2, 0.2, 0.2]]).T
    assert slip_events(s, speed=speed).ravel().tolist() == [False, False, False, True, True, False]
    with pytest.raises(ValueError, match="speed"):
        slip_events(s, speed=speed[:3])


def test_invalid_odometry_is_ignored_and_bad_arguments_are_named():
    est = SlipEstimator(XY, R_WHEEL)
    est.add_odometry(0.1, [math.nan, 0.0, 0.0], 1 / 60)
    est.add_odometry(0.1, [0.5, 0.0, 0.0], 1 / 60, quality=0.0)
    e = est.estimate(0.1)
    assert not e.valid.any() and np.all(np.isfinite(e.slip_ratio))
    with pytest.raises(ValueError, match="wheel_rate"):
        est.add_wheels(0.1, [1.0, 2.0], 1 / 30)
    with pytest.raises(ValueError, match="wheel_xy"):
        SlipEstimator(np.zeros((3, 2)), R_WHEEL)
    with pytest.raises(ValueError, match="event_off"):
        SlipConfig(event_on=0.1, event_off=0.2)
    with pytest.raises(ValueError, match="query time"):
        est.estimate(math.nan)


def ramp_drive(accel: bool, seconds: float = 6.0, bias: float = 0.1, spin: bool = False, seed: int = 0):
    """A straight drive, odometry and fisheye at 30 Hz, and an accelerometer if ``accel``.

    v_x is 0.3 m/s, ramping up at 1.5 m/s^2 over 1-1.8 s and back down over 2.5-3.3 s. The wheels'
    motors hold a speed over each frame (the rate a frame measures is the frame's last); with
    ``spin`` they speed up at 3 m/s^2 over 4-4.5 s while the body keeps its speed. The
    accelerometer's x and y read the body's acceleration plus ``bias`` [m/s^2] and noise.
    Returns per frame (t, estimated v_x, true v_x, estimated FL slip, true slip, FL event) and
    the estimator.
    """

    def v(t):
        return 0.3 + 1.5 * min(max(t - 1.0, 0.0), 0.8) - 1.5 * min(max(t - 2.5, 0.0), 0.8)

    def tread(t):
        return v(t) + (3.0 * min(max(t - 4.0, 0.0), 0.5) if spin else 0.0)

    rng = np.random.default_rng(seed)
    est = SlipEstimator(XY, R_WHEEL)
    ff = 1 / 30
    rows = []
    for k in range(1, int(seconds * 30) + 1):
        t = k * ff
        vm = interval_mean(v, t - ff, t)
        est.add_odometry(t, np.array([vm, 0.0, 0.0]) + rng.normal(0, 0.01, 3), ff)
        if accel:
            a = (v(t) - v(t - ff)) / ff + bias + rng.normal(0, 0.02)
            est.add_accel(t, (a, bias + rng.normal(0, 0.02)), ff)
        est.add_wheels(t, np.full(4, tread(t) / R_WHEEL) + rng.normal(0, 0.03, 4), ff, steering=np.zeros(4))
        e = est.estimate(t)
        s_true = (tread(t) - v(t)) / max(abs(tread(t)), abs(v(t)))
        rows.append((t, e.twist[0], v(t), e.slip_ratio[0], s_true, e.events[0]))
    return np.array(rows), est


def test_an_accelerometer_removes_the_lag_of_the_body_velocity_and_learns_its_bias():
    """The odometry's frames are averages, half a frame old when applied; the accelerometer carries
    the velocity to the query time, and its 0.1 m/s^2 bias is learnt from the odometry."""
    errs = {}
    for accel in (False, True):
        rows, est = ramp_drive(accel)
        t, ve, vt = rows[:, 0], rows[:, 1], rows[:, 2]
        ramps = ((t > 1.1) & (t < 1.8)) | ((t > 2.6) & (t < 3.3))
        errs[accel] = np.abs(ve - vt)[ramps].mean()
    # 1.5 m/s^2 over the filter's lag: 0.026 m/s without, 0.010 with (measured)
    assert errs[False] >= 0.02, errs
    assert errs[True] <= 0.5 * errs[False] and errs[True] <= 0.013, errs
    bias = est._x[_ACC_BIAS : _ACC_BIAS + 2]
    assert abs(bias[0] - 0.1) <= 0.02 and abs(bias[1] - 0.1) <= 0.02, bias


def test_a_wheel_that_spins_up_while_the_body_keeps_its_speed_is_an_event_at_once():
    rows, _ = ramp_drive(True, spin=True)
    t, s_est, s_true, on = rows[:, 0], rows[:, 3], rows[:, 4], rows[:, 5].astype(bool)
    true_on = slip_events(s_true, min_frames=2)
    t_est = t[np.flatnonzero(np.diff(on.astype(int)) == 1) + 1]
    t_true = t[np.flatnonzero(np.diff(true_on.astype(int)) == 1) + 1]
    assert len(t_est) == len(t_true) == 1, (t_est, t_true)
    assert 0.0 <= t_est[0] - t_true[0] <= 1 / 30 + 1e-9, (t_est, t_true)
    spinning = t > 4.2
    assert np.abs(s_est - s_true)[spinning & (t < 4.5)].mean() <= 0.03


def test_accelerometer_input_is_checked():
    est = SlipEstimator(XY, R_WHEEL)
    with pytest.raises(ValueError, match="accel_xy"):
        est.add_accel(0.1, [1.0, 2.0, 3.0], 0.01)
    est.add_accel(0.1, [math.nan, 0.0], 0.01)  # left out: the filter stays a random walk
    est.add_accel(0.1, [1.0, 0.0], 0.0)
    assert not est._accel_used
    with pytest.raises(ValueError, match="accel_wheel_rate_rw"):
        SlipConfig(accel_wheel_rate_rw=-1.0)
    with pytest.raises(ValueError, match="accel_rate_std_own"):
        SlipConfig(accel_rate_std_own=math.nan)


def test_one_outlying_wheel_rate_held_over_a_missed_frame_is_not_an_event():
    """At 0.6 m/s a wrong tread alignment reads FL 30 % slow; the next frame misses FL (its rate is
    held), the one after measures it right: no event. Two measurements in a row that slow: an event."""
    v, dt = 0.6, 1 / 30
    rate = v / R_WHEEL

    def run(fl_rates, config=None):
        est = SlipEstimator(XY, R_WHEEL, config)
        events = []
        for k in range(40):
            t = (k + 1) * dt
            est.add_odometry(t, [v, 0.0, 0.0], dt)
            rates = np.full(4, rate)
            valid = np.ones(4, bool)
            j = k - 30
            if 0 <= j < len(fl_rates):
                if fl_rates[j] is None:
                    valid[0] = False  # the wheel is missed in this frame
                else:
                    rates[0] = fl_rates[j]
            est.add_wheels(t, rates, dt, valid)
            events.append(bool(est.estimate(t).events[0]))
        return events

    slow = 0.7 * rate
    assert not any(run([slow, None, rate]))  # s = -0.3 for two frames from one measurement
    assert any(run([slow, slow, rate]))
    assert any(run([slow, None, slow]))  # a newer measurement confirms it
    assert any(run([slow, None, rate], SlipConfig(event_confirm=False)))  # the outlier alone, held
    # a reading half as fast (s = -1 for two frames) is surely above the threshold, held or not
    assert not any(run([0.5 * rate, None, rate]))


@pytest.mark.parametrize("gap", [3, 5])
def test_an_event_is_held_over_an_estimate_that_resolves_no_slip(gap):
    """FL spins at s = 0.5 for 20 frames at 0.6 m/s; the odometry misses ``gap`` frames in the
    middle, so that estimates older than ``max_age`` resolve no slip. One such estimate (three
    frames missed) holds the event: one event, not two. Longer (five frames, three unresolved
    estimates, 0.1 s): the event ends ``max_age`` after its last resolved estimate."""
    v, dt = 0.6, 1 / 30
    est = SlipEstimator(XY, R_WHEEL)
    on, valid = [], []
    for k in range(60):
        t = (k + 1) * dt
        j = k - 30
        if not 5 <= j < 5 + gap:
            est.add_odometry(t, [v, 0.0, 0.0], dt)
        rates = np.full(4, v / R_WHEEL)
        if 0 <= j < 20:
            rates[0] = v / (1 - 0.5) / R_WHEEL
        est.add_wheels(t, rates, dt)
        e = est.estimate(t)
        on.append(bool(e.events[0]))
        valid.append(bool(e.valid[0]))
    on, valid = np.array(on), np.array(valid)
    starts = np.flatnonzero(np.diff(on.astype(int)) == 1) + 1
    unresolved = np.flatnonzero(~valid[30:50]) + 30
    assert len(unresolved) == gap - 2, unresolved
    if gap == 3:
        assert len(starts) == 1 and on[31:50].all(), np.flatnonzero(on)
    else:  # held for two estimates (max_age 0.07 s), ended at the third
        assert on[unresolved[:2]].all() and not on[unresolved[2]]


def test_a_rate_given_with_its_own_deviation_weighs_less_and_starts_no_event():
    """One wheel's rates scattered by 1 rad/s, as a wheel seen obliquely on few cells is measured.

    Taken at the filter's usual rate noise (0.05 rad/s and 1 %) the scatter reads as slip and
    starts events; given with their deviation (``std``, taken whole: ``rate_std_own=1``), the
    rates weigh less, that wheel's slip is less certain and no event starts. The other wheels
    are unchanged. With ``rate_std_own=0`` the deviations change nothing. (One frame's slip:
    without the window of travel, which would resolve the uncertain wheel over 30 frames.)
    """
    twist, steer = np.array([0.3, 0.0, 0.0]), np.zeros(4)
    whole = SlipConfig(rate_std_own=1.0, window_max=0.0)
    plain, told, deaf = (
        SlipEstimator(XY, R_WHEEL, whole),
        SlipEstimator(XY, R_WHEEL, whole),
        SlipEstimator(XY, R_WHEEL, SlipConfig(rate_std_own=0.0, window_max=0.0)),
    )
    rng = np.random.default_rng(5)
    events: dict[int, int] = {}
    std = np.array([np.inf, 1.0, np.inf, np.inf])
    for k in range(1, 151):
        t = k / 30
        z = np.full(4, 0.3 / R_WHEEL) + rng.normal(0, 0.02, 4)
        z[1] += rng.normal(0, 1.0)
        odo = twist + rng.normal(0, 0.005, 3)
        for est in (plain, told, deaf):
            est.add_odometry(t, odo, 1 / 30)
            est.add_wheels(t, z, 1 / 30, steering=steer, std=None if est is plain else std)
            e = est.estimate(t)
            events[id(est)] = events.get(id(est), 0) + int(e.events[1])
    a, b = plain.estimate(150 / 30), told.estimate(150 / 30)
    np.testing.assert_array_equal(deaf.estimate(150 / 30).slip_ratio, a.slip_ratio)
    assert events[id(plain)] >= 5 and events[id(told)] == 0
    assert b.slip_ratio_std[1] > 2 * a.slip_ratio_std[1]
    np.testing.assert_allclose(b.slip_ratio_std[[0, 2, 3]], a.slip_ratio_std[[0, 2, 3]], rtol=0.3)
    with pytest.raises(ValueError, match="std"):
        told.add_wheels(5.1, np.ones(4), 1 / 30, std=[1.0, 1.0])


def test_a_sure_rise_starts_an_event_in_its_first_frame_above_the_threshold():
    """``event_sure``: |s| at least ``event_off`` in one frame, then surely above ``event_on``.

    The estimates are frame means, a frame behind a wheel that brakes within a frame, so a true
    two-frame event shows as one frame part-way, one well above 0.2 and one near it. A jump from
    steady rolling (one outlying rate) and a wheel that was not valid the frame before still
    need two frames above ``event_on``.
    """

    def run(spins, quality=1.0, lost=(), config=None):
        est = SlipEstimator(XY, R_WHEEL, config)
        seen, std = [], []
        for k, spin in enumerate(spins):
            t = k / 30
            measured = np.array([k not in lost, True, True, True])  # FL missed in the lost frames
            for _ in range(20):
                est.add_odometry(t, np.array([0.5, 0.0, 0.0]), 0.0, quality=quality)
                est.add_wheels(t, np.full(4, spin * 0.5 / R_WHEEL), 0.0, measured)
            e = est.estimate(t)
            seen.append(bool(e.events[0]))
            std.append(float(e.slip_ratio_std[0]))
        return seen, std

    rise = [1.0, 1.0, 1.15, 1.6, 1.6, 1.0]  # s = 0.13, then 0.375
    assert run(rise)[0] == [False, False, False, True, True, False]
    assert run(rise, config=SlipConfig(event_sure=0.0))[0] == [False, False, False, False, True, False]
    # from steady rolling straight to 0.375: two frames
    assert run([1.0, 1.0, 1.6, 1.6, 1.0])[0] == [False, False, False, True, False]
    # with poor odometry (quality 0.05, s = 0.371 +- 0.045) the rise is not sure at 4.5 deviations ...
    strict = SlipConfig(event_sure=4.5, grip_std=0.0)
    poor, std = run(rise, quality=0.05, config=strict)
    assert std[3] > (0.371 - 0.2) / 4.5 and poor == [False, False, False, False, True, False]
    # ... and with good odometry (+- 0.004) it is
    sharp, std = run(rise, config=strict)
    assert std[3] < (0.371 - 0.2) / 4.5 and sharp == [False, False, False, True, True, False]
    # FL is missed in the part-way frame (it keeps its last rate, s near 0), then found fast
    assert run(rise, lost=(2,))[0] == [False, False, False, False, True, False]
    for bad in (-1.0, math.nan):
        with pytest.raises(ValueError, match="event_sure"):
            SlipConfig(event_sure=bad)
    with pytest.raises(ValueError, match="rate_std_own"):
        SlipConfig(rate_std_own=-0.5)


def replay_window(path, accel: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The slip filter on a recorded window of filter inputs (``benchmarks/slip_replay.py window``).

    Returns the estimates' times, events and the truth's slip; ``accel`` False leaves out the
    IMU's inputs (the filter without one).
    """
    d = np.load(path)
    est = SlipEstimator(d["wheel_xy"], float(d["wheel_radius"]))
    # a window without an IMU has no gyro or accelerometer arrays (and no such rows in "order")
    kinds = ("odometry", "wheels", "gyro", "accel")
    missing = [k for i, k in enumerate(kinds) if k not in d.files and (d["order"] == i).any()]
    assert not missing, f"{path}: 'order' has {missing} rows but the file has no such arrays"
    rows = {k: iter(d[k] if k in d.files else ()) for k in kinds}
    events = []
    for kind in d["order"].astype(int):
        if kind == 0:
            r = next(rows["odometry"])
            cov = None if np.isnan(r[6:15]).any() else r[6:15].reshape(3, 3)
            est.add_odometry(r[0], r[1:4], r[4], r[5], cov=cov)
        elif kind == 1:
            r = next(rows["wheels"])
            est.add_wheels(r[0], r[1:5], r[5], r[6:10].astype(bool), r[10:14], r[14:18])
        elif kind == 2:
            r = next(rows["gyro"])
            if accel:
                est.add_gyro(r[0], r[1], r[2], r[3])
        elif kind == 3:
            r = next(rows["accel"])
            if accel:
                est.add_accel(r[0], r[1:3], r[3])
        else:
            events.append(est.estimate(d["t"][len(events)]).events.copy())
    return d["t"], np.array(events), d["slip_true"]


@pytest.mark.parametrize("accel", [False, True])
def test_a_recorded_skid_of_a_turns_inner_wheel_is_caught_with_and_without_the_imu(accel):
    """A closed-loop skid (``Rover-v0`` seed 100, slip-unaware follower, field cameras, BMI088):
    entering a turn at 0.8 m/s the rear-left wheel brakes within a frame, true slip -0.32 and
    -0.22 in two frames. The filter calls it within two frames of the truth's onset, with the
    IMU's inputs and without, and no event on the other wheels (the front-left's one frame at
    -0.23 is no true event). Before the slip with an accelerometer was taken at the rates' time,
    the filter with the IMU's inputs missed it (the rates' deviation, doubled by extrapolating
    their accelerations, left it at -0.15 and -0.23)."""
    t, events, s_true = replay_window(DATA / "skid_rover_v0_seed100_bmi088.npz", accel)
    true_on = slip_events(s_true, min_frames=2)
    assert true_on[:, 2].any() and not true_on[:, [0, 1, 3]].any()
    first_true = np.flatnonzero(np.abs(s_true[:, 2]) >= 0.2)[0]
    assert events[:, 2].any(), "the skid was missed"
    first = np.flatnonzero(events[:, 2])[0]
    assert 0 <= first - first_true <= 2, (t[first], t[first_true])
    assert not events[:, [0, 1, 3]].any()


def test_a_wheel_driving_off_from_reverse_starts_its_event_within_two_frames():
    """A recorded reversal (``RoverRoughSlippery-v0`` seed 412 of the scripted slip drives, field
    cameras, no IMU): the wheels spin backwards (true slip -1), then drive forwards at 0.1-0.3 m/s
    of tread with true slip 0.25-0.28 from t = 6.300 s. At that speed the first estimates are too
    wide to be valid (deviation above ``max_slip_std``); those at ``event_min_speed`` or more
    (deviation 0.11-0.17) surely show slip above ``event_off``: they tell the first valid
    estimate's sure rise from a jump out of steady rolling, so the front-left and rear-right
    wheels' events started at 6.367 s, two frames after the truth's onset (a frame later, three,
    before the wide estimates counted). With the slip over a window of travel (``window_max``),
    whose short windows resolve these wheels a frame sooner, they start at 6.333 s."""
    t, events, s_true = replay_window(DATA / "reverse_rough_seed412_field.npz", False)
    after = t > 6.25
    onset = t[after][np.flatnonzero(s_true[after, 0] >= 0.2)[0]]
    assert onset == pytest.approx(6.300, abs=1e-3)
    for w in (0, 3):
        first = t[after][np.flatnonzero(events[after, w])[0]]
        assert first == pytest.approx(6.333, abs=1e-3), (w, first)
        assert round((first - onset) * 30) <= 2


SKID_S = 1.0


def outage_drive(config: SlipConfig, outage=(2.0, 8.0), bias: float = 0.3, seed: int = 0) -> np.ndarray:
    """A weaving drive (see :func:`truth`) without odometry within ``outage`` [s], where the
    accelerometer's error steps to ``bias`` m/s^2 on both axes (gravity through a new tilt error,
    1.7 deg at 0.3) and the wheels skid at -0.5 for its first ``SKID_S`` seconds (so that the zero-slip
    pseudo-measurements let go); per frame (t, estimated twist, true twist)."""
    rng = np.random.default_rng(seed)
    est = SlipEstimator(XY, R_WHEEL, config)
    ff = 1 / 30
    rows = []

    def twist(t):
        return truth(t)[0]

    for k in range(1, 10 * 30 + 1):
        t = k * ff
        tw, steer, _ = truth(t)
        if not outage[0] <= t < outage[1]:
            est.add_odometry(t, interval_mean(twist, t - ff, t) + rng.normal(0, 0.01, 3), ff)
        dv = (twist(t)[:2] - twist(t - ff)[:2]) / ff
        leak = bias if outage[0] <= t < outage[1] else 0.0
        est.add_accel(t, dv + leak + rng.normal(0, 0.02, 2), ff)
        v_long, _ = wheel_ground_velocity(interval_mean(twist, t - ff, t), XY, steer)
        skid = 0.5 if outage[0] <= t < outage[0] + SKID_S else 0.0  # the wheels lock half-way
        est.add_wheels(t, (1 - skid) * v_long / R_WHEEL + rng.normal(0, 0.03, 4), ff, steering=steer)
        rows.append((t, *est.estimate(t).twist, *tw))
    return np.array(rows)


def test_in_an_odometry_outage_the_rolling_wheels_bound_the_velocity():
    """Six seconds without odometry (a textureless ground) and an accelerometer 0.3 m/s^2 off: the
    rolling wheels' loose pseudo-measurement holds the velocity; without it (``outage_after`` inf)
    the error is integrated. With the odometry there, the pseudo-measurement never acts."""
    err = {}
    for after in (0.5, math.inf):
        rows = outage_drive(SlipConfig(outage_after=after))
        t, est, tru = rows[:, 0], rows[:, 1:3], rows[:, 4:6]
        late = (t > 4.0) & (t < 8.0)
        err[after] = np.abs(est - tru)[late].max()
    assert err[0.5] <= 0.08, err  # measured 0.046 (1.8 without)
    assert err[math.inf] >= 0.5, err
    np.testing.assert_array_equal(
        outage_drive(SlipConfig(), outage=(0.0, 0.0)),
        outage_drive(SlipConfig(outage_after=math.inf), outage=(0.0, 0.0)),
    )
    with pytest.raises(ValueError, match="outage_after"):
        SlipConfig(outage_after=0.0)
    with pytest.raises(ValueError, match="outage_slip_std"):
        SlipConfig(outage_slip_std=math.nan)


def crawl(config: SlipConfig, long_baseline: bool, seconds: float = 3.0, seed: int = 4) -> SlipEstimator:
    """Four wheels crawling on sand: tread 0.1 m/s, ground 0.05 m/s (s = 0.5), straight.

    Odometry at 30 Hz with 0.01 m/s of noise and reading 10 % slow frame to frame (what a crawl
    does to it); with ``long_baseline`` also the true mean speed over the last 0.5 s, as the
    odometry over a longer baseline reads it (1 % noise), every frame.
    """
    rng = np.random.default_rng(seed)
    est = SlipEstimator(XY, R_WHEEL, config)
    dt = 1 / 30
    for k in range(1, int(seconds * 30) + 1):
        t = k * dt
        est.add_odometry(t, np.array([0.045, 0.0, 0.0]) + rng.normal(0, 0.01, 3), dt)
        if long_baseline and t >= 0.5:
            z = np.array([0.05 * (1 + rng.normal(0, 0.01)), 0.0, 0.0])
            est.add_window_odometry(t - 0.5, t, z, cov=np.diag([5e-4, 5e-4, 1e-3]) ** 2)
        est.add_wheels(t, np.full(4, 0.1 / R_WHEEL) + rng.normal(0, 0.02, 4), dt, steering=np.zeros(4))
    return est


def test_a_crawling_wheel_gets_its_slip_over_a_window_of_travel():
    """At a crawl a frame does not resolve the slip (0.01 m/s of speed is 0.1 of slip): without
    the window no wheel is valid. Over a window of travel every wheel is, within its deviation,
    and over the longer baseline's twist the frame-to-frame odometry's bias is gone."""
    t = 3.0
    off = crawl(SlipConfig(window_max=0.0), False).estimate(t)
    assert not off.valid.any()
    frames = crawl(SlipConfig(), False).estimate(t)
    assert frames.valid.all() and np.all(frames.slip_ratio_std <= 0.1)
    # the frames' bias (the odometry 10 % slow: s = 1 - 0.045 / 0.1) within the deviation
    np.testing.assert_allclose(frames.slip_ratio, 0.55, atol=0.03)
    assert np.all(np.abs(frames.slip_ratio - 0.55) <= 2 * frames.slip_ratio_std)
    longer = crawl(SlipConfig(), True).estimate(t)
    assert longer.valid.all()
    np.testing.assert_allclose(longer.slip_ratio, 0.5, atol=0.02)
    assert not longer.events.any()  # below event_min_speed: no events at a crawl
    # poor odometry (quality 0.05) does not make a window: its errors need not average out
    est = SlipEstimator(XY, R_WHEEL, SlipConfig())
    for k in range(1, 61):
        est.add_odometry(k / 30, np.array([0.3, 0.0, 0.0]), 1 / 30, quality=0.05)
        est.add_wheels(k / 30, np.full(4, 0.6 / R_WHEEL), 1 / 30, steering=np.zeros(4))
    assert not est.estimate(2.0).valid.any()
    with pytest.raises(ValueError, match="window_max"):
        SlipConfig(window_max=-1.0)


def test_a_second_rate_source_of_the_same_frames_does_not_double_the_grip_prior():
    """Encoders beside the fisheye measure the same frames: one zero-slip prior a wheel a frame."""
    est = SlipEstimator(XY, R_WHEEL)
    applied = []
    update = est._update

    def counting(H, z, R):
        if not np.any(z):  # the pseudo-measurements: z = 0 rows on twist and rates
            applied.append(H.shape[0])
        update(H, z, R)

    est._update = counting
    ff = 1 / 30
    v = 0.5
    rate = np.full(4, v / R_WHEEL)
    for k in range(1, 31):
        t = k * ff
        est.add_odometry(t, np.array([v, 0.0, 0.0]), ff)
        est.add_wheels(t, rate, ff)  # the fisheye's
        est.add_wheels(t - 0.002, rate * 1.001, ff)  # the encoders' window of the same frame
        est.estimate(t)
    assert sum(applied) <= 4 * 30  # at most one a wheel a frame
    assert sum(applied) >= 4 * 25  # and the prior is still there
