"""Reinforcement learning with stable-baselines3: residual policies on the estimator, and their loader.

The learned policy is residual (Johannink et al. 2019, "Residual reinforcement learning for robot
control"): its action is added to the path follower's drive command (speed, lambda_F,
lambda_R), scaled by ``scale`` per component, and the sum is clipped to [-1, 1]. By default
the slip-aware traction controller (:class:`~controllers.SlipAwareController`) then turns
that command into per-wheel speeds within its slip bounds: the policy learns speed and
steering, the classical layer keeps the wheels from digging in (base ``"traction"``,
``wheels`` action mode). Base ``"follower"`` sends the command to the environment as it is
(``drive`` mode). At the start of training the rover already follows the course, so the
policy learns only what its base lacks, from far fewer steps than driving from scratch.
:class:`ResidualDrive` is that wrapper; :func:`train` runs PPO (default) or SAC on vectorised
estimated-observation environments with observation normalisation, checkpoints, periodic
evaluation and TensorBoard logs (with slip metrics); :class:`PolicyController` turns a saved
run into a :class:`~controllers.Controller`.

Needs the ``rl`` extra: ``pip install 'rover-vision[rl]'``.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from controllers.path_follower import PathFollower
from controllers.traction import SlipAwareController
from perception.slip import SLIP_EVENT

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


def _check_base(base: str) -> None:
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
        mode = env.unwrapped.action_mode.value
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


class ResidualDrive(gym.Wrapper):
    """Actions as residuals on a base controller's drive command (:class:`Residual`).

    The base follows from the wrapped environment's action mode: ``wheels`` (traction control)
    or ``drive`` (the path follower alone). The action space is Box(-1, 1, (3,)): residuals on
    (speed, lambda_F, lambda_R).

    Args:
        env: The environment.
        scale: Residual range per component (speed, lambda_F, lambda_R), in action units.
    """

    def __init__(self, env: gym.Env, scale: Sequence[float] = (0.5, 0.3, 0.3)) -> None:
        super().__init__(env)
        self.residual = Residual.for_env(env, scale)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self._obs: np.ndarray | None = None

    def reset(self, **kwargs):
        """Reset the environment and the base controller."""
        obs, info = self.env.reset(**kwargs)
        self.residual.reset()
        self._obs = obs
        return obs, info

    def step(self, action):
        """Step with the base controller's action for the residual ``action``."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        obs, reward, term, trunc, info = self.env.step(self.residual.compose(self._obs, action))
        self._obs = obs
        return obs, reward, term, trunc, info


class EpisodeStats(gym.Wrapper):
    """Adds ``info["episode_stats"]`` at an episode's end: success, time in slip, mean |slip|, energy.

    Slip is the simulator's (``info["ground_truth"]``), whatever the observation source.
    """

    SLIP = SLIP_EVENT  # |slip ratio| above which a wheel slips

    def reset(self, **kwargs):
        """Reset the environment and the counters."""
        self._n, self._slipping, self._abs_slip, self._energy = 0, 0, 0.0, 0.0
        return self.env.reset(**kwargs)

    def step(self, action):
        """Step and count."""
        obs, reward, term, trunc, info = self.env.step(action)
        s = np.abs(info["ground_truth"]["slip_ratio"])
        self._n += 1
        self._slipping += int(s.max() > self.SLIP)
        self._abs_slip += float(s.mean())
        self._energy += info["wheel_power"] * self.env.unwrapped.control_dt
        if term or trunc:
            dt = self.env.unwrapped.control_dt
            info["episode_stats"] = {
                "success": float(info["is_success"]),
                "time_in_slip": self._slipping * dt,
                "mean_abs_slip": self._abs_slip / max(self._n, 1),
                "energy": self._energy,
                "progress": float(info["progress"]),
            }
        return obs, reward, term, trunc, info


