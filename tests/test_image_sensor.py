"""The image sensor model against known answers: photon transfer, auto-exposure, vignetting, gamma."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from perception.models.photometry import flat_field, flat_field_gain, relative_illumination
from rover_env.config.image_sensor import ImageSensorConfig
from rover_env.config.io import ConfigError
from rover_env.sensors.image_sensor import ImageSensor

PERIOD = 1 / 30


def flat(level: int, size=(256, 256)) -> np.ndarray:
    """A rendered flat field: every pixel at ``level`` (255: white in full sun)."""
    w, h = size
    return np.full((h, w, 3), level, np.uint8)


def test_photon_transfer_recovers_the_system_gain_and_read_noise():
    """EMVA 1288's method on flat fields: variance of the difference of two frames against the mean."""
    gain_db = 12.0
    cfg = ImageSensorConfig(gain_db=gain_db, auto_exposure=False, vignetting=1.0)
    sensor = ImageSensor(cfg, (256, 256), PERIOD, seed=1)
    k_true = cfg.system_gain(gain_db)
    # flat fields from dark to 80 % of the ADC's range (at this gain, before the full well), by exposure
    means, variances = [], []
    dark = [sensor.raw(flat(0), 1e-4).astype(np.float64) for _ in range(2)]
    dark_mean = 0.5 * (dark[0].mean() + dark[1].mean())
    for share in np.linspace(0.05, 0.8, 8):
        t = share * (cfg.dn_max - cfg.black_level_dn) / k_true / cfg.sun_e_per_s
        a, b = (sensor.raw(flat(255), t).astype(np.float64) for _ in range(2))
        means.append(0.5 * (a.mean() + b.mean()) - dark_mean)
        variances.append(np.var(a - b) / 2.0)
    slope, _ = np.polyfit(means, variances, 1)
    assert slope == pytest.approx(k_true, rel=0.1), (slope, k_true)
    # the dark variance is the read noise's plus the ADC's rounding (1/12 DN^2)
    dark_var = np.var(dark[0] - dark[1]) / 2.0
    read_noise_e = math.sqrt(max(dark_var - 1 / 12, 0.0)) / slope
    assert read_noise_e == pytest.approx(cfg.read_noise_e, rel=0.1), read_noise_e


@pytest.mark.parametrize("step", [4.0, 0.25])
def test_auto_exposure_settles_within_its_configured_time_after_a_step_of_light(step):
    cfg = ImageSensorConfig(exposure_max_s=PERIOD, exposure_s=0.002)
    sensor = ImageSensor(cfg, (128, 96), PERIOD, seed=2)
    rng = np.random.default_rng(0)
    scene = np.repeat(rng.integers(20, 120, (96, 128, 1), dtype=np.uint8), 3, axis=2)
    for _ in range(60):
        out = sensor.capture(scene)
    assert out.mean() / 255 == pytest.approx(cfg.ae_target, rel=0.05)
    frames = None
    for k in range(1, 60):
        level = sensor.capture(scene, light=step).mean() / 255
        if frames is None and abs(level / cfg.ae_target - 1) <= 0.05:
            frames = k
        elif frames is not None and abs(level / cfg.ae_target - 1) > 0.05:
            frames = None  # it must stay within
    settle = cfg.ae_settling_s / PERIOD
    assert frames is not None
    # the first frame after the step was exposed before the light changed: it is counted too
    assert 0.5 * settle <= frames <= settle + 1, (frames, settle)


def test_vignetting_matches_its_model_and_the_corner_figure():
    cfg = ImageSensorConfig(vignetting=0.7, auto_exposure=False, prnu=0.0, dsnu_e=0.0, read_noise_e=0.0)
    size = (320, 240)
    sensor = ImageSensor(cfg, size, PERIOD, seed=3)
    t = 0.5 * cfg.full_well_e / cfg.sun_e_per_s
    e = np.mean([sensor.raw(flat(255, size), t) for _ in range(8)], axis=0) - cfg.black_level_dn
    centre = e[110:130, 150:170].mean()
    model = relative_illumination(size, 0.7)
    rel = e / centre
    assert np.abs(rel - model / model[110:130, 150:170].mean()).mean() < 0.01
    assert rel[:4, :4].mean() == pytest.approx(0.7, abs=0.02)


