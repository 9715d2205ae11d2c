"""Wheel rotation from synthetic fisheye images of a textured tread (no simulator)."""

import math

import cv2
import numpy as np
import pytest
from test_markers import fisheye, rover_model

from perception.kinematics.wheel_rotation import (
    RotationMeasurement,
    StaticPattern,
    TreadConfig,
    align_strips,
    arc_angle,
    masked_ncc,
    measure_pairs,
    measure_rotation,
    measure_strips,
    ransac_1d,
    ray_cylinder,
    strip_resolution,
    track_strip_features,
    unwrap_tread,
)
from perception.models.photometry import cfa_luminance, linear_gray


def tread_texture(rng) -> np.ndarray:
    """A tread texture, (rows across the tread, columns around it), periodic around the wheel."""
    rows = round(2048 * 0.08 / (2 * np.pi * 0.115))  # square texels on the tread (0.35 mm)
    tex = rng.normal(size=(rows, 2048)).astype(np.float32)
    wide = cv2.GaussianBlur(np.hstack([tex, tex, tex]), (0, 0), 10.0)  # blur with wrap-around
    tex = wide[:, 2048:4096]
    return (128 + 45 * tex / tex.std()).astype(np.float32)


def render_wheel(model, camera, frame, theta, tex, background=60.0):
    """Grey fisheye image of one wheel's tread at wheel angle ``theta`` on a flat ``background``."""
    w, h = camera.image_size
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = camera.cam2world(np.stack([gx, gy], -1).reshape(-1, 2))
    ok = np.isfinite(rays[:, 0])
    rays[~ok] = (0.0, 0.0, 1.0)
    pts, hit = ray_cylinder(
        camera.T_body_cam[:3, 3],
        rays @ camera.T_body_cam[:3, :3].T,
        *frame,
        model.wheel_radius,
        model.wheel_width / 2,
    )
    hit &= ok
    phi_wheel = np.arctan2(pts[hit, 0], pts[hit, 2]) - theta  # the texture turns with the wheel
    u = (phi_wheel / (2 * np.pi) % 1.0) * tex.shape[1]
    v = (pts[hit, 1] / model.wheel_width + 0.5) * (tex.shape[0] - 1)
    vals = cv2.remap(
        tex,
        u.astype(np.float32).reshape(-1, 1),
        v.astype(np.float32).reshape(-1, 1),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    ).ravel()
    img = np.full(w * h, background, np.float32)
    img[hit] = vals
    return np.clip(img.reshape(h, w) + 0.5, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("wheel", [0, 1, 2, 3])
@pytest.mark.parametrize("alpha", [0.15, -0.3, 0.55])  # tread 0.5 to 2 m/s at 30 Hz
def test_known_tread_rotation_is_recovered_within_1_percent(wheel, alpha):
    model = rover_model()
    cam = fisheye(model)
    psi, depth, lam = (0.08, -0.05), (0.155, 0.145), (0.2, -0.2)
    frame = model.wheel_frames(psi, depth, model.wheel_angles(*lam))[wheel]
    tex = tread_texture(np.random.default_rng(wheel))
    prev = render_wheel(model, cam, frame, 0.3, tex)
    curr = render_wheel(model, cam, frame, 0.3 + alpha, tex)
    m = measure_rotation(prev, curr, model, cam, frame, frame, TreadConfig())  # no prior: from rest
    print(f"wheel {wheel} alpha {alpha}: measured {m.alpha:.5f}, {m.n_inliers}/{m.n_tracked} tracks agree")
    assert m.valid
    assert abs(m.alpha - alpha) <= 0.01 * abs(alpha)


def test_arc_angle_sign_and_eq6():
    r = 0.115
    a = np.radians([3.0, -20.0, 40.0])
    p1 = np.array([[0.0, 0.01, r]] * 3)
    p2 = np.stack([r * np.sin(a), np.full(3, -0.02), r * np.cos(a)], 1)  # rotation about +y by a
    np.testing.assert_allclose(arc_angle(p1, p2, r), a, atol=1e-12)


def test_ransac_1d_keeps_the_consistent_angles():
    v = np.r_[np.full(12, 0.2) + np.linspace(-0.004, 0.004, 12), 0.0, 0.0, 0.6, -0.3]
    inl = ransac_1d(v, 0.01)
    assert inl[:12].all() and not inl[12:].any()


def test_rotation_is_invalid_without_texture():
    model = rover_model()
    cam = fisheye(model)
    frame = model.wheel_frames((0, 0), (0.15, 0.15), np.zeros(4))[0]
    flat = np.full((480, 640), 90, np.uint8)
    m = measure_rotation(flat, flat, model, cam, frame, frame, TreadConfig())
    assert not m.valid and math.isnan(m.alpha)


def test_masked_ncc_equals_the_direct_sum_at_every_lag():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(5, 17)), rng.normal(size=(5, 12))
    ma, mb = rng.random((5, 17)) > 0.3, rng.random((5, 12)) > 0.3
    lags, ncc, cnt = masked_ncc(a, ma, b, mb)
    for s_, r, c in zip(lags, ncc, cnt, strict=True):
        pairs = [
            (a[i, j], b[i, j - s_])
            for i in range(5)
            for j in range(17)
            if 0 <= j - s_ < 12 and ma[i, j] and mb[i, j - s_]
        ]
        assert c == pytest.approx(len(pairs), abs=1e-6)
        if len(pairs) >= 3:
            x, y = np.array(pairs).T
            assert r == pytest.approx(np.corrcoef(x, y)[0, 1], abs=1e-6)


