"""Learned policies (stable-baselines3) as controllers: residual policies on the estimator, and their loader.

The learned policy is residual (Johannink et al. 2019, "Residual reinforcement learning for robot
control"): its action is added to the path follower's drive command (speed, lambda_F,
lambda_R), scaled by ``scale`` per component, and the sum is clipped to [-1, 1]. By default
the slip-aware traction controller (:class:`~controllers.SlipAwareController`) then turns
that command into per-wheel speeds within its slip bounds: the policy learns speed and
steering, the classical layer keeps the wheels from digging in (base ``"traction"``,
``wheels`` action mode). Base ``"follower"`` sends the command to the environment as it is
(``drive`` mode). At the start of training the rover already follows the course, so the
policy learns only what its base lacks, from far fewer steps than driving from scratch.
:class:`Residual` composes the two; :class:`PolicyController` turns a saved run into a
:class:`~controllers.Controller`. Training (which needs the environments) is
:mod:`rover_env.tools.training`.

Needs the ``rl`` extra: ``pip install 'rover-vision[rl]'``.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from controllers.path_follower import PathFollower
from controllers.traction import SlipAwareController

log = logging.getLogger(__name__)

#: The policy shipped with the package (``rover train`` output, see the README).
SHIPPED = Path(__file__).parent / "policies" / "ppo_residual"
POLICY_FILE = "policy.zip"
#: The observation statistics as plain arrays (mean, var, count, clip_obs, epsilon): no pickle.
STATS_FILE = "obs_stats.npz"
#: What older folders hold instead: SB3's pickled VecNormalize (loading it runs code).
NORMALIZE_FILE = "vecnormalize.pkl"
META_FILE = "policy.json"
#: Keys that ``policy.json`` must hold.
META_KEYS = ("algo", "action_mode", "obs_fields", "residual")


#: Bases of a residual policy: the environment action mode each acts in.
BASES = {"traction": "wheels", "follower": "drive"}


def check_base(base: str) -> None:
    """Raise ValueError unless ``base`` is a key of :data:`BASES`."""
    if base not in BASES:
        raise ValueError(f"base {base!r}: choose one of {sorted(BASES)}")


class Residual:
    """A base controller's drive command plus a scaled residual.

    The drive command is the path follower's (speed, lambda_F, lambda_R) in action units; the
    residual, times ``scale``, is added to it and the sum clipped to [-1, 1]. With a
    :class:`~controllers.PathFollower` base that sum is the environment's action (``drive``
    mode); with a :class:`~controllers.SlipAwareController` base its traction control turns it
    into per-wheel commands within the slip bounds (``wheels`` mode), so the policy chooses
    speed and steering while the wheels stay near the slip set-point.

    Args:
        base: The base controller.
        scale: Residual range per component (speed, lambda_F, lambda_R), in action units.
    """

    def __init__(self, base: PathFollower | SlipAwareController, scale: Sequence[float]) -> None:
        if not isinstance(base, (PathFollower, SlipAwareController)):
            raise TypeError(f"base: {type(base).__name__}; expected a PathFollower or a SlipAwareController")
        self.base = base
        self.scale = np.asarray(scale, dtype=np.float32)
        if self.scale.shape != (3,) or np.any(self.scale < 0):
            raise ValueError(f"scale: {scale!r}; expected three non-negative numbers")

    @classmethod
    def for_env(cls, env: gym.Env, scale: Sequence[float]) -> Residual:
        """The residual for ``env``'s action mode: traction base for ``wheels``, follower for ``drive``."""
        base: Any = env.unwrapped  # a RoverEnv (controllers do not import the environment)
        mode = base.action_mode.value
        if mode == "wheels":
            return cls(SlipAwareController.for_env(env), scale)
        if mode == "drive":
            return cls(PathFollower.for_env(env), scale)
        raise ValueError(f"a residual policy acts in action_mode 'drive' or 'wheels', not {mode!r}")

    @property
    def follower(self) -> PathFollower:
        """The path follower that gives the drive command."""
        return self.base.follower if isinstance(self.base, SlipAwareController) else self.base

    def reset(self) -> None:
        """Reset the base controller (start of an episode)."""
        self.base.reset()

    def compose(self, obs: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """The environment action for ``obs`` and ``residual`` (advances the base controller).

        The speed stays at or above the follower's ``min_speed``: the policy can slow the rover
        but not stop it (a rover stopped mid-turn on a slope, its wheels held at its ground
        speed by traction control, stays stopped: a deadlock the policy's mean can fall into).
        """
        f = self.follower.cfg
        drive = np.clip(
            self.follower.act(obs) + self.scale * np.asarray(residual, dtype=np.float32), -1.0, 1.0
        )
        drive[0] = max(drive[0], f.min_speed / f.v_max)
        if isinstance(self.base, PathFollower):
            return drive
        lam_f, lam_r = float(drive[1]) * f.steer_limit, float(drive[2]) * f.steer_limit
        commands = self.base.limit(obs, float(drive[0]) * f.v_max, lam_f, lam_r)
        return self.base.action(commands, lam_f, lam_r)


def observation_fields() -> list[str]:
    """The observation table's field names, in order (what a policy folder records)."""
    from perception.observation import OBS_FIELDS

    return list(OBS_FIELDS)


class ObsStats:
    """Running observation statistics of a training run, and the normalisation VecNormalize applies.

    Args:
        mean, var: Per input [its units, squared].
        count: Samples behind them.
        clip_obs: Normalised inputs are clipped to +-clip_obs.
        epsilon: Added to the variance.
    """

    def __init__(self, mean, var, count: float, clip_obs: float, epsilon: float) -> None:
        self.mean = np.asarray(mean, dtype=np.float64)
        self.var = np.asarray(var, dtype=np.float64)
        self.count, self.clip_obs, self.epsilon = float(count), float(clip_obs), float(epsilon)
        ok = self.mean.ndim == 1 and self.var.shape == self.mean.shape
        finite = np.all(np.isfinite(self.mean)) and np.all(np.isfinite(self.var))
        ok = ok and bool(finite and np.all(self.var >= 0))
        if not (ok and self.count > 0 and self.clip_obs > 0 and self.epsilon > 0):
            raise ValueError(
                "observation statistics: need finite 1-D mean and var >= 0, count, clip_obs, epsilon > 0"
            )

    @classmethod
    def load(cls, path: str | Path) -> ObsStats:
        """Read :func:`save_obs_stats`'s file (ValueError naming it if it is not one)."""
        try:
            with np.load(path, allow_pickle=False) as d:
                return cls(d["mean"], d["var"], d["count"], d["clip_obs"], d["epsilon"])
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"{path}: not observation statistics written by rover train ({exc})") from None

    def normalize(self, x: np.ndarray) -> np.ndarray:
        """``x`` as the policy saw it in training: centred, scaled and clipped."""
        z = (np.asarray(x, dtype=np.float64) - self.mean) / np.sqrt(self.var + self.epsilon)
        return np.clip(z, -self.clip_obs, self.clip_obs)