class MissionCycle(gym.Env):
    """Several environments behind one: each reset moves on to the next (same spaces).

    Lets one training process see every mission in turn. Each environment is made on its first
    use; ``close`` closes them all.

    Args:
        makers: Functions that make the environments, in the order they are used.
    """

    def __init__(self, makers: Sequence) -> None:
        if not makers:
            raise ValueError("MissionCycle needs at least one environment")
        self._makers = list(makers)
        self._envs: list[gym.Env | None] = [None] * len(self._makers)
        self._k = -1
        first = self._env(0)
        self.observation_space, self.action_space = first.observation_space, first.action_space
        self.metadata = first.metadata

    def _env(self, k: int) -> gym.Env:
        if self._envs[k] is None:
            self._envs[k] = self._makers[k]()
        return self._envs[k]

    @property
    def current(self) -> gym.Env:
        """The environment of the running episode."""
        return self._env(max(self._k, 0))

    def reset(self, *, seed=None, options=None):
        """Reset the next environment in the cycle."""
        super().reset(seed=seed)
        self._k = (self._k + 1) % len(self._makers)
        return self.current.reset(seed=seed, options=options)

    def step(self, action):
        """Step the current environment."""
        return self.current.step(action)

    def close(self) -> None:
        """Close every environment made."""
        for env in self._envs:
            if env is not None:
                env.close()


def make_env(
    missions: str | Sequence[str],
    obs_source: str = "estimated",
    preset: str = "train",
    residual: Sequence[float] | None = (0.5, 0.3, 0.3),
    seed: int | None = None,
    reward: dict | None = None,
    base: str = "traction",
) -> gym.Env:
    """A training or evaluation environment: Monitor(EpisodeStats(ResidualDrive(env))).

    Args:
        missions: Registered environment id (or scenario name or YAML path), or several: then
            one episode of each in turn (:class:`MissionCycle`).
        obs_source: ``"estimated"`` or ``"ground_truth"``.
        preset: Camera preset.
        residual: Residual scale (None: the policy's action is the action).
        seed: Seed of the action space (episodes are seeded by ``reset``).
        reward: Weights of the reward terms that differ from :class:`~rover_env.task.course.RewardConfig`'s.
        base: The residual's base, a key of :data:`BASES` (sets the action mode).
    """
    _check_base(base)
    from stable_baselines3.common.monitor import Monitor

    from rover_env.task.course import RewardConfig
    from rover_env.tools.evaluation import make_mission_env

    weights = RewardConfig(**(reward or {}))

    def one(mission: str):
        def make():
            env = make_mission_env(
                mission, obs_source=obs_source, preset=preset, action_mode=BASES[base], reward=weights
            )
            if residual is not None:
                env = ResidualDrive(env, residual)
            return EpisodeStats(env)

        return make

    names = [missions] if isinstance(missions, str) else list(missions)
    env = one(names[0])() if len(names) == 1 else MissionCycle([one(m) for m in names])
    env = Monitor(env, info_keywords=())
    if seed is not None:
        env.action_space.seed(seed)
    return env


@dataclass
class TrainConfig:
    """A training run (everything :func:`train` needs; saved next to the policy).

    Attributes:
        algo: ``"ppo"`` or ``"sac"``.
        missions: Environment ids; every environment process runs one episode of each in turn.
        total_steps: Environment steps over all environments.
        n_envs: Environments, each in its own process.
        obs_source: ``"estimated"`` (default) or ``"ground_truth"``.
        preset: Camera preset.
        residual: Residual scale on the drive command (None: learn the whole action).
        base: What the residual is added to: ``"traction"`` (the slip-aware traction
            controller, wheels action mode) or ``"follower"`` (the path follower, drive mode).
        seed: Random seed.
        eval_every: Evaluate every this many steps (over all environments).
        eval_episodes: Episodes per evaluation.
        checkpoint_every: Save a checkpoint every this many steps.
        hyper: Algorithm keyword arguments (override the defaults).
        reward: Reward weights that differ from the environment's (:class:`~rover_env.task.course.RewardConfig`).
    """

    algo: str = "ppo"
    missions: tuple[str, ...] = ("Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0", "RoverSlopeLoose-v0")
    total_steps: int = 200_000
    n_envs: int = 2
    obs_source: str = "estimated"
    preset: str = "train"
    residual: tuple[float, float, float] | None = (0.5, 0.3, 0.3)
    base: str = "traction"
    seed: int = 0
    eval_every: int = 20_000
    eval_episodes: int = 4
    checkpoint_every: int = 20_000
    hyper: dict = field(default_factory=dict)
    reward: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.algo not in ("ppo", "sac"):
            raise ValueError(f"algo {self.algo!r}: use 'ppo' or 'sac'")
        if self.total_steps < 1 or self.n_envs < 1:
            raise ValueError("total_steps and n_envs must be at least 1")
        _check_base(self.base)