def strips_of(model, cam, frame, tex, theta0, alpha, shadow=None):
    """Tread strips of one wheel at two wheel angles; ``shadow``: (H, W) light factor, fixed in the image."""
    cfg = TreadConfig()
    dphi = strip_resolution(model, cam, *frame, cfg.column_px)
    out = []
    for th in (theta0, theta0 + alpha):
        img = render_wheel(model, cam, frame, th, tex)
        if shadow is not None:
            img = np.clip(img * shadow, 0, 255).astype(np.uint8)
        out.append(unwrap_tread(img, model, cam, *frame, dphi, cfg))
    return out


@pytest.mark.parametrize("alpha", [0.15, -0.3])
def test_the_papers_features_alone_recover_the_rotation_within_1_percent(alpha):
    model = rover_model()
    cam = fisheye(model)
    frame = model.wheel_frames((0.05, 0.0), (0.15, 0.15), model.wheel_angles(0.1, -0.1))[2]
    prev, curr = strips_of(model, cam, frame, tread_texture(np.random.default_rng(5)), 1.0, alpha)
    # started 0.6 columns off the answer: Lucas-Kanade converges from there
    m = track_strip_features(prev, curr, model.wheel_radius, TreadConfig(), alpha + 0.6 * prev.dphi)
    print(f"features: {m.alpha:.5f} for {alpha}, {m.n_inliers}/{m.n_tracked} consistent")
    assert m.valid and m.n_inliers >= 10
    assert abs(m.alpha - alpha) <= 0.01 * abs(alpha)


def shadowed_front_left():
    """The front-left wheel with the body's shadow edge across its tread's image: a straight edge
    through the middle, slanted, light ratio 3. Returns (model, camera, frame, config, column step,
    (480, 640) light factor)."""
    model = rover_model()
    cam = fisheye(model)
    frame = model.wheel_frames((0.0, 0.0), (0.15, 0.15), np.zeros(4))[0]
    cfg = TreadConfig()
    dphi = strip_resolution(model, cam, *frame, cfg.column_px)
    probe = unwrap_tread(np.full((480, 640), 128, np.uint8), model, cam, *frame, dphi, cfg)
    mid = probe.pixels[probe.visible].mean(axis=0)
    gx, gy = np.meshgrid(np.arange(640.0), np.arange(480.0))
    return model, cam, frame, cfg, dphi, np.where((gx - mid[0]) + 0.4 * (gy - mid[1]) > 0, 1.0, 1 / 3)