def _read_meta(path: Path) -> dict:
    """``policy.json`` of a policy folder, checked: a mapping with :data:`META_KEYS` and a known algorithm."""
    meta_path = path / META_FILE
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{meta_path}: not readable JSON ({exc}); retrain or restore the file") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object with keys {', '.join(META_KEYS)}")
    missing = [k for k in META_KEYS if k not in meta]
    if missing:
        raise ValueError(f"{meta_path}: missing {', '.join(missing)}; retrain or restore the file")
    if meta["algo"] not in ("ppo", "sac"):
        raise ValueError(f"{meta_path}: algo {meta['algo']!r} is not 'ppo' or 'sac'")
    if meta["action_mode"] not in BASES.values():
        raise ValueError(
            f"{meta_path}: action_mode {meta['action_mode']!r} is not one of {sorted(BASES.values())}"
        )
    if not (isinstance(meta["obs_fields"], list) and all(isinstance(n, str) for n in meta["obs_fields"])):
        raise ValueError(f"{meta_path}: obs_fields must be a list of observation field names")
    res = meta["residual"]
    if res is not None and not (
        isinstance(res, list)
        and len(res) == 3
        and all(isinstance(v, int | float) and math.isfinite(v) for v in res)
    ):
        raise ValueError(f"{meta_path}: residual must be null or three finite numbers")
    return meta