PPO_DEFAULTS = dict(
    n_steps=512, batch_size=256, n_epochs=5, learning_rate=3e-4, gamma=0.99, gae_lambda=0.95,
    clip_range=0.2, ent_coef=0.0, policy_kwargs=dict(net_arch=[64, 64], log_std_init=-1.0),
)  # fmt: skip
SAC_DEFAULTS = dict(
    learning_rate=3e-4, buffer_size=200_000, batch_size=256, gamma=0.99, train_freq=1, learning_starts=2_000,
    policy_kwargs=dict(net_arch=[64, 64]),
)  # fmt: skip


def save_policy(model, cfg: TrainConfig, out: str | Path) -> Path:
    """Write a policy folder that :class:`PolicyController` loads.

    It holds the model, its observation statistics and ``policy.json`` (the training
    configuration, the observation fields and the steps trained).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / POLICY_FILE)
    save_obs_stats(model.get_vec_normalize_env(), out / STATS_FILE)
    space = model.action_space
    meta = asdict(cfg) | {
        "action_mode": BASES[cfg.base],
        "obs_fields": _obs_fields(),
        "steps": int(model.num_timesteps),
        "obs_dim": int(np.prod(model.observation_space.shape)),
        "action_low": np.asarray(space.low, dtype=float).tolist(),
        "action_high": np.asarray(space.high, dtype=float).tolist(),
    }
    (out / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")
    return out


def _save_callback(cfg: TrainConfig, out: Path):
    from stable_baselines3.common.callbacks import BaseCallback

    class SaveBest(BaseCallback):
        """Saves the policy folder when the evaluation finds a new best."""

        def _on_step(self) -> bool:
            save_policy(self.model, cfg, out)
            return True

    return SaveBest()


def _slip_callback():
    from stable_baselines3.common.callbacks import BaseCallback

    class SlipMetrics(BaseCallback):
        """Logs each finished episode's success, time in slip, mean |slip|, energy and progress."""

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                stats = info.get("episode_stats")
                if stats:
                    for k, v in stats.items():
                        self.logger.record_mean(f"episode/{k}", v)
            return True

    return SlipMetrics()


def _progress_callback(total: int):
    import sys
    import time

    from stable_baselines3.common.callbacks import BaseCallback

    class Progress(BaseCallback):
        """A one-line progress display on stderr."""

        def _on_training_start(self) -> None:
            self._start, self._last, self._success = time.perf_counter(), 0.0, []

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                if "episode_stats" in info:
                    self._success = (self._success + [info["episode_stats"]["success"]])[-20:]
            now = time.perf_counter()
            if now - self._last >= 2.0:
                self._last = now
                n = min(int(30 * self.num_timesteps / total), 30)
                rate = self.num_timesteps / max(now - self._start, 1e-9)
                ok = f"{100 * np.mean(self._success):.0f} %" if self._success else "-"
                sys.stderr.write(
                    f"\rtrain [{'#' * n}{'.' * (30 - n)}] {self.num_timesteps}/{total} steps, "
                    f"{rate:.0f} steps/s, success (last 20 episodes) {ok}   "
                )
                sys.stderr.flush()
            return True

        def _on_training_end(self) -> None:
            rate = self.num_timesteps / max(time.perf_counter() - self._start, 1e-9)
            sys.stderr.write(f"\rtrain [{'#' * 30}] {self.num_timesteps} steps, {rate:.0f} steps/s\n")

    return Progress()