def test_a_shadow_edge_fixed_in_the_image_does_not_pull_the_rotation():
    """The body's shadow across a tread: it stays put while the tread turns under it."""
    model, cam, frame, cfg, dphi, shadow = shadowed_front_left()
    alpha = 0.2
    blind = TreadConfig(min_step=1e9)  # without the edge band
    err, err_blind = [], []
    for seed in (8, 9, 10, 11):
        tex = tread_texture(np.random.default_rng(seed))
        imgs = [
            np.clip(render_wheel(model, cam, frame, th, tex) * shadow, 0, 255).astype(np.uint8)
            for th in (0.4, 0.4 + alpha)
        ]
        prev, curr = (unwrap_tread(im, model, cam, *frame, dphi, cfg) for im in imgs)
        if seed == 8:  # the edge band is left out (the step is not found on every texture: 9 and 11)
            assert 0.05 < (~curr.valid & inner(curr.visible)).mean() < 0.6
        m = measure_strips(prev, curr, model.wheel_radius, cfg)
        assert m.valid and abs(m.alpha - alpha) <= 0.015 * alpha
        err.append(abs(m.alpha - alpha))
        unmasked = [unwrap_tread(im, model, cam, *frame, dphi, blind) for im in imgs]
        err_blind.append(abs(measure_strips(*unmasked, model.wheel_radius, blind).alpha - alpha))
    print(f"shadowed tread, {alpha} rad: mean error {np.mean(err):.5f}; no band {np.mean(err_blind):.5f}")
    # without the band, the edge's ring in the band-passed strip pulls the rotation toward 0
    assert np.mean(err) <= 0.011 * alpha
    assert np.mean(err_blind) >= 1.5 * np.mean(err)


def noisy_tread_pair(tex, noise_level, cfg, angles=(0.2, 0.7)):
    """Strips of the front-right wheel at ``angles`` [rad] (default 0.5 rad apart: 1.7 m/s of tread
    at 30 Hz) under blurred image noise of ``noise_level`` grey levels; returns (model, strips, dphi,
    frame, cam)."""
    model = rover_model()
    cam = fisheye(model)
    frame = model.wheel_frames((0.0, 0.0), (0.15, 0.15), np.zeros(4))[1]
    dphi = strip_resolution(model, cam, *frame, cfg.column_px)
    rng = np.random.default_rng(1)
    strips = []
    for th in angles:
        img = render_wheel(model, cam, frame, th, tex).astype(np.float32)
        noise = cv2.GaussianBlur(rng.normal(size=img.shape).astype(np.float32), (0, 0), 1.5)
        img = np.clip(img + noise_level * noise / noise.std(), 0, 255).astype(np.uint8)
        strips.append(unwrap_tread(img, model, cam, *frame, dphi, cfg))
    return model, strips, dphi, frame, cam


def test_a_decisive_alignment_of_a_tracked_wheel_stands_without_the_features():
    """Noisy treads (correlation about 0.55): the peak stands far above any other rotation."""
    cfg = TreadConfig()
    model, strips, dphi, frame, cam = noisy_tread_pair(tread_texture(np.random.default_rng(4)), 40, cfg)
    pair = [tuple(strips)]
    al = align_strips(*strips, cfg, 0.45, 0.25)
    assert cfg.decisive_ncc <= al.ncc < cfg.min_ncc and al.margin >= cfg.decisive_margin
    tracked = measure_pairs(pair, model.wheel_radius, cfg, [0.45], [0.25], [0])[0]
    assert tracked.valid and abs(tracked.alpha - 0.5) <= 0.02 * 0.5
    # a wheel searched for after a loss needs the features, which fail on this noise
    assert not measure_pairs(pair, model.wheel_radius, cfg, [0.45], [0.8], [2])[0].valid
    # two unrelated treads: no decisive peak
    img = render_wheel(model, cam, frame, 0.2, tread_texture(np.random.default_rng(9)))
    other = unwrap_tread(img, model, cam, *frame, dphi, cfg)
    assert not measure_pairs([(strips[0], other)], model.wheel_radius, cfg, [0.45], [0.25], [0])[0].valid


