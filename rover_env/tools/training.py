"""Training residual policies with stable-baselines3 on the estimated-observation environments.

:class:`ResidualDrive` makes the policy's action a residual on a base controller's drive command
(:class:`controllers.rl.Residual`); :func:`train` runs PPO (default) or SAC on vectorised
environments with observation normalisation, checkpoints, periodic evaluation and TensorBoard
logs (with slip metrics), and writes a policy folder that :class:`controllers.rl.PolicyController`
loads.

Needs the ``rl`` extra: ``pip install 'rover-vision[rl]'``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from controllers.rl import (
    BASES,
    META_FILE,
    POLICY_FILE,
    STATS_FILE,
    Residual,
    check_base,
    observation_fields,
)
from perception.fusion.slip import SLIP_EVENT
from perception.logs.outputs import OutputFolder
from rover_env.config.rig import PresetName
from rover_env.envs.rover_env import ObsSourceName
from rover_env.task.judge import RewardConfig

log = logging.getLogger(__name__)


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


def _mission_id(env: gym.Env) -> str:
    """The registered id (else the scenario's name) of the running episode's environment."""
    inner = env.current if isinstance(env, MissionCycle) else env
    base = inner.unwrapped
    spec = getattr(base, "spec", None)
    if spec is not None:
        return spec.id
    scenario = getattr(base, "scenario", None)
    return scenario.name if scenario is not None else type(base).__name__


class EpisodeSeeds(gym.Wrapper):
    """Seeds every episode from a fixed sequence: ``first``, ``first + stride``, ...

    A training run's episodes then have known seeds, so its worlds (with randomisation, drawn
    from the seed) can be driven again (``rover eval --seeds``). An explicit ``reset(seed=...)``
    is overridden. At an episode's end, ``info["episode_seed"]`` holds the mission's id and the
    seed.

    Args:
        env: The environment (or a :class:`MissionCycle`).
        first: The first episode's seed.
        stride: Between consecutive episodes' seeds (the number of processes, so that theirs
            interleave and never meet).
    """

    def __init__(self, env: gym.Env, first: int, stride: int = 1) -> None:
        super().__init__(env)
        if first < 0 or stride < 1:
            raise ValueError(f"EpisodeSeeds: first={first!r} must be >= 0 and stride={stride!r} >= 1")
        self.first, self.stride = int(first), int(stride)
        self.episodes = 0  # episodes reset so far
        self._current: dict | None = None

    def reset(self, *, seed=None, options=None):
        """Reset with the next seed of the sequence (``seed`` is ignored)."""
        s = self.first + self.stride * self.episodes
        self.episodes += 1
        obs, info = self.env.reset(seed=s, options=options)
        self._current = {"mission": _mission_id(self.env), "seed": s}
        return obs, info

    def step(self, action):
        """Step; at the episode's end add ``info["episode_seed"]``."""
        obs, reward, term, trunc, info = self.env.step(action)
        if (term or trunc) and self._current is not None:
            info["episode_seed"] = dict(self._current)
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
        env = self._envs[k]
        if env is None:
            env = self._envs[k] = self._makers[k]()
        return env

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
    obs_source: ObsSourceName = "estimated",
    preset: PresetName = "train",
    residual: Sequence[float] | None = (0.5, 0.3, 0.3),
    seed: int | None = None,
    reward: dict | None = None,
    base: str = "traction",
    camera_effects: str = "field",
    randomize: str | None = None,
    episode_seeds: tuple[int, int] | None = None,
    imu: str | None = None,
) -> gym.Env:
    """A training or evaluation environment: Monitor(EpisodeStats(ResidualDrive(env))).

    Args:
        missions: Registered environment id (or scenario name or YAML path), or several: then
            one episode of each in turn (:class:`MissionCycle`).
        obs_source: ``"estimated"`` or ``"ground_truth"``.
        preset: Camera preset.
        residual: Residual scale (None: the policy's action is the action).
        seed: Seed of the action space (episodes are seeded by ``reset``).
        reward: Weights of the reward terms that differ from :class:`~rover_env.task.judge.RewardConfig`'s.
        base: The residual's base, a key of :data:`BASES` (sets the action mode).
        camera_effects: The cameras with estimated observations (``"ideal"`` or ``"field"``).
        randomize: Domain randomisation (``"off"``, ``"on"`` or None: the scenario's).
        episode_seeds: (first, stride): seed the episodes first, first + stride, ...
            (:class:`EpisodeSeeds`); None: as ``reset`` is called.
        imu: An IMU preset on the rover (``rover_env.config.imu.IMU_PRESETS``; None: none).
    """
    check_base(base)
    from stable_baselines3.common.monitor import Monitor

    from rover_env.tools.evaluation import make_mission_env

    weights = RewardConfig(**(reward or {}))

    def one(mission: str):
        def make():
            env = make_mission_env(
                mission,
                obs_source=obs_source,
                preset=preset,
                action_mode=BASES[base],
                reward=weights,
                camera_effects=camera_effects,
                randomize=randomize,
                **({"imu": imu} if imu else {}),
            )
            if residual is not None:
                env = ResidualDrive(env, residual)
            return EpisodeStats(env)

        return make

    names = [missions] if isinstance(missions, str) else list(missions)
    env = one(names[0])() if len(names) == 1 else MissionCycle([one(m) for m in names])
    if episode_seeds is not None:
        env = EpisodeSeeds(env, *episode_seeds)
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
        reward: Reward weights that differ from the environment's
            (:class:`~rover_env.task.judge.RewardConfig`).
        camera_effects: The cameras (``"ideal"`` or ``"field"``).
        episode_seeds: Episode k (0, 1, ...) of environment process i is seeded
            ``episode_seeds + k * n_envs + i`` (:class:`EpisodeSeeds`): a run's worlds are known
            (``episodes.csv`` lists them) and lie apart from the comparison's seeds (0-999) and
            the evaluation's (``seed + 1000`` on).
        randomize: Domain randomisation of each episode's world (``"off"``, ``"on"`` or None:
            each scenario's ``randomize`` key).
        imu: An IMU preset on the rover (None: none); evaluate the policy with the same one
            (``rover eval --controllers policy:FOLDER@imu:PRESET``).
    """

    algo: str = "ppo"
    missions: tuple[str, ...] = ("Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0", "RoverSlopeLoose-v0")
    total_steps: int = 200_000
    n_envs: int = 2
    obs_source: ObsSourceName = "estimated"
    preset: PresetName = "train"
    residual: tuple[float, float, float] | None = (0.5, 0.3, 0.3)
    base: str = "traction"
    seed: int = 0
    eval_every: int = 20_000
    eval_episodes: int = 4
    checkpoint_every: int = 20_000
    hyper: dict = field(default_factory=dict)
    reward: dict = field(default_factory=dict)
    camera_effects: str = "field"
    randomize: str | None = None
    episode_seeds: int = 10_000
    imu: str | None = None

    def __post_init__(self) -> None:
        import math

        if self.episode_seeds < 0:
            raise ValueError(f"episode_seeds {self.episode_seeds!r} must be >= 0")
        if self.algo not in ("ppo", "sac"):
            raise ValueError(f"algo {self.algo!r}: use 'ppo' or 'sac'")
        if self.total_steps < 1 or self.n_envs < 1:
            raise ValueError("total_steps and n_envs must be at least 1")
        if not self.missions:
            raise ValueError("missions: give at least one environment id or scenario")
        check_base(self.base)
        if self.residual is not None:
            r = tuple(self.residual)
            numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in r)
            ok = len(r) == 3 and numbers and all(math.isfinite(v) and 0.0 <= v <= 2.0 for v in r)
            if not ok:
                raise ValueError(
                    f"residual {list(r)!r}: give three numbers from 0 to 2 (action units: the residual's "
                    "range on speed, lambda_F, lambda_R)"
                )
        if self.obs_source not in ("estimated", "ground_truth"):
            raise ValueError(f"obs_source {self.obs_source!r}: use 'estimated' or 'ground_truth'")
        if self.camera_effects not in ("ideal", "field"):
            raise ValueError(f"camera_effects {self.camera_effects!r}: use 'ideal' or 'field'")
        if self.randomize not in (None, "off", "on"):
            raise ValueError(f"randomize {self.randomize!r}: use 'off', 'on' or None (the scenario's)")
        if self.imu is not None:
            from rover_env.config.imu import IMU_PRESETS

            if self.imu not in IMU_PRESETS:
                raise ValueError(f"imu {self.imu!r}: use one of {sorted(IMU_PRESETS)} or None (no IMU)")
            if self.obs_source != "estimated":
                raise ValueError(
                    f"imu {self.imu!r}: the IMU feeds the estimator; train with obs_source 'estimated', or "
                    "leave the IMU out"
                )

    def rollout(self) -> int:
        """Environment steps between two updates of the policy (PPO: n_steps x environments)."""
        hyper = {**(PPO_DEFAULTS if self.algo == "ppo" else SAC_DEFAULTS), **self.hyper}
        if self.algo == "ppo":
            return int(hyper["n_steps"]) * self.n_envs
        return int(hyper["learning_starts"])

    def steps_trained(self) -> int:
        """The steps :func:`train` runs: ``total_steps``, or one rollout if that is more (PPO)."""
        if self.algo == "ppo":
            r = self.rollout()
            return -(-self.total_steps // r) * r
        return self.total_steps

    def check(self) -> None:
        """Check every mission and the environment each makes, in this process, before any worker starts.

        Raises:
            ValueError: A mission that is neither an environment id nor a scenario, or an
                environment that refuses this configuration (the message names the mission).
        """
        import rover_env
        from rover_env.config.scenario import load_scenario

        for m in self.missions:
            if m not in rover_env.ENV_IDS:
                try:
                    load_scenario(m)
                except (ValueError, OSError) as exc:
                    raise ValueError(
                        f"mission {m!r}: not an environment id ({', '.join(rover_env.ENV_IDS)}), scenario "
                        f"preset or readable scenario file ({exc})"
                    ) from None
        RewardConfig(**self.reward)
        for m in self.missions:
            try:
                make_env(
                    m, self.obs_source, self.preset, self.residual, None, self.reward, self.base,
                    self.camera_effects, self.randomize, None, self.imu,
                ).close()  # fmt: skip
            except (ValueError, TypeError) as exc:
                raise ValueError(f"mission {m!r}: {exc}") from None


PPO_DEFAULTS = dict(
    n_steps=512, batch_size=256, n_epochs=5, learning_rate=3e-4, gamma=0.99, gae_lambda=0.95,
    clip_range=0.2, ent_coef=0.0, policy_kwargs=dict(net_arch=[64, 64], log_std_init=-1.0),
)  # fmt: skip
SAC_DEFAULTS = dict(
    learning_rate=3e-4, buffer_size=200_000, batch_size=256, gamma=0.99, train_freq=1, learning_starts=2_000,
    policy_kwargs=dict(net_arch=[64, 64]),
)  # fmt: skip


#: The files of a policy folder.
POLICY_FILES = (POLICY_FILE, META_FILE, STATS_FILE)
#: What :func:`train` writes into its folder.
TRAIN_PRODUCTS = (*POLICY_FILES, "episodes.csv", "checkpoints/", "tb/", "best/")


def save_policy(model, cfg: TrainConfig, out: str | Path | OutputFolder) -> Path:
    """Write a policy folder that :class:`PolicyController` loads.

    It holds the model, its observation statistics and ``policy.json`` (the training
    configuration, the observation fields and the steps trained). ``out``: an
    :class:`OutputFolder` whose products include :data:`POLICY_FILES` (staged; the caller
    commits), or a folder path (written and committed here, replacing an earlier policy).
    """
    if not isinstance(out, OutputFolder):
        with OutputFolder(out, POLICY_FILES, overwrite=True, announce=False) as folder:
            save_policy(model, cfg, folder)
            folder.commit()
        return Path(out)
    with out.writing(POLICY_FILE) as tmp:
        model.save(tmp)
    with out.writing(STATS_FILE) as tmp:
        save_obs_stats(model.get_vec_normalize_env(), tmp)
    space = model.action_space
    meta = asdict(cfg) | {
        "action_mode": BASES[cfg.base],
        "obs_fields": observation_fields(),
        "steps": int(model.num_timesteps),
        "obs_dim": int(np.prod(model.observation_space.shape)),
        "action_low": np.asarray(space.low, dtype=float).tolist(),
        "action_high": np.asarray(space.high, dtype=float).tolist(),
    }
    out.write_text(META_FILE, json.dumps(meta, indent=2) + "\n")
    return out.path


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


#: The episodes of a training run: one row per finished episode (mission, seed, success, ...).
EPISODES_FILE = "episodes.csv"


def _episodes_callback(path: Path):
    from stable_baselines3.common.callbacks import BaseCallback

    class EpisodeLog(BaseCallback):
        """Writes each finished episode's mission, seed and statistics to ``path`` (CSV)."""

        def _on_training_start(self) -> None:
            self._file = path.open("w", encoding="utf-8")
            self._file.write("step,mission,seed,success,time_in_slip,mean_abs_slip,energy,progress\n")

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                world, stats = info.get("episode_seed"), info.get("episode_stats")
                if world and stats:
                    self._file.write(
                        f"{self.num_timesteps},{world['mission']},{world['seed']},{int(stats['success'])},"
                        f"{stats['time_in_slip']:.4g},{stats['mean_abs_slip']:.4g},{stats['energy']:.4g},"
                        f"{stats['progress']:.4g}\n"
                    )
                    self._file.flush()
            return True

        def _on_training_end(self) -> None:
            self._file.close()

    return EpisodeLog()