def train(cfg: TrainConfig, out: str | Path, progress: bool = False) -> Path:
    """Train a policy; write ``policy.zip``, ``vecnormalize.pkl``, ``policy.json``, checkpoints and logs.

    Observations, and in training the rewards, are normalised by running statistics
    (``VecNormalize``); the observation statistics are saved with the policy. TensorBoard logs go to
    ``out/tb``, checkpoints to ``out/checkpoints``, the best evaluated policy (a folder like ``out``
    itself) to ``out/best``.

    Args:
        cfg: The run.
        out: Output folder.
        progress: Show progress on stderr (steps, rate, recent success rate).

    Returns:
        ``out``.
    """
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback, EvalCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    missions = list(cfg.missions)

    def factory(names, seed: int):
        return lambda: make_env(names, cfg.obs_source, cfg.preset, cfg.residual, seed, cfg.reward, cfg.base)

    # every process cycles through all missions, each from its own starting point
    fns = [
        factory(missions[i % len(missions) :] + missions[: i % len(missions)], cfg.seed + i)
        for i in range(cfg.n_envs)
    ]
    venv = SubprocVecEnv(fns, start_method="spawn") if cfg.n_envs > 1 else DummyVecEnv(fns)
    venv.seed(cfg.seed)
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, clip_obs=10.0)
    # evaluated on the last mission (the hardest of the defaults), with the training statistics
    eval_env = VecNormalize(
        DummyVecEnv([factory(missions[-1], cfg.seed + 1000)]),
        norm_obs=True,
        norm_reward=False,
        training=False,
    )
    algo = {"ppo": (PPO, PPO_DEFAULTS), "sac": (SAC, SAC_DEFAULTS)}[cfg.algo]
    kwargs = {**algo[1], **cfg.hyper}
    model = algo[0]("MlpPolicy", venv, seed=cfg.seed, tensorboard_log=str(out / "tb"), verbose=0, **kwargs)
    per_env = max(1, cfg.n_envs)
    callbacks = CallbackList(
        [_progress_callback(cfg.total_steps)] * progress
        + [
            _slip_callback(),
            CheckpointCallback(
                max(cfg.checkpoint_every // per_env, 1), str(out / "checkpoints"), save_vecnormalize=True
            ),
            EvalCallback(
                eval_env,
                n_eval_episodes=cfg.eval_episodes,
                eval_freq=max(cfg.eval_every // per_env, 1),
                callback_on_new_best=_save_callback(cfg, out / "best"),
                deterministic=True,
                verbose=0,
            ),
        ]
    )
    try:
        model.learn(total_timesteps=cfg.total_steps, callback=callbacks, tb_log_name=cfg.algo)
        save_policy(model, cfg, out)
    finally:
        venv.close()
        eval_env.close()
    return out


def _obs_fields() -> list[str]:
    from perception.observation import OBS_FIELDS

    return list(OBS_FIELDS)


def save_obs_stats(vec_normalize, path: str | Path) -> Path:
    """Write a VecNormalize's observation statistics to ``path`` (.npz, plain arrays, no pickle)."""
    rms = vec_normalize.obs_rms
    np.savez(
        path,
        mean=np.asarray(rms.mean, dtype=np.float64),
        var=np.asarray(rms.var, dtype=np.float64),
        count=np.float64(rms.count),
        clip_obs=np.float64(vec_normalize.clip_obs),
        epsilon=np.float64(vec_normalize.epsilon),
    )
    return Path(path)


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
        ok = ok and np.all(np.isfinite(self.mean)) and np.all(np.isfinite(self.var)) and np.all(self.var >= 0)
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
        if env.unwrapped.action_mode.value != self.meta["action_mode"]:
            raise ValueError(f"the policy acts in action_mode={self.meta['action_mode']!r}; make the env so")
        # the policy's inputs by name: a policy trained before fields were added still reads its own
        names = [f.name for f in env.unwrapped.obs_fields]
        trained = list(self.meta["obs_fields"])
        missing = [n for n in trained if n not in names]
        if missing:
            raise ValueError(
                f"{path}: the policy was trained on observation fields {missing} that this "
                "environment does not have; retrain it (rover train)"
            )
        n_state = len(_obs_fields())  # the previous action follows the state fields
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
    "EpisodeStats",
    "MissionCycle",
    "PolicyController",
    "Residual",
    "ResidualDrive",
    "TrainConfig",
    "make_env",
    "policy_action_mode",
    "shipped_policy",
    "train",
]