def test_an_alignment_at_the_predicted_rotation_of_a_tracked_wheel_stands_without_the_features():
    """A striped tread (period 0.15 rad) under noise: correlation 0.57, rivals 0.16 below it.

    Neither strong nor decisive, and the features do not confirm it; the alignment is taken
    when it lies within ``prior_tolerance`` of the predicted rotation, and not otherwise.
    """
    cfg = TreadConfig()
    base = tread_texture(np.random.default_rng(4))
    phi = np.arange(base.shape[1]) / base.shape[1] * 2 * np.pi
    tex = (128 + 0.4 * (base - 128) + 0.6 * 45 * np.sin(phi / 0.15 * 2 * np.pi)[None, :]).astype(np.float32)
    model, strips, _, _, _ = noisy_tread_pair(tex, 22, cfg)
    pair = [tuple(strips)]
    al = align_strips(*strips, cfg, 0.5, 0.25)
    assert cfg.prior_ncc <= al.ncc < cfg.min_ncc and cfg.min_peak_margin <= al.margin < cfg.decisive_margin
    at_prior = measure_pairs(pair, model.wheel_radius, cfg, [0.49], [0.25], [0])[0]
    assert at_prior.valid and abs(at_prior.alpha - 0.5) <= 0.005
    assert not measure_pairs(pair, model.wheel_radius, cfg, [0.45], [0.25], [0])[0].valid  # 0.05 off
    assert not measure_pairs(pair, model.wheel_radius, cfg, [0.49], [0.8], [2])[0].valid  # after a loss


def test_a_still_tread_seen_by_a_turning_wheel_needs_the_features():
    """Rotation 0 under noise: a decisive peak at 0, where still shading and shadows also fit.

    Taken as it is for a wheel predicted to stand still; for one predicted to turn 0.23 rad
    per frame, the features must confirm it (``static_band``), and on this noise they do not.
    """
    cfg = TreadConfig()
    model, strips, _, _, _ = noisy_tread_pair(tread_texture(np.random.default_rng(4)), 40, cfg, (0.2, 0.2))
    pair = [tuple(strips)]
    al = align_strips(*strips, cfg, 0.0, 0.25)
    assert abs(al.alpha) <= 0.005 and al.ncc < cfg.min_ncc and al.margin >= cfg.decisive_margin
    standing = measure_pairs(pair, model.wheel_radius, cfg, [0.0], [0.25], [0])[0]
    assert standing.valid and abs(standing.alpha) <= 0.005
    assert not measure_pairs(pair, model.wheel_radius, cfg, [0.23], [0.25], [0])[0].valid
    unguarded = TreadConfig(static_band=0.0)
    assert measure_pairs(pair, model.wheel_radius, unguarded, [0.23], [0.25], [0])[0].valid