def _progress_callback(total: int):
    import sys
    import time

    from stable_baselines3.common.callbacks import BaseCallback

    class Progress(BaseCallback):
        """A one-line progress display on stderr."""

        def _on_training_start(self) -> None:
            self._start, self._last = time.perf_counter(), 0.0
            self._success: list[float] = []

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


def train(cfg: TrainConfig, out: str | Path | OutputFolder, progress: bool = False) -> Path:
    """Train a policy; write ``policy.zip``, ``obs_stats.npz``, ``policy.json``, checkpoints and logs.

    Observations, and in training the rewards, are normalised by running statistics
    (``VecNormalize``); the observation statistics are saved with the policy. TensorBoard logs go to
    ``out/tb``, checkpoints to ``out/checkpoints`` (as they are made: they survive an
    interruption), the best evaluated policy (a folder like ``out`` itself) to ``out/best``; the
    policy and ``episodes.csv`` are committed when training ends, or when it is interrupted
    (Ctrl-C: the policy so far, its ``policy.json`` counting the steps it had).

    Args:
        cfg: The run.
        out: An :class:`OutputFolder` with the products :data:`TRAIN_PRODUCTS` (committed here
            when training ends), or a folder path (an earlier run's results there are replaced).
        progress: Show progress on stderr (steps, rate, recent success rate).

    Returns:
        The folder's path.
    """
    if not isinstance(out, OutputFolder):
        with OutputFolder(out, TRAIN_PRODUCTS, overwrite=True) as folder:
            return train(cfg, folder, progress)
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback, EvalCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    folder = out
    for sub in ("checkpoints/", "tb/", "best/"):
        folder.subfolder(sub)
    episodes = folder.stage(EPISODES_FILE)
    out = folder.path
    missions = list(cfg.missions)

    def factory(names, seed: int, episode_seeds=None):
        return lambda: make_env(
            names,
            cfg.obs_source,
            cfg.preset,
            cfg.residual,
            seed,
            cfg.reward,
            cfg.base,
            cfg.camera_effects,
            cfg.randomize,
            episode_seeds,
            cfg.imu,
        )

    # every process cycles through all missions, each from its own starting point
    fns = [
        factory(
            missions[i % len(missions) :] + missions[: i % len(missions)],
            cfg.seed + i,
            (cfg.episode_seeds + i, cfg.n_envs),
        )
        for i in range(cfg.n_envs)
    ]
    raw = SubprocVecEnv(fns, start_method="spawn") if cfg.n_envs > 1 else DummyVecEnv(fns)
    raw.seed(cfg.seed)
    venv = VecNormalize(raw, norm_obs=True, norm_reward=True, clip_obs=10.0)
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
            _episodes_callback(episodes),
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
        save_policy(model, cfg, folder)
    except KeyboardInterrupt:  # Ctrl-C: keep the policy so far (policy.json says its steps)
        log.warning(
            "interrupted after %d steps: the policy so far and episodes.csv are saved", model.num_timesteps
        )
        save_policy(model, cfg, folder)
        folder.commit()
        raise
    finally:
        venv.close()
        eval_env.close()
    folder.commit()
    return out


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