def test_gamma_saturation_and_the_same_seed():
    cfg = ImageSensorConfig(auto_exposure=False, prnu=0.0, dsnu_e=0.0, read_noise_e=0.0, vignetting=1.0)
    sensor = ImageSensor(cfg, (64, 48), PERIOD, seed=4)
    # half the full well: the output is 255 * 0.5 ** (1 / gamma) up to shot noise
    sensor.exposure_s = 0.5 * cfg.full_well_e / cfg.sun_e_per_s
    out = sensor.capture(flat(255, (64, 48)))
    assert out.mean() == pytest.approx(255 * 0.5 ** (1 / cfg.gamma), abs=1.0)
    sensor.exposure_s = cfg.exposure_max_s  # far beyond the full well
    assert np.all(sensor.capture(flat(255, (64, 48))) == 255)
    scene = np.random.default_rng(5).integers(0, 80, (48, 64, 3), dtype=np.uint8)
    a = ImageSensor(ImageSensorConfig(), (64, 48), PERIOD, seed=7).capture(scene)
    b = ImageSensor(ImageSensorConfig(), (64, 48), PERIOD, seed=7).capture(scene)
    c = ImageSensor(ImageSensorConfig(), (64, 48), PERIOD, seed=8).capture(scene)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_jpeg_output_is_close_to_the_uncompressed_image():
    scene = np.random.default_rng(6).integers(10, 100, (48, 64, 3), dtype=np.uint8)
    raw = ImageSensor(ImageSensorConfig(auto_exposure=False), (64, 48), PERIOD, seed=9).capture(scene)
    jpg = ImageSensor(ImageSensorConfig(auto_exposure=False, jpeg_quality=80), (64, 48), PERIOD, seed=9)
    out = jpg.capture(scene)
    assert out.shape == raw.shape and out.dtype == np.uint8
    diff = np.abs(out.astype(int) - raw.astype(int))
    assert 0 < diff.mean() < 12


@pytest.mark.parametrize(
    "figures, key",
    [
        ({"exposure_s": -0.001}, "exposure_s"),
        ({"full_well_e": 0.0}, "full_well_e"),
        ({"gamma": 0.0}, "gamma"),
        ({"gamma": -1.0}, "gamma"),
        ({"adc_bits": 7}, "adc_bits"),
        ({"jpeg_quality": 0}, "jpeg_quality"),
        ({"prnu": float("nan")}, "prnu"),
        ({"exposure_min_s": 0.01, "exposure_max_s": 0.001, "exposure_s": 0.005}, "exposure_max_s"),
    ],
)
def test_impossible_figures_are_refused_naming_the_key(figures, key):
    with pytest.raises(ConfigError, match=key):
        ImageSensorConfig(**figures)
    with pytest.raises(ConfigError, match=f"sensor.{key}|{key}"):
        ImageSensorConfig.from_dict(figures)


def test_an_exposure_longer_than_the_frame_period_is_refused():
    cfg = ImageSensorConfig(exposure_max_s=0.05)
    with pytest.raises(ConfigError, match="exposure_max_s: 50 ms is longer than the frame period 33.3333 ms"):
        ImageSensor(cfg, (64, 48), PERIOD)
    with pytest.raises(ConfigError, match="unknown key 'sensor.exposure'"):
        ImageSensorConfig.from_dict({"exposure": 0.01})
    with pytest.raises(ConfigError, match="sensor.preset"):
        ImageSensorConfig.from_dict({"preset": "nikon"})


def test_the_per_frame_noise_is_unbiased_from_the_first_pixel_and_repeats_with_the_seed():
    """The first draws after seeding OpenCV's generator are biased; the sensor drops them."""
    first = np.array(
        [ImageSensor(ImageSensorConfig(), (64, 48), PERIOD, seed=s)._normal((4,)) for s in range(2000)]
    )
    assert np.abs(first.mean(axis=0)).max() < 0.08  # 3.5 standard errors
    assert np.abs((first > 0).mean(axis=0) - 0.5).max() < 0.04
    frames = ImageSensor(ImageSensorConfig(), (64, 48), PERIOD, seed=3)._normal((48, 64))
    assert frames.std() == pytest.approx(1.0, abs=0.03) and abs(float(frames.mean())) < 0.03
    again = ImageSensor(ImageSensorConfig(), (64, 48), PERIOD, seed=3)._normal((48, 64))
    np.testing.assert_array_equal(frames, again)