def test_strips_of_all_wheels_together_equal_each_wheel_alone():
    """The wheels share one projection, resampling and band-pass, with gaps wider than its reach."""
    from perception.kinematics.wheel_rotation import _masked_blur, unwrap_treads

    model = rover_model()
    cam = fisheye(model)
    frames = model.wheel_frames((0.06, -0.04), (0.16, 0.14), model.wheel_angles(0.2, -0.15))
    rng = np.random.default_rng(4)
    gray = cv2.GaussianBlur(rng.normal(120, 40, (480, 640)).astype(np.float32), (0, 0), 1.0)
    gray = np.clip(gray, 0, 255).astype(np.uint8)
    cfg = TreadConfig()
    dphi = strip_resolution(model, cam, *frames[0], cfg.column_px)
    together = unwrap_treads(gray, model, cam, frames, dphi, cfg)
    for frame, strip in zip(frames, together, strict=True):
        alone = unwrap_tread(gray, model, cam, *frame, dphi, cfg)
        assert strip.k0 == alone.k0 and strip.visible.sum() > 1000
        np.testing.assert_array_equal(strip.pixels, alone.pixels)
        np.testing.assert_array_equal(strip.valid, alone.valid)
        np.testing.assert_allclose(strip.texture, alone.texture, atol=1e-6)
    # grey levels asked for by rectangle (the colour-filter array's luminance about the treads
    # only) give the strips of the whole frame's
    rgb = np.clip(rng.normal(120, 40, (480, 640, 3)), 0, 255).astype(np.uint8)
    rgb = cv2.GaussianBlur(rgb, (0, 0), 1.0)
    whole = unwrap_treads(cfa_luminance(rgb, "RGGB", 2.2), model, cam, frames, dphi, cfg)
    asked = []

    def region(x0, y0, x1, y1):
        asked.append((x1 - x0) * (y1 - y0))
        return cfa_luminance(rgb, "RGGB", 2.2, rect=(x0, y0, x1, y1))

    by_region = unwrap_treads(region, model, cam, frames, dphi, cfg)
    assert len(asked) == 4 and sum(asked) < 0.5 * 640 * 480
    for a, b in zip(whole, by_region, strict=True):
        np.testing.assert_array_equal(a.valid, b.valid)
        np.testing.assert_allclose(a.texture, b.texture, atol=1e-4 * np.abs(a.texture).max())
    # the band-pass's blur is OpenCV's Gaussian blur, normalised over the mask
    img = rng.random((40, 70)).astype(np.float32)
    mask = rng.random((40, 70)) > 0.3
    img[~mask] = 0
    ref = [cv2.GaussianBlur(x, (0, 0), sigmaX=6.9, sigmaY=3.7, borderType=cv2.BORDER_CONSTANT)
           for x in (img, mask.astype(np.float32))]  # fmt: skip
    np.testing.assert_allclose(
        _masked_blur(img, mask, (6.9, 3.7)), ref[0] / np.maximum(ref[1], 1e-3), rtol=1e-6
    )


def test_a_rotation_the_other_wheels_contradict_is_searched_for_near_theirs():
    """The rover's shadow on a tread does not turn: a wheel read near zero (or jumping from its own
    prediction with a weak correlation) while the others turn is measured again within
    ``peer_tolerance`` of their rotation, where its features must confirm it."""
    from perception.kinematics.fisheye import KinematicStateEstimator

    cfg = TreadConfig()
    tex = tread_texture(np.random.default_rng(4))
    model, still, _, frame, cam = noisy_tread_pair(tex, 40, cfg, (0.2, 0.2))
    _, turning, _, _, _ = noisy_tread_pair(tex, 5, cfg, (0.2, 0.43))
    est = KinematicStateEstimator(cam, model)
    frames = model.wheel_frames((0.0, 0.0), (0.15, 0.15), np.zeros(4))  # straight: equal rolling speeds
    peers = [RotationMeasurement(0.23, 0, 0, 0, True, 0.9)] * 4
    prior = np.full(4, 0.23)

    def check(pair, first):
        rots = list(peers)
        rots[1] = first
        pairs = [None, tuple(pair), None, None]
        return est._check_against_peers(pairs, rots, prior, frames, np.zeros(4), 1 / 30)

    # a still tread (or a shadow) read as a standing wheel: not confirmed near 0.23, not measured
    standing = measure_pairs([tuple(still)], model.wheel_radius, cfg, [0.0], [0.25], [0])[0]
    assert standing.valid and abs(standing.alpha) <= 0.005
    out = check(still, standing)
    assert not out[1].valid and all(out[k] is peers[k] for k in (0, 2, 3))
    # a weak alignment 0.18 rad off: the tread's features find the rotation near the others'
    out = check(turning, RotationMeasurement(0.05, 0, 0, 0, True, 0.5))
    assert out[1].valid and abs(out[1].alpha - 0.23) <= 0.01, out[1]
    # a strong reading that differs from the others and from nothing else (a wheel that slips) stands
    slipping = RotationMeasurement(0.3, 0, 0, 0, True, 0.9)
    assert check(turning, slipping)[1] is slipping


