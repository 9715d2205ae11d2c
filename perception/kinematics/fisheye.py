"""All 10 joint degrees of freedom from one downward fisheye (kinematics paper, Fig. 5).

Per frame: the markers give axle roll, axle-body distance and steering
(:mod:`perception.kinematics.markers`); with them each wheel's tread cylinder is placed and its rotation
since the last frame measured (:mod:`perception.kinematics.wheel_rotation`); the white correction marker on
each tread removes the accumulated rotation drift once per sighting (eq. 7). Degrees of freedom
that cannot be measured in a frame keep their previous value (rotations continue at their last
rate, or at the other wheels' until they have one) and are flagged.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from perception.kinematics.markers import (
    MarkerConfig,
    SteeringCalibration,
    assign_markers,
    marker_projection,
    measure_axles,
    segment_magenta,
)
from perception.kinematics.wheel_rotation import (
    StaticPattern,
    TreadConfig,
    measure_pairs,
    strip_resolution,
    unwrap_treads,
)
from perception.models.cameras import OmniCamera
from perception.models.photometry import cfa_luminance, linear_gray
from perception.models.rover import AXLES, MARKERS, WHEELS, RoverKinematicModel
from perception.models.wheel_kinematics import rolling_speeds

DOF_NAMES: tuple[str, ...] = (
    "psi_F",
    "psi_R",
    "d_F",
    "d_R",
    "lam_F",
    "lam_R",
    "theta_FL",
    "theta_FR",
    "theta_RL",
    "theta_RR",
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KinematicsConfig:
    """Parameters of :class:`KinematicStateEstimator`.

    Attributes:
        markers: Magenta marker segmentation.
        tread: Tread tracking.
        white_min_value: Correction marker: smallest HSV value (0-255) of its cells ...
        white_max_saturation: ... largest saturation ...
        white_min_pixels: ... fewest cells for a sighting ...
        white_contrast: ... and how many times brighter than the tread around them (the median
            of the nearby columns' cells) they are: paint and tread under the same light, lit
            or in shadow.
        white_max_cv: The marker's cells (inside its edge) vary by at most this share of their
            mean: paint is even, lit tread is speckled.
        white_min_area: The marker's blob covers at least this share of the area the whole
            marker would cover facing the camera.
        acquire_span: Rotation search around the last rotation when a wheel is not being
            tracked [rad per frame].
        track_span: The same while it is: the change of rotation between frames [rad].
        track_hold: A wheel stays tracked for this many frames after its last measurement:
            searched within ``track_span`` of its predicted rotation (the last rotation per
            frame, carried on at its last change per frame), its decisive alignments taken
            as they are. Its rotation per frame cannot change that much meanwhile (30 rad/s^2,
            more than a wheel spinning up on sand, changes it by 0.17 rad in 5 frames at 30 Hz),
            while the wide search after a loss must wait for the tread features to confirm it,
            which at 320x240 and 1.5-2 m/s often fail for many frames in a row.
        shadow_robust: Align band-passed treads with shadow edges left out.
        max_wheel_accel: Largest wheel acceleration the rotation's prediction assumes
            [rad/s^2] (the last change of rotation per frame is clipped to it).
        peer_tolerance: A wheel's rotation is not taken when it lies farther than this [rad per
            frame] from the rotation the other wheels predict for it and is near zero (within
            ``tread.static_band``) or has changed from the wheel's own prediction by more than
            ``max_wheel_accel`` allows: the rover's shadow on a tread does not turn, and both the
            alignment and the features can settle on it (GL shadows, shadow mission: a fifth of
            one wheel's frames, 0.2-0.3 rad per frame off). The wheel is then searched for within
            this of its peers' rotation, where its features must confirm the alignment; a wheel
            that is really stuck while the others turn is reported unmeasured, not stuck.
        roi_margin_frac: While every marker is found, each is looked for only within a quarter
            of the gate plus this share of the image width around its predicted pixel (a marker moves
            less than 5 px between frames in 99 % of the frames of a rough drive, and the
            margin holds the blob); a marker not found there is looked for in the whole frame.
        geometry_refresh: The predicted marker pixels and the centroid offsets are computed
            again when the roll or steering has changed by this [rad], or the depth by this [m]
            (the offsets, about 0.2 px, change by at most 0.03 px over 2 degrees).
        max_correction: Largest drift a correction-marker sighting may remove [rad]; a larger
            one means the white blob was not the marker. The first two sightings must agree
            within it to fix the marker's offset.
        reacquire_tolerance: Sightings that ask for a larger correction are taken when two of
            them, at least half a turn apart, agree on it within this [rad] (the drift grew past
            ``max_correction`` while the marker was not seen).
        rate_scale_prior: Each wheel's rates and angle increments are multiplied by a scale
            that the correction marker measures: the rotation between two of its sightings,
            whole turns, over the increments the treads measured in between (least squares over
            the intervals, with this rotation [rad] of prior weight on 1; 0: off). The treads'
            rotation is exact only where the wheel's cylinder model lies where the image shows
            it: a fisheye mount error of millimetres and tenths of a degree makes a wheel's rates
            read 0-2 % off, which dead reckoning on gripping wheels carries into the distance.
        max_rate_scale: Largest change of that scale from 1 [-]; an interval that asks for more
            than twice it is left out (a marker sighting taken for the wrong turn).
        max_steering_zero: Largest steering offset :meth:`KinematicStateEstimator.zero_steering`
            takes out [rad]; a frame that measures more is not of centred steering.
        max_depth_zero: Largest axle-depth offset :meth:`KinematicStateEstimator.zero_depth`
            takes out [m]; a frame that measures more is not of the rover at rest.
        static_rate: Weight of a frame in the learnt static pattern of each tread
            (:class:`~perception.kinematics.wheel_rotation.StaticPattern`), taken out of the strips before
            they are aligned; 0: off. Chosen on recorded drives of the shadow mission (train
            preset, field cameras, seeds 411-416): the frames that lost a wheel fell from 9.3 %
            to 1.8 % (to 1.2 % from 8.9 % on seeds 221-226, not used to choose), the wheel
            rates' error from 0.187 to 0.169 rad/s; weights of 0.2-0.5 did about as well, 0.05
            half as well.
        static_min_rotation: A frame feeds the pattern when the wheel turned at least this in
            it [rad] (the tread's own texture then averages out).
        static_min_frames: Frames a cell needs before its pattern is taken out.
        key_rotation: A slow wheel's rotation is measured against a key strip, the tread of an
            earlier frame, until the wheel has turned this far from it [rad] (or ``key_frames``
            have passed, or an alignment fails); then the frame's strip becomes the key. Between
            consecutive frames a small rotation reads short: something in the treads' image
            does not turn with them (shading, the band-pass's edges), and its correlation peak at
            zero pulls the tread's towards it. On rigid ground, ideal cameras, train preset,
            the rotation per frame read 0.86-0.90 of the truth at 0.4 columns a frame, 0.89-0.94
            at one, 0.95-0.98 at two and 0.99 at four (against keys: 0.97-0.99); aligned against
            the key, each frame's rotation is the key alignment's change, and the rotation
            between keys is measured over several columns. A wheel turning ``key_rotation`` in a
            frame (0.35 m/s of tread at 30 Hz) pairs only with the frame before (no extra
            alignment). At 0.25 rad the keys
            also took the wheels braking in a turn at 3-4 rad/s, and the slip-unaware follower's
            skids on flat ground were missed 2 times of 6 (seeds 0-2, BMI088; 0 without keys).
        key_frames: Most frames a key strip is kept (the light on the treads changes).
        key_span: Search around the predicted rotation from the key [rad].
        static_shrink: The pattern is taken out where it stands this many times above the
            texture left in its estimate (on the rough mission, where little is static, the
            rates' error rose by 7 % with no shrinkage and by 2 % with it).
    """

    markers: MarkerConfig = field(default_factory=MarkerConfig)
    tread: TreadConfig = field(default_factory=TreadConfig)
    white_min_value: int = 25
    white_max_saturation: int = 40
    white_min_pixels: int = 40
    white_contrast: float = 1.4
    white_max_cv: float = 0.1
    white_min_area: float = 0.25
    acquire_span: float = 0.8
    shadow_robust: bool = True
    max_correction: float = 0.2
    reacquire_tolerance: float = 0.06
    track_span: float = 0.25
    track_hold: int = 5
    max_wheel_accel: float = 100.0
    peer_tolerance: float = 0.05
    roi_margin_frac: float = 0.03
    geometry_refresh: tuple[float, float] = (math.radians(2.0), 0.004)
    rate_scale_prior: float = 2.0 * math.pi
    max_rate_scale: float = 0.05
    max_steering_zero: float = 0.1
    max_depth_zero: float = 0.01
    static_rate: float = 0.25
    static_min_rotation: float = 0.08
    static_min_frames: int = 5
    static_shrink: float = 2.0
    key_rotation: float = 0.1
    key_frames: int = 15
    key_span: float = 0.05


@dataclass
class KinematicState:
    """The estimate at one frame. Angles [rad], lengths [m], rates [rad/s]; wheel order FL, FR, RL, RR.

    Attributes:
        t: Time of the frame [s].
        psi: Axle roll (psi_F, psi_R).
        depth: Axle-body distance (d_F, d_R).
        lam: Axle steering (lambda_F, lambda_R).
        delta: Wheel steering angles.
        theta: Integrated wheel rotation since the start.
        theta_dot: Wheel rates.
        valid: Degree of freedom (``DOF_NAMES``) -> measured in this frame.
        markers_found: Magenta markers identified.
        corrected: Wheels whose rotation the correction marker reset in this frame.
        theta_dot_std: Standard deviation of each wheel rate measured in this frame [rad/s]
            (:meth:`~perception.kinematics.wheel_rotation.RotationMeasurement.std` over the frame
            interval; inf where not measured).
    """

    t: float
    psi: np.ndarray
    depth: np.ndarray
    lam: np.ndarray
    delta: np.ndarray
    theta: np.ndarray
    theta_dot: np.ndarray
    valid: dict[str, bool]
    markers_found: int = 0
    corrected: tuple[str, ...] = ()
    theta_dot_std: np.ndarray = field(default_factory=lambda: np.full(4, np.inf))

    @property
    def quality(self) -> float:
        """Share of the 10 degrees of freedom measured in this frame (0-1)."""
        return sum(self.valid.values()) / len(DOF_NAMES)

    @property
    def axles_valid(self) -> bool:
        """Both axles' roll, depth and steering measured in this frame (where the wheels stand)."""
        return all(self.valid[d] for d in DOF_NAMES[:6])


class KinematicStateEstimator:
    """Axle roll, axle-body distance, steering and wheel rotation from fisheye frames.

    Args:
        camera: The fisheye model (its ``T_body_cam`` is the mount).
        model: The rover's kinematic geometry.
        config: Parameters.
        calibration: Use the paper's distance-ratio steering (eq. 5) through this map.
        gamma: The camera's photometric response (:attr:`perception.rig.SensorSpec.gamma`): the
            treads are unwrapped from the linearised grey image, so that their band-pass, which
            divides by the local light level, sees light as a factor.
        bayer: The camera's colour-filter array (:attr:`perception.rig.SensorSpec.bayer`), or
            None: the treads are unwrapped from each pixel's own sample
            (:func:`perception.models.photometry.cfa_luminance`).
    """

    def __init__(
        self,
        camera: OmniCamera,
        model: RoverKinematicModel,
        config: KinematicsConfig | None = None,
        calibration: SteeringCalibration | None = None,
        gamma: float = 1.0,
        bayer: str | None = None,
    ) -> None:
        if not np.allclose(camera.T_body_cam, model.T_body_cam, atol=1e-9):
            raise ValueError("camera.T_body_cam and model.T_body_cam differ; use one fisheye mount for both")
        self.camera = camera
        self.model = model
        self.config = config or KinematicsConfig()
        self.calibration = calibration
        self.gamma = float(gamma)
        self.bayer = bayer
        nominal = model.wheel_frames(np.zeros(2), np.full(2, model.nominal_depth), np.zeros(4))
        # one column step for all wheels (the finest), so that their strips are processed together
        self._dphi = min(
            strip_resolution(model, camera, R, c, self.config.tread.column_px) for R, c in nominal
        )
        cfg = self.config
        self._static = (
            StaticPattern(
                4, cfg.tread.rows, math.ceil(2 * math.pi / self._dphi) + 1, cfg.static_rate,
                cfg.static_min_rotation, cfg.static_min_frames, cfg.static_shrink,
            )
            if cfg.static_rate > 0
            else None
        )  # fmt: skip
        self.reset()

    def reset(self) -> None:
        """Start again from the nominal state (no roll, nominal height, straight ahead, theta 0)."""
        m = self.model
        self._state = KinematicState(
            t=math.nan,
            psi=np.zeros(2),
            depth=np.full(2, m.nominal_depth),
            lam=np.zeros(2),
            delta=np.zeros(4),
            theta=np.zeros(4),
            theta_dot=np.zeros(4),
            valid=dict.fromkeys(DOF_NAMES, False),
        )
        self._alpha = np.zeros(4)  # each wheel's last measured rotation per frame [rad]
        self._trend = np.zeros(4)  # its last change per frame [rad]
        self._missed = np.full(4, 1 << 30)  # frames since each wheel's last measurement
        self._measured = np.zeros(4, dtype=bool)  # measured since the reset
        self._strips: list = [None] * 4  # the last frame's tread strips (static pattern taken out)
        # each wheel's key strip, its rotation from the key to the last frame [rad] and the frames since
        self._key: list = [None] * 4
        self._key_alpha = np.zeros(4)
        self._key_age = np.zeros(4, dtype=int)
        if self._static is not None:
            self._static.reset()
        self._geometry: tuple[np.ndarray, Any] | None = (
            None  # (state, (predicted marker pixels, centroid offsets))
        )
        self._markers_tracked = False  # all markers found in the last frame
        self._offset = np.full(4, math.nan)  # eq. 7: theta - marker phase, once confirmed
        self._pending = np.full(4, math.nan)  # the last unconfirmed sighting's offset
        self._doubt: list = [None] * 4  # (correction, theta) of a sighting too far from theta
        self._fixed_at = np.full(4, math.nan)  # theta at the last correction
        # the treads' rate scale (rate_scale_prior): sums over the marker's intervals of the
        # true rotation times the measured one and of the measured one squared [rad^2], and the
        # increments since the interval began, as measured and as applied (scaled) [rad]
        self._scale = np.ones(4)
        self._scale_sums = np.zeros((4, 2))
        self._since = np.full((4, 2), math.nan)  # NaN: no interval open (no sighting yet)
        self._delta_zero = np.zeros(4)  # steering measured at rest, centred (zero_steering)
        self._lam_zero = np.zeros(2)
        self._depth_zero = np.zeros(2)  # axle depths measured at rest less their rest depths

    @property
    def state(self) -> KinematicState:
        """The latest estimate."""
        return self._state

    @property
    def steering_zero(self) -> np.ndarray:
        """The per-wheel steering offsets (FL, FR, RL, RR) taken out of every frame [rad]."""
        return self._delta_zero.copy()

    @property
    def rate_scale(self) -> np.ndarray:
        """Each wheel's tread-rate scale (FL, FR, RL, RR) the correction marker has measured [-]."""
        return self._scale.copy()

    def _marker_interval(self, k: int, correction: float | None) -> None:
        """Close wheel ``k``'s interval at a marker sighting (None: the first, which opens one)."""
        cfg = self.config
        raw, applied = self._since[k]
        self._since[k] = 0.0
        if correction is None or not math.isfinite(raw) or cfg.rate_scale_prior <= 0:
            return
        true = applied + correction
        if abs(raw) < math.pi or abs(true / raw - 1.0) > 2.0 * cfg.max_rate_scale:
            return  # under half a turn: the sighting's own error weighs too much; or a wrong turn
        self._scale_sums[k] += (true * raw, raw * raw)
        prior = cfg.rate_scale_prior**2
        tr, rr = self._scale_sums[k]
        lim = cfg.max_rate_scale
        self._scale[k] = min(max((tr + prior) / (rr + prior), 1.0 - lim), 1.0 + lim)

    @property
    def depth_zero(self) -> np.ndarray:
        """The axle-depth offsets (F, R) taken out of every frame [m] (see :meth:`zero_depth`)."""
        return self._depth_zero.copy()

    def _rest_measurement(self, img: np.ndarray):
        """The markers' axle measurement of a frame, linearised about the rest state."""
        w, h = self.camera.image_size
        if not self._usable(img):
            raise ValueError(
                f"image: {img.dtype} {img.shape}; give the fisheye's ({h}, {w}, 3) uint8 RGB frame"
            )
        m = self.model
        rest = (np.zeros(2), np.full(2, m.nominal_depth))
        predicted, offsets = marker_projection(m, self.camera, *rest, np.zeros(4))
        cent, _, _ = segment_magenta(img, self.config.markers)
        found = assign_markers(predicted, cent, self.config.markers.gate_frac * w)
        meas = measure_axles(
            m, self.camera, {k: cent[j] for k, j in found.items()}, *rest, self.calibration, offsets=offsets
        )
        return meas, len(found)

    def zero_depth(self, image: np.ndarray, rest_depth=None) -> np.ndarray | None:
        """Take the axle depths a frame of the rover at rest measures as its known rest depths.

        A fisheye mount off its calibration by millimetres and tenths of a degree moves the
        plate markers as the axles sinking or rising by 1-4 mm would, differently per axle. The
        downward odometry's ground plane is drawn through the wheels and reaches the camera
        ahead of the front axle, so such an error changes the camera's height over the ground,
        the odometry's scale, by up to 2 % (randomised mounts of +-3 mm and +-0.5 degrees).
        The depths measured here less ``rest_depth`` are subtracted from every later frame's
        until :meth:`reset`.

        Args:
            image: (H, W, 3) uint8 RGB fisheye frame, the rover at rest on its wheels.
            rest_depth: The axles' depths at rest (F, R) [m]: on level ground both are the
                model's ``nominal_depth`` (the springs' preload carries the body there); on a
                slope the load moves between the axles. None: only the mean of the two axles'
                offsets is taken out (the mean rest depth hardly changes with the slope: by
                0.3 mm at 10 degrees on the simulated rover).

        Returns:
            The offsets taken (F, R) [m], or None: a plate marker missing, or an offset above
            ``max_depth_zero`` (then nothing is taken and a warning is logged).
        """
        meas, found = self._rest_measurement(np.asarray(image))
        if rest_depth is None:
            rest = np.full(2, self.model.nominal_depth)
        else:
            rest = np.asarray(rest_depth, dtype=np.float64).reshape(-1)
            if rest.shape != (2,) or not np.all(np.isfinite(rest)):
                raise ValueError(f"rest_depth: {rest_depth!r}; give the finite (F, R) depths at rest [m]")
        if not np.all(np.isfinite(meas.depth)):
            log.warning("zero_depth: %d of %d markers found; the depths keep no offset", found, len(MARKERS))
            return None
        offset = meas.depth - rest
        if rest_depth is None:
            offset = np.full(2, offset.mean())
        worst = float(np.abs(offset).max())
        if worst > self.config.max_depth_zero:
            log.warning(
                "zero_depth: the frame measures axle depths %.4f m off their rest, more than "
                "max_depth_zero=%g; is the rover at rest on its wheels? the depths keep no offset",
                worst,
                self.config.max_depth_zero,
            )
            return None
        self._depth_zero = offset
        self._geometry = None
        return offset.copy()

    def zero_steering(self, image: np.ndarray) -> np.ndarray | None:
        """Take the steering a frame of the rover at rest, its steering centred, measures as zero.

        A fisheye mount off its calibration by half a degree shifts the tie-rod markers as a
        steering of 10-30 mrad would. The mount itself cannot be recovered from one pose (a
        camera that rolls or pitches and axles that roll or sink look alike to the markers),
        but its effect on the steering hardly changes with the state: the steering measured
        here is subtracted from every later frame's until :meth:`reset` (on synthetic frames with
        mount errors of 0.5 degrees, a worst wheel's error of 40 mrad falls to 10, a mean one's to
        2-5).

        Args:
            image: (H, W, 3) uint8 RGB fisheye frame, the rover at rest with its steering centred.

        Returns:
            The offsets taken (FL, FR, RL, RR) [rad], or None: markers missing, or an offset
            above ``max_steering_zero`` (then nothing is taken and a warning is logged).
        """
        meas, found = self._rest_measurement(np.asarray(image))
        if not (np.all(np.isfinite(meas.delta)) and np.all(np.isfinite(meas.lam))):
            log.warning(
                "zero_steering: %d of %d markers found; the steering keeps no offset",
                found,
                len(MARKERS),
            )
            return None
        worst = float(np.abs(meas.delta).max())
        if worst > self.config.max_steering_zero:
            log.warning(
                "zero_steering: the frame measures %.3f rad of steering, more than max_steering_zero=%g;"
                " is the steering centred? the steering keeps no offset",
                worst,
                self.config.max_steering_zero,
            )
            return None
        self._delta_zero = meas.delta.copy()
        self._lam_zero = meas.lam.copy()
        self._geometry = None
        return self._delta_zero.copy()

    def _usable(self, img: np.ndarray) -> bool:
        """Whether ``img`` is a uint8 RGB frame at the fisheye's resolution."""
        w, h = self.camera.image_size
        return img.dtype == np.uint8 and img.ndim == 3 and img.shape[:2] == (h, w) and img.shape[2] == 3

    def _marker_geometry(self) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """(predicted marker pixels, centroid offsets) at the last state.

        Both are kept until the state moves by ``geometry_refresh`` (angle [rad], depth [m]): the
        offsets change by ~0.015 px per degree and the predictions only place search regions.
        """
        s = self._state
        q = np.concatenate([s.psi, s.delta, s.depth])
        angle, length = self.config.geometry_refresh
        if self._geometry is not None:
            dq = np.abs(q - self._geometry[0])
            if dq[:6].max() <= angle and dq[6:].max() <= length:
                return self._geometry[1]
        # where the image shows them: the depths as measured, before zero_depth's offsets
        depth = s.depth + self._depth_zero
        self._geometry = (q, marker_projection(self.model, self.camera, s.psi, depth, s.delta))
        return self._geometry[1]

    def update(self, image: np.ndarray, t: float) -> KinematicState:
        """Estimate the state at a new frame.

        Args:
            image: (H, W, 3) uint8 RGB fisheye frame at the camera's resolution.
            t: Its time [s], finite and later than the last frame's (else ValueError).

        Returns:
            The state; a frame that cannot be used (wrong size or type, black, saturated, no
            markers) gives the previous state carried forward, finite, with every flag False.
        """
        if not math.isfinite(t):
            raise ValueError(f"t={t!r}: a frame's time must be finite [s]")
        prev = self._state
        if math.isfinite(prev.t) and not t > prev.t:
            raise ValueError(
                f"t={t!r} s does not follow the last frame's {prev.t!r} s; give increasing times"
            )
        img = np.asarray(image)
        w, h = self.camera.image_size
        usable = self._usable(img)
        dt = t - prev.t if math.isfinite(prev.t) else math.nan
        if not usable:
            return self._carry(t, dt)
        cfg = self.config
        predicted, offsets = self._marker_geometry()
        gate = cfg.markers.gate_frac * w
        found: dict = {}
        if self._markers_tracked:  # look where the markers should be first
            at = np.array([p for p in predicted.values() if np.all(np.isfinite(p))])
            reach = 0.25 * gate + cfg.roi_margin_frac * w
            cent, _, _ = segment_magenta(img, cfg.markers, np.hstack([at - reach, at + reach + 1]))
            found = assign_markers(predicted, cent, gate)
        if len(found) < len(MARKERS):  # lost one: search the whole frame
            cent, _, _ = segment_magenta(img, cfg.markers)
            found = assign_markers(predicted, cent, gate)
        self._markers_tracked = len(found) == len(MARKERS)
        meas = measure_axles(
            self.model,
            self.camera,
            {m: cent[j] for m, j in found.items()},
            prev.psi,
            prev.depth + self._depth_zero,
            self.calibration,
            offsets=offsets,
        )
        psi = np.where(np.isfinite(meas.psi), meas.psi, prev.psi)
        depth = np.where(np.isfinite(meas.depth), meas.depth - self._depth_zero, prev.depth)
        lam = np.where(np.isfinite(meas.lam), meas.lam - self._lam_zero, prev.lam)
        from_lam = self.model.wheel_angles(*lam)
        delta = np.where(np.isfinite(meas.delta), meas.delta - self._delta_zero, from_lam)
        valid = {f"psi_{a}": bool(np.isfinite(meas.psi[i])) for i, a in enumerate(AXLES)}
        valid.update({f"d_{a}": bool(np.isfinite(meas.depth[i])) for i, a in enumerate(AXLES)})
        valid.update({f"lam_{a}": bool(np.isfinite(meas.lam[i])) for i, a in enumerate(AXLES)})
        # the treads' band-pass divides light levels: linear ones, without the colour-filter
        # array's checker (fixed to the sensor, it would be found at zero rotation)
        gray: np.ndarray | Callable[[int, int, int, int], np.ndarray]
        if self.bayer is not None:
            # only about the treads (the image is mostly other things)
            pattern, gamma = self.bayer, self.gamma

            def gray(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
                return cfa_luminance(img, pattern, gamma, rect=(x0, y0, x1, y1))
        else:
            gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            if self.gamma != 1.0:
                gray = linear_gray(gray, self.gamma)
        theta, theta_dot = prev.theta.copy(), prev.theta_dot.copy()
        rate_std = np.full(4, np.inf)
        corrected = []
        # the treads where the image shows them (the depths as measured, as the markers are)
        curr_frames = self.model.wheel_frames(psi, depth + self._depth_zero, delta)
        raw = unwrap_treads(
            gray, self.model, self.camera, curr_frames, self._dphi, cfg.tread, list(WHEELS), cfg.shadow_robust
        )
        static = self._static
        strips = raw if static is None else [static.remove(k, s_) for k, s_ in enumerate(raw)]
        if dt > 0:
            r = self.model.wheel_radius
            pairs = list(zip(self._strips, strips, strict=True))
            tracked = self._missed <= cfg.track_hold
            spans = [cfg.track_span if tracked[k] else cfg.acquire_span for k in range(4)]
            # while a wheel is searched for over the wide span, the features must confirm the
            # alignment (a strong false peak is possible there); while it is tracked, a strong or
            # decisive alignment is taken as it is (strong ones are checked with check_strong)
            check = [int(cfg.tread.check_strong) if on else 2 for on in tracked]
            # a tracked wheel's rotation per frame carries on at its last change
            prior = self._alpha + np.where(tracked, self._trend * (self._missed + 1), 0.0)
            rots = measure_pairs(pairs, r, cfg.tread, prior.tolist(), spans, check)
            # a wheel not measured gets a second search around the rotation the wheels that
            # were predict for it: scaled by the steering geometry (wheels that roll turn in
            # proportion to their distance from the centre of rotation), they differ by slip,
            # not by multiples. Within track_span of it, the rules of a tracked wheel hold (the
            # other wheels are its prediction); a wheel not yet tracked is then searched over
            # acquire_span, where the features must confirm
            good = [k for k in range(4) if rots[k].valid]
            lost = [k for k in range(4) if not rots[k].valid]
            peer = (
                self._peer_rotations(curr_frames, delta, {k: rots[k].alpha for k in good})
                if good and lost
                else []
            )
            for near in (True, False):
                again = [k for k in lost if not rots[k].valid and (near or not tracked[k])]
                if not (peer and again):
                    continue
                more = measure_pairs(
                    [pairs[k] for k in again], r, cfg.tread, [peer[k] for k in again],
                    [cfg.track_span if near else cfg.acquire_span] * len(again),
                    [int(cfg.tread.check_strong) if near else 2] * len(again),
                )  # fmt: skip
                for k, m in zip(again, more, strict=True):
                    rots[k] = m
            rots = self._check_against_peers(pairs, rots, prior, curr_frames, delta, dt)
            rots = self._against_keys(strips, rots)
            alphas = [r.alpha for r in rots if r.valid]  # this frame's rotations [rad]
            for k, wheel in enumerate(WHEELS):
                rot = rots[k]
                if rot.valid:
                    if tracked[k] and self._measured[k]:
                        bound = cfg.max_wheel_accel * dt * dt
                        change = (rot.alpha - self._alpha[k]) / (self._missed[k] + 1)
                        self._trend[k] = min(max(change, -bound), bound)
                    else:
                        self._trend[k] = 0.0
                    self._alpha[k] = rot.alpha
                    self._measured[k] = True
                    step = rot.alpha * self._scale[k]
                    self._since[k] += (rot.alpha, step)
                    theta[k] += step
                    theta_dot[k] = step / dt
                    rate_std[k] = rot.std(self._dphi, cfg.tread) * self._scale[k] / dt
                    self._missed[k] = 0
                else:
                    self._missed[k] += 1
                    if not self._measured[k] and alphas:  # no rate of its own yet: the others'
                        theta_dot[k] = float(np.median(alphas)) * self._scale[k] / dt
                    self._since[k] += (theta_dot[k] * dt / self._scale[k], theta_dot[k] * dt)
                    theta[k] += theta_dot[k] * dt
                valid[f"theta_{wheel}"] = rot.valid
                if static is not None and alphas:
                    # a wheel not measured in this frame is taken to turn as predicted: the
                    # pattern is often what lost it (a frame with no wheel measured, such as a
                    # dark one, teaches nothing)
                    static.learn(k, raw[k], rot.alpha if rot.valid else prior[k])
        else:
            valid.update({f"theta_{w_}": False for w_ in WHEELS})
        for k, wheel in enumerate(WHEELS):
            if abs(theta[k] - self._fixed_at[k]) < math.pi:
                continue  # corrected in this pass of the marker already: once per turn is enough
            # where the marker should be, if it was seen within the last turn
            recent = abs(theta[k] - self._fixed_at[k]) < 2 * math.pi
            expected = theta[k] - self._offset[k] if recent else math.nan
            if not self._marker_may_show(strips[k], expected):
                continue
            phase = self._marker_phase(img, strips[k])
            if phase is None:
                continue
            if not math.isfinite(self._offset[k]):
                # c0 of eq. 7: fixed once two sightings agree on it (one may be a false one)
                offset = theta[k] - phase
                gap = math.remainder(offset - self._pending[k], 2 * math.pi)
                if abs(gap) <= cfg.max_correction:
                    self._offset[k] = offset
                    self._marker_interval(k, None)
                self._pending[k] = offset
                continue
            fixed = self._correct(k, theta[k], phase)
            if fixed is not None:
                self._marker_interval(k, fixed - theta[k])
                theta[k] = fixed
                corrected.append(wheel)
        self._strips = strips
        self._state = KinematicState(
            t, psi, depth, lam, delta, theta, theta_dot, valid, len(found), tuple(corrected), rate_std
        )
        return self._state

    def _check_against_peers(self, pairs, rots, prior, frames, delta, dt: float):
        """Rotations that the other wheels contradict, searched for again near theirs (``peer_tolerance``)."""
        cfg = self.config
        bound = cfg.max_wheel_accel * dt * dt
        speeds = rolling_speeds(np.array([c[:2] for _, c in frames]), delta)
        suspect, near = [], []
        for k, rot in enumerate(rots):
            others = {j: rots[j].alpha for j in range(len(rots)) if j != k and rots[j].valid}
            if not (rot.valid and others):
                continue
            peer = self._peer_rotations(frames, delta, others, speeds)[k]
            static = abs(rot.alpha) < cfg.tread.static_band
            jump = abs(rot.alpha - prior[k]) > bound
            weak = rot.ncc < cfg.tread.strong_ncc
            if abs(rot.alpha - peer) > cfg.peer_tolerance and (static or jump or weak):
                suspect.append(k)
                near.append(peer)
        if not suspect:
            return rots
        again = measure_pairs(
            [pairs[k] for k in suspect], self.model.wheel_radius, cfg.tread, near,
            [cfg.peer_tolerance] * len(suspect), [2] * len(suspect),
        )  # fmt: skip
        rots = list(rots)
        for k, m in zip(suspect, again, strict=True):
            rots[k] = m
        return rots

    def _against_keys(self, strips: list, rots: list) -> list:
        """Each slow wheel's rotation in this frame, measured against its key strip (``key_rotation``).

        A wheel whose key is older than the last frame is aligned with it around the rotation
        from the key plus this frame's; where that alignment is valid, the frame's rotation is
        its change since the last frame. The keys move on here.
        """
        cfg = self.config
        old = [
            k for k in range(4)
            if rots[k].valid and self._key[k] is not None and self._key_age[k] >= 1 and strips[k] is not None
        ]  # fmt: skip
        rots = list(rots)
        if old:
            again = measure_pairs(
                [(self._key[k], strips[k]) for k in old], self.model.wheel_radius, cfg.tread,
                [self._key_alpha[k] + rots[k].alpha for k in old], [cfg.key_span] * len(old),
                [int(cfg.tread.check_strong)] * len(old),
            )  # fmt: skip
            for k, m in zip(old, again, strict=True):
                if m.valid:  # the frame pair's correlation still sets the rate's deviation
                    rots[k] = replace(
                        m, alpha=m.alpha - self._key_alpha[k], ncc=rots[k].ncc, overlap=rots[k].overlap
                    )
                else:
                    self._key[k] = None  # from the frame before: this frame's rotation stands
        for k in range(4):
            if rots[k].valid and self._key[k] is not None:
                self._key_alpha[k] += rots[k].alpha
                self._key_age[k] += 1
            else:  # no rotation measured, or none against the key
                self._key[k], self._key_alpha[k], self._key_age[k] = self._strips[k], 0.0, 0
                if rots[k].valid:
                    self._key_alpha[k], self._key_age[k] = rots[k].alpha, 1
            if (
                abs(self._key_alpha[k]) >= cfg.key_rotation
                or self._key_age[k] >= cfg.key_frames
                or not rots[k].valid
            ):
                self._key[k], self._key_alpha[k], self._key_age[k] = strips[k], 0.0, 0
        return rots

    @staticmethod
    def _peer_rotations(frames, delta: np.ndarray, measured: dict[int, float], speeds=None) -> list[float]:
        """Each wheel's rotation [rad] as the measured wheels (at least one) predict it.

        Theirs scaled by the ratio of the wheels' rolling speeds (:func:`rolling_speeds`, or
        ``speeds`` when already known), median over them; a wheel near the centre of rotation
        (under a fifth of the fastest speed) would scale its noise without bound and predicts
        nothing.
        """
        if speeds is None:
            speeds = rolling_speeds(np.array([c[:2] for _, c in frames]), delta)
        usable = [j for j in measured if abs(speeds[j]) >= 0.2]
        if not usable:
            return [float(np.median(list(measured.values())))] * len(frames)
        return [
            float(np.median([measured[j] * speeds[k] / speeds[j] for j in usable]))
            for k in range(len(frames))
        ]

    def _carry(self, t: float, dt: float) -> KinematicState:
        prev = self._state
        theta = prev.theta + (prev.theta_dot * dt if dt > 0 else 0.0)
        self._strips = [None] * 4  # the next usable frame cannot be paired with an unusable one
        self._key = [None] * 4
        self._state = KinematicState(
            t,
            prev.psi.copy(),
            prev.depth.copy(),
            prev.lam.copy(),
            prev.delta.copy(),
            theta,
            prev.theta_dot.copy(),
            dict.fromkeys(DOF_NAMES, False),
        )
        return self._state

    def _correct(self, k: int, theta: float, phase: float) -> float | None:
        """Eq. 7 for wheel ``k``: the corrected angle for a marker sighting at ``phase``, or None.

        A sighting asking for more than ``max_correction`` is a false one, or drift that grew
        while the marker was not seen: two such sightings at least half a turn apart that ask
        for the same correction (within ``reacquire_tolerance``) are the marker, since nothing
        else white turns with the wheel.
        """
        cfg = self.config
        target = phase + self._offset[k]
        snapped = target + 2 * math.pi * round((theta - target) / (2 * math.pi))
        fix = snapped - theta
        if abs(fix) > cfg.max_correction:
            d = self._doubt[k]
            later = d is not None and abs(theta - d[1]) >= math.pi
            if not (later and abs(fix - d[0]) <= cfg.reacquire_tolerance):
                if d is None or later:
                    self._doubt[k] = (fix, theta)
                return None
        self._doubt[k] = None
        self._fixed_at[k] = snapped
        return snapped

    def _marker_may_show(self, strip, expected: float) -> bool:
        """Whether the correction marker, expected at ``expected`` [rad] (NaN: unknown), can be in view."""
        if strip is None:
            return False
        if not math.isfinite(expected):
            return True
        lo, hi = strip.k0 * strip.dphi, (strip.k0 + strip.pixels.shape[1]) * strip.dphi
        mid = 0.5 * (lo + hi)
        at = mid + math.remainder(expected - mid, 2 * math.pi)  # the marker's turn nearest the strip
        reach = self.model.correction_marker_arc / 2 + self.config.max_correction
        return lo - reach <= at <= hi + reach

    def _marker_phase(self, img: np.ndarray, strip) -> float | None:
        """Wheel-angle phase of the white correction marker if it is on the tread strip.

        The marker sits at wheel angle 0 on the +z side of the wheel, so at wheel angle theta it
        is seen at angle theta about the axle (from the knuckle's +z toward +x).
        """
        cfg = self.config
        if strip is None:
            return None
        vis = strip.visible
        hsv = cv2.cvtColor(strip.sample(img), cv2.COLOR_RGB2HSV)
        # paint against tread is a ratio of linear levels
        v = linear_gray(hsv[..., 2], self.gamma) if self.gamma != 1.0 else hsv[..., 2].astype(np.float32)
        sat = hsv[..., 1]
        # the marker is white paint on a grey tread: far brighter than the tread around it under
        # the same light, whatever that light is
        # the tread's level around each column: the median over the cells of the columns within
        # about two marker widths (lit and shadowed parts of the tread each keep their own)
        arc = self.model.correction_marker_arc
        col_med = _masked_median(v, vis, axis=0)
        half = max(1, int(round(2 * arc / strip.dphi)))
        padded = np.concatenate([np.full(half, np.nan), col_med, np.full(half, np.nan)])
        windows = np.lib.stride_tricks.as_strided(  # read-only view: (columns, 2 half + 1)
            padded, (len(col_med), 2 * half + 1), (padded.strides[0],) * 2, writeable=False
        )
        level = _masked_median(windows, np.isfinite(windows), axis=1)
        bright = (v >= cfg.white_min_value) & (v >= cfg.white_contrast * np.nan_to_num(level, nan=255.0))
        white = (vis & bright & (sat <= cfg.white_max_saturation)).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(white, connectivity=8)
        if n <= 1:
            return None
        big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        # the painted marker is one patch of its known arc across the tread; speckle is small spots
        expected = arc / strip.dphi * vis.shape[0]
        if stats[big, cv2.CC_STAT_AREA] < max(cfg.white_min_pixels, cfg.white_min_area * expected):
            return None
        blob = labels == big
        inner = cv2.erode(blob.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        vals = v[inner] if inner.sum() >= 10 else v[blob]
        if vals.std() > cfg.white_max_cv * vals.mean():  # paint is even; lit tread is speckled
            return None
        cols = np.nonzero(blob)[1]
        phi = (strip.k0 + cols) * strip.dphi
        mean = float(phi.mean())
        # the whole marker in view: its cells span about its arc, centred on the mean
        if not (0.6 * arc <= 2 * np.percentile(np.abs(phi - mean), 95) <= 1.3 * arc):
            return None
        return mean


def _masked_median(a: np.ndarray, mask: np.ndarray, axis: int) -> np.ndarray:
    """Median of ``a`` over the cells of ``mask`` along ``axis`` (NaN where there are none).

    The same as ``np.nanmedian`` of the masked array, by one sort (several times faster on
    small arrays).
    """
    srt = np.sort(np.moveaxis(np.where(mask, a, np.inf), axis, -1), axis=-1)
    n = mask.sum(axis=axis).reshape(-1)
    flat = srt.reshape(-1, srt.shape[-1])
    rows = np.arange(len(flat))
    lo = flat[rows, np.maximum(n - 1, 0) // 2]
    hi = flat[rows, np.minimum(n // 2, flat.shape[1] - 1)]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan).reshape(srt.shape[:-1])


__all__ = ["DOF_NAMES", "KinematicState", "KinematicStateEstimator", "KinematicsConfig", "MARKERS"]