def test_a_region_of_interest_readout_reads_its_own_bayer_sites_and_nothing_else():
    """Only the region (grown to whole 2 x 2 tiles) is read, each pixel through its own colour."""
    cfg = ImageSensorConfig(auto_exposure=False, vignetting=1.0, prnu=0.0, dsnu_e=0.0)
    roi = np.zeros((48, 64), bool)
    roi[11:30, 21:40] = True  # odd corners: the tiles it touches are read
    red = np.zeros((48, 64, 3), np.uint8)
    red[..., 0] = 200
    full = ImageSensor(cfg, (64, 48), PERIOD, seed=1).raw(red).astype(float)
    part = ImageSensor(cfg, (64, 48), PERIOD, seed=1, readout=roi).raw(red).astype(float)
    read = np.zeros_like(roi)
    read[10:30, 20:40] = True
    assert np.all(part[~read] == 0)
    r_sites = np.zeros_like(roi)
    r_sites[0::2, 0::2] = True
    # the same signal inside: red sites bright, the others at the black level
    for sites in (r_sites, ~r_sites):
        a, b = full[read & sites], part[read & sites]
        assert abs(a.mean() - b.mean()) < 4.0 * a.std() / math.sqrt(a.size) + 0.5
    assert part[read & r_sites].mean() > 10 * part[read & ~r_sites].mean()
    with pytest.raises(ValueError, match="readout: no pixel"):
        ImageSensor(cfg, (64, 48), PERIOD, readout=np.zeros((48, 64), bool))
    with pytest.raises(ValueError, match="readout: shape"):
        ImageSensor(cfg, (64, 48), PERIOD, readout=np.ones((64, 48), bool))


def test_a_presets_longest_exposure_fits_a_faster_camera_and_one_set_by_hand_must_fit():
    preset = ImageSensorConfig()
    fast = preset.for_frame_period(1 / 120)
    assert fast.exposure_max_s == pytest.approx(1 / 120) and fast.exposure_s <= 1 / 120
    ImageSensor(fast, (64, 48), 1 / 120)  # no error
    assert preset.for_frame_period(1 / 30) is preset
    by_hand = ImageSensorConfig.from_dict({"exposure_max_s": 0.01})
    assert by_hand.for_frame_period(1 / 120) is by_hand
    with pytest.raises(ConfigError, match="exposure_max_s: 10 ms is longer than the frame period"):
        ImageSensor(by_hand, (64, 48), 1 / 120)


def test_the_estimators_flat_field_undoes_the_delivered_vignetting():
    """A white wall through the sensor (vignetting 0.8, gamma 2.2), then the odometry's flat field:
    the delivered grey falls ~12 DN from centre to corner, the flat-fielded one's 8 x 8 means stay
    within 0.6 DN of the centre's (shot noise and 8-bit rounding are left)."""
    cfg = ImageSensorConfig(vignetting=0.8, auto_exposure=False, prnu=0.0, dsnu_e=0.0, read_noise_e=0.0)
    size = (160, 120)
    sensor = ImageSensor(cfg, size, PERIOD, seed=3)
    sensor.exposure_s = 0.4 * cfg.full_well_e / cfg.sun_e_per_s
    gray = np.mean(
        [cv2.cvtColor(sensor.capture(flat(255, size)), cv2.COLOR_RGB2GRAY) for _ in range(8)], axis=0
    )
    flat_gray = np.mean(
        [
            flat_field(
                cv2.cvtColor(sensor.capture(flat(255, size)), cv2.COLOR_RGB2GRAY),
                flat_field_gain(size, 0.8, cfg.gamma),
            )
            for _ in range(8)
        ],
        axis=0,
    )
    centre = gray[50:70, 70:90].mean()
    assert centre - gray[:3, :3].mean() > 8.0
    blocks = flat_gray.reshape(15, 8, 20, 8).mean(axis=(1, 3))
    rel = blocks - flat_gray[50:70, 70:90].mean()
    assert np.abs(rel).max() < 0.6, np.abs(rel).max()