def test_a_gamma_encoded_shadow_edge_is_found_once_the_tread_is_linearised():
    """A camera's output gamma shrinks a shadow's light ratio of 3 to 1.65: the edge band then misses
    the step and the rotation is pulled; linearised with the camera's gamma, it is as with linear images."""
    model, cam, frame, cfg, dphi, shadow = shadowed_front_left()
    tex = tread_texture(np.random.default_rng(8))
    alpha, gamma = 0.2, 2.2
    lit = [np.clip(render_wheel(model, cam, frame, th, tex) * shadow, 0, 255) for th in (0.4, 0.4 + alpha)]
    encoded = [np.rint(255 * (x / 255) ** (1 / gamma)).astype(np.uint8) for x in lit]
    assert linear_gray(encoded[0], gamma).dtype == np.float32
    assert abs(float(linear_gray(np.array([128], np.uint8), gamma)[0]) - 55.98) < 0.01
    as_is = [unwrap_tread(img, model, cam, *frame, dphi, cfg) for img in encoded]
    linear = [unwrap_tread(linear_gray(img, gamma), model, cam, *frame, dphi, cfg) for img in encoded]
    # the edge band: cells left out within the tread, away from its outline (``boundary``)
    band = [float((~s.valid & inner(s.visible)).mean()) for s in (as_is[1], linear[1])]
    m_as_is = measure_strips(*as_is, model.wheel_radius, cfg)
    m_lin = measure_strips(*linear, model.wheel_radius, cfg)
    print(f"edge band {band}; rotation {m_as_is.alpha:.5f} encoded, {m_lin.alpha:.5f} linear, for {alpha}")
    assert band[0] < 0.02 < 0.05 < band[1]  # the step is found only in linear levels
    # within the spread of test_a_shadow_edge_fixed_in_the_image_does_not_pull_the_rotation
    assert m_lin.valid and abs(m_lin.alpha - alpha) <= 0.015 * alpha
    assert not (m_as_is.valid and abs(m_as_is.alpha - alpha) <= 0.015 * alpha)


def inner(visible: np.ndarray) -> np.ndarray:
    """Cells of ``visible`` with all eight neighbours visible."""
    return cv2.erode(visible.view(np.uint8), np.ones((3, 3), np.uint8), borderValue=0).view(bool)


def test_the_texture_of_valid_cells_does_not_depend_on_what_lies_beyond_the_tread():
    """A black or a white background: the cells the rotation uses read the same tread.

    A cell at the silhouette samples the image bilinearly and the band-pass blurs it, so without
    the ``boundary`` the background leaks into the edge cells (by more than the texture's RMS).
    """
    model, cam = rover_model(), fisheye(rover_model())
    frame = model.wheel_frames((0, 0), (0.15, 0.15), np.zeros(4))[0]
    tex = tread_texture(np.random.default_rng(1))
    for cfg, most in ((TreadConfig(), 0.3), (TreadConfig(boundary=(0, 0)), None)):
        dphi = strip_resolution(model, cam, *frame, cfg.column_px)
        dark, bright = (
            unwrap_tread(render_wheel(model, cam, frame, 0.3, tex, bg), model, cam, *frame, dphi, cfg, "FL")
            for bg in (0, 255)
        )
        both = dark.valid & bright.valid
        rms = float(np.sqrt(np.mean(dark.texture[both] ** 2)))
        worst = float(np.abs(dark.texture - bright.texture)[both].max())
        print(f"boundary {cfg.boundary}: largest change {worst / rms:.2f} RMS of the texture")
        if most is not None:
            assert worst <= most * rms
        else:
            assert worst > rms