def _load_model(cls, file: Path, meta: dict):
    """The SB3 model in ``file``, built without unpickling anything when ``meta`` gives its spaces.

    An SB3 zip holds its network weights (read with ``torch.load(weights_only=True)``) and a JSON
    of parameters, some of which are cloudpickled objects (the policy class, the spaces, the
    schedules, the last observation): unpickling runs code. With ``obs_dim``, ``action_low`` and
    ``action_high`` in ``policy.json`` (``rover train`` writes them), every pickled entry is
    replaced by its known value, so nothing is unpickled. Older folders fall back to SB3's
    loader (with a warning).
    """
    import zipfile

    from gymnasium import spaces

    if not all(k in meta for k in ("obs_dim", "action_low", "action_high")):
        log.warning(
            "%s: policy.json has no spaces (an older rover train); loading unpickles its objects, "
            "which runs code: load only folders you trust", file.parent,
        )  # fmt: skip
        return cls.load(file, device="cpu")
    try:
        with zipfile.ZipFile(file) as z:
            data = json.loads(z.read("data"))
    except (OSError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{file}: not a policy saved by rover train ({exc})") from None
    low = np.asarray(meta["action_low"], dtype=np.float32)
    high = np.asarray(meta["action_high"], dtype=np.float32)
    known = {
        "policy_class": cls.policy_aliases["MlpPolicy"],
        "observation_space": spaces.Box(-np.inf, np.inf, (int(meta["obs_dim"]),), np.float32),
        "action_space": spaces.Box(low, high, dtype=np.float32),
        "lr_schedule": lambda _: 0.0,
        "learning_rate": 0.0,
        "clip_range": lambda _: 0.0,
        "clip_range_vf": None,
        "rollout_buffer_class": None,
        "replay_buffer_class": None,
    }
    custom = {}
    for key, item in data.items():
        if isinstance(item, dict) and ":serialized:" in item:
            custom[key] = known.get(key)  # None for the rest (last observation, episode buffers)
    try:
        return cls.load(file, device="cpu", custom_objects=custom)
    except (ValueError, KeyError, RuntimeError) as exc:
        raise ValueError(f"{file}: does not load as a {meta['algo']} policy ({exc})") from None


def policy_action_mode(path: str | Path) -> str:
    """The environment action mode (``"wheels"`` or ``"drive"``) of the policy saved in ``path``."""
    meta = Path(path) / META_FILE
    if not meta.is_file():
        raise FileNotFoundError(f"{meta} is missing; point to the folder `rover train` wrote")
    try:
        mode = json.loads(meta.read_text())["action_mode"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{meta}: malformed ({exc}); retrain or restore the file") from exc
    if mode not in BASES.values():
        raise ValueError(f"{meta}: action_mode {mode!r} is not one of {sorted(BASES.values())}")
    return mode


def shipped_policy() -> Path:
    """The folder of the policy shipped with the package (:class:`PolicyController` loads it)."""
    if not (SHIPPED / POLICY_FILE).is_file():
        raise FileNotFoundError(
            f"{SHIPPED} holds no policy; reinstall the package or train one (rover train)"
        )
    return SHIPPED


def _load_stats(path: Path) -> ObsStats:
    """The folder's observation statistics: ``obs_stats.npz``, else (older folders) ``vecnormalize.pkl``."""
    if (path / STATS_FILE).is_file():
        return ObsStats.load(path / STATS_FILE)
    pkl = path / NORMALIZE_FILE
    if not pkl.is_file():
        raise FileNotFoundError(f"{path / STATS_FILE} is missing; point to the folder `rover train` wrote")
    import pickle

    log.warning("%s: unpickling it (an older rover train) runs code: load only folders you trust", pkl)
    try:
        with open(pkl, "rb") as fh:
            vn = pickle.load(fh)  # noqa: S301 (documented trust boundary)
        rms = vn.obs_rms
        return ObsStats(rms.mean, rms.var, rms.count, vn.clip_obs, vn.epsilon)
    except Exception as exc:  # a garbage pickle raises anything
        raise ValueError(
            f"{pkl}: not a VecNormalize saved by rover train ({type(exc).__name__}: {exc})"
        ) from None


class PolicyController:
    """A saved policy (:func:`train`) as a :class:`~controllers.Controller` for one environment.

    Args:
        path: The training run's folder (``policy.zip``, ``vecnormalize.pkl``, ``policy.json``).
        env: The environment it will drive, in the policy's action mode (``policy.json``:
            ``wheels`` for a traction base, ``drive`` for a follower base); the residual's base
            controller is built for it.
        deterministic: Act on the policy's mean (default) or sample.

    The policy reads the observation fields it was trained on (``policy.json``) by name, so a
    policy trained before fields were added to the observation drives unchanged; one trained on
    a field the environment lacks is refused.
    """

    def __init__(self, path: str | Path, env: gym.Env, deterministic: bool = True) -> None:
        from stable_baselines3 import PPO, SAC

        path = Path(path)
        for name in (POLICY_FILE, META_FILE):
            if not (path / name).is_file():
                raise FileNotFoundError(f"{path / name} is missing; point to the folder `rover train` wrote")
        if path.resolve() != SHIPPED.resolve():
            log.warning(
                "policy from outside the package (%s): its weights and statistics load without "
                "unpickling, but older folders unpickle theirs (running code) and any policy decides "
                "how the rover drives: use folders you made or trust", path,
            )  # fmt: skip
        self.meta = _read_meta(path)
        base: Any = env.unwrapped
        if base.action_mode.value != self.meta["action_mode"]:
            raise ValueError(f"the policy acts in action_mode={self.meta['action_mode']!r}; make the env so")
        trained_imu = self.meta.get("imu")
        pipeline = getattr(base, "pipeline", None)
        if trained_imu and pipeline is not None and pipeline.imu is None:
            log.warning(
                "%s: the policy was trained with an IMU (%s) and this environment has none: its yaw "
                "rate, roll and pitch are not what it saw; drive it with one (rover eval --controllers "
                "NAME@imu:%s, or gym.make(..., imu=%r))", path, trained_imu, trained_imu, trained_imu,
            )  # fmt: skip
        # the policy's inputs by name: a policy trained before fields were added still reads its own
        names = [f.name for f in base.obs_fields]
        trained = list(self.meta["obs_fields"])
        missing = [n for n in trained if n not in names]
        if missing:
            raise ValueError(
                f"{path}: the policy was trained on observation fields {missing} that this "
                "environment does not have; retrain it (rover train)"
            )
        n_state = len(observation_fields())  # the previous action follows the state fields
        self._inputs = np.array([names.index(n) for n in trained] + list(range(n_state, len(names))))
        cls = {"ppo": PPO, "sac": SAC}[self.meta["algo"]]
        self.model = _load_model(cls, path / POLICY_FILE, self.meta)
        self._normalize = _load_stats(path)
        scale = self.meta["residual"]
        self.residual = None if scale is None else Residual.for_env(env, scale)
        self.deterministic = deterministic
        # fields that never varied in training (the quality fields on ground truth): their variance
        # is only what the running statistics' prior (variance 1, weight 1e-4) left, and any change
        # there normalises to far outside what the policy saw
        rms = self._normalize
        if rms.mean.shape != self._inputs.shape:
            raise ValueError(
                f"{path}: the observation statistics cover {rms.mean.size} inputs, {POLICY_FILE} "
                f"expects {self._inputs.size}; the folder mixes two runs, retrain or restore it"
            )
        prior = 2e-4 * (1.0 + rms.mean**2) / max(float(rms.count), 1e-4)
        self._constant = np.flatnonzero(rms.var <= prior)
        self._constant_mean = rms.mean[self._constant]
        self._warned = False

    def reset(self) -> None:
        """Reset the residual's base controller."""
        if self.residual is not None:
            self.residual.reset()

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The action for ``obs`` (raw, as the environment returns it), in the policy's action mode."""
        seen = np.asarray(obs)[self._inputs]
        if not self._warned and np.any(np.abs(seen[self._constant] - self._constant_mean) > 1e-3):
            fields = self.meta["obs_fields"]
            names = [
                fields[i] if i < len(fields) else f"previous action {i - len(fields)}" for i in self._constant
            ]
            log.warning(
                "observation fields %s vary but were constant in training (obs_source=%r): the "
                "policy sees inputs it never saw; train it on the observation source it drives on",
                names, self.meta.get("obs_source"),
            )  # fmt: skip
            self._warned = True
        x = self._normalize.normalize(seen).astype(np.float32)
        a, _ = self.model.predict(x, deterministic=self.deterministic)
        if self.residual is not None:
            return self.residual.compose(obs, a)
        return np.clip(a, -1.0, 1.0).astype(np.float32)


__all__ = [
    "BASES",
    "PolicyController",
    "Residual",
    "check_base",
    "policy_action_mode",
    "shipped_policy",
]