def test_the_rotation_deviation_follows_the_error_of_noisy_treads():
    """``RotationMeasurement.std`` against the error of rotations under three levels of image noise."""
    cfg = TreadConfig()
    stds = []
    for noise in (5, 20, 40):
        err, sd = [], []
        for seed in range(6):
            model, strips, dphi, *_ = noisy_tread_pair(
                tread_texture(np.random.default_rng(seed)), noise, cfg, angles=(0.2, 0.3)
            )
            m = measure_strips(*strips, model.wheel_radius, cfg, 0.1, 0.25)
            assert m.valid
            s = m.std(dphi, cfg)
            r = min(max(m.ncc, 0.0), 1.0)
            assert s == pytest.approx(dphi * math.sqrt(1 - r * r) * cfg.noise_cells / m.overlap)
            err.append(m.alpha - 0.1)
            sd.append(s)
        ratio = math.sqrt(np.mean(np.square(err)) / np.mean(np.square(sd)))
        print(f"noise {noise}: RMS error / RMS deviation {ratio:.2f}")
        assert 0.5 <= ratio <= 2.0
        stds.append(np.mean(sd))
    assert stds[0] < stds[1] < stds[2]
    assert RotationMeasurement(math.nan, 0, 0, 0, False).std(0.03, cfg) == math.inf
    assert RotationMeasurement(0.1, 0, 0, 0, True, 0.9, 0).std(0.03, cfg) == math.inf  # no cells compared
    for bad in ({"boundary": (-1, 1)}, {"boundary": (1.5, 1)}, {"clip": math.nan}, {"noise_cells": 0.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TreadConfig(**bad)


def test_a_pattern_fixed_in_the_image_is_learnt_and_taken_out_of_a_turning_tread():
    """A blotchy shade fixed in the image (struts' shadows, a smudge: 40 % RMS, 3 px across)
    over a tread turning 0.23 rad per frame: every plain alignment is lost to it, and once the
    static pattern has five frames, every one is found within 3 %; a tread that then stands
    still is measured still (a standing wheel teaches the pattern nothing), and a black one
    stays without texture."""
    cfg = TreadConfig()
    model = rover_model()
    cam = fisheye(model)
    frame = model.wheel_frames((0.0, 0.0), (0.15, 0.15), np.zeros(4))[1]
    dphi = strip_resolution(model, cam, *frame, cfg.column_px)
    tex = tread_texture(np.random.default_rng(4))
    rng = np.random.default_rng(1)
    w, h = cam.image_size
    shade = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 3.0)
    shade = 1 + 0.4 * shade / shade.std()
    static = StaticPattern(1, cfg.rows, math.ceil(2 * math.pi / dphi) + 1)
    assert static.min_frames == 5

    def strip(theta):
        img = render_wheel(model, cam, frame, theta, tex).astype(np.float32) * shade
        noise = cv2.GaussianBlur(rng.normal(size=img.shape).astype(np.float32), (0, 0), 1.5)
        return unwrap_tread(
            np.clip(img + 10 * noise / noise.std(), 0, 255).astype(np.uint8), model, cam, *frame, dphi, cfg
        )

    alpha, r = 0.23, model.wheel_radius
    plain, removed = [], []
    prev_raw = prev_sub = None
    for n in range(20):
        raw = strip(alpha * n)
        sub = static.remove(0, raw)
        if prev_raw is not None:
            plain.append(measure_pairs([(prev_raw, raw)], r, cfg, [alpha], [0.25], [0])[0])
            removed.append(measure_pairs([(prev_sub, sub)], r, cfg, [alpha], [0.25], [0])[0])
        static.learn(0, raw, alpha)
        prev_raw, prev_sub = raw, sub
    assert sum(m.valid for m in plain) == 0
    late = removed[5:]  # both strips of the pair with the pattern taken out
    assert all(m.valid and abs(m.alpha - alpha) <= 0.03 * alpha for m in late)
    # standing still: measured at zero, and nothing learnt
    before = static._n.copy()
    raw = [strip(0.0), strip(0.0)]
    for s_ in raw:
        static.learn(0, s_, 0.0)
    assert np.array_equal(static._n, before)
    still = measure_pairs([(static.remove(0, raw[0]), static.remove(0, raw[1]))], r, cfg, [0.0], [0.25], [0])[
        0
    ]
    assert still.valid and abs(still.alpha) <= 0.01
    # a black frame has no texture, and none is made for it out of the pattern
    black = unwrap_tread(np.zeros_like(shade, dtype=np.uint8), model, cam, *frame, dphi, cfg)
    assert not np.any(static.remove(0, black).texture)


def test_a_slow_wheel_measured_against_its_key_strip_reads_its_full_rotation():
    """A shade fixed in the image (20 % RMS, 3 px across) pulls a small rotation between
    consecutive frames towards zero: a tread turning one strip column a frame reads 10 % short
    pair by pair. Against the key strip of an earlier frame (``key_rotation``) the rotation is
    measured over many columns, and the frames' rotations add up to the truth within 1.5 % (keys
    of up to 0.25 rad here; the default 0.1 rad of the rover leaves 6 % of this strong shade)."""
    from perception.kinematics.fisheye import KinematicsConfig, KinematicStateEstimator

    model = rover_model()
    cam = fisheye(model)
    cfg = TreadConfig()
    frame = model.wheel_frames((0.0, 0.0), (0.15, 0.15), np.zeros(4))[1]
    dphi = strip_resolution(model, cam, *frame, cfg.column_px)
    rng = np.random.default_rng(1)
    w, h = cam.image_size
    shade = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 3.0)
    shade = 1 + 0.2 * shade / shade.std()
    tex = tread_texture(np.random.default_rng(4))

    def strip(theta):
        img = render_wheel(model, cam, frame, theta, tex).astype(np.float32) * shade
        noise = cv2.GaussianBlur(rng.normal(size=img.shape).astype(np.float32), (0, 0), 1.5)
        img = np.clip(img + 5 * noise / noise.std(), 0, 255).astype(np.uint8)
        return unwrap_tread(img, model, cam, *frame, dphi, cfg)

    est = KinematicStateEstimator(cam, model, KinematicsConfig(key_rotation=0.25))
    alpha = dphi  # one column a frame: 0.8 rad/s, a wheel crawling at 0.1 m/s
    pairwise, keyed = [], []
    prev = None
    for k in range(16):
        s = strip(alpha * k)
        if prev is not None:
            m = measure_pairs([(prev, s)], model.wheel_radius, cfg, [alpha], [0.25], [0])[0]
            assert m.valid
            pairwise.append(m.alpha)
            keyed.append(est._against_keys([s] * 4, [m] * 4)[1])
        est._strips = [s] * 4
        prev = s
    assert all(m.valid for m in keyed)
    total = alpha * len(pairwise)
    assert sum(pairwise) <= 0.93 * total
    assert abs(sum(m.alpha for m in keyed) - total) <= 0.015 * total
    # a fast wheel's key is the frame before: nothing is aligned twice
    fast = KinematicStateEstimator(cam, model)
    a, b = strip(0.0), strip(0.3)
    m = measure_pairs([(a, b)], model.wheel_radius, cfg, [0.3], [0.25], [0])[0]
    fast._strips = [a] * 4
    assert fast._against_keys([b] * 4, [m] * 4)[1] is m
    assert fast._key[1] is b and fast._key_alpha[1] == 0.0
