"""The judge: a mission scored on the true state, as named reward terms and termination reasons.

The reward of a control step is the sum of :data:`REWARD_TERMS`, each a weight from
:class:`RewardConfig` times a measure of the true state (``info["reward_terms"]`` holds them
by name). An episode ends at the first reason of :data:`TERMINATIONS` that holds (tipping over
before leaving the terrain before missing the goal before success), and is truncated at the
scenario's duration. The judge reads the truth only; nothing here reaches the observation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rover_env.config.io import check_range
from rover_env.sim.ground_truth import GroundTruth


def wheel_power(gt: GroundTruth) -> float:
    """Mechanical power of the four drive motors, sum of |torque * rate| [W]."""
    return float(np.sum(np.abs(gt.wheel_torque * gt.wheel_rate)))


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the reward terms; every term is reported in ``info["reward_terms"]``.

    Attributes:
        progress: Reward per metre of progress along the course [1/m].
        cross_track: Penalty per metre of |cross-track error| per second [1/(m s)].
        heading: Penalty per radian of |heading error| per second [1/(rad s)].
        slip: Penalty per unit of mean |slip ratio| of the wheels per second [1/s].
        slip_speed: Penalty per m/s of mean wheel slip speed |omega r - v_long| per second
            [1/m]: unlike the ratio, which saturates at 1, it keeps falling as a spinning wheel
            slows toward its ground speed (0: off).
        energy: Penalty per joule of wheel-motor mechanical work [1/J].
        time: Penalty per second [1/s].
        success: Bonus for reaching the last waypoint.
        failure: Penalty for tipping over or leaving the terrain.
    """

    progress: float = 1.0
    cross_track: float = 0.2
    heading: float = 0.05
    slip: float = 0.5
    slip_speed: float = 0.0
    energy: float = 0.002
    time: float = 0.05
    success: float = 10.0
    failure: float = 10.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            check_range(name, getattr(self, name), 0.0, 1e6)


@dataclass(frozen=True)
class StepFacts:
    """What the judge measures in one control step (all from the truth).

    Attributes:
        gt: The true state at the end of the step.
        progress_gain: Progress along the course in this step [m] (true pose, tracker's segment).
        cross_track: True distance from the tracker's current segment [m].
        heading_error: True heading error to that segment [rad].
        wheel_radius: Wheel radius [m].
        dt: Control period [s].
        tipped: The body's z axis is tilted more than 60 deg.
        left_terrain: The true position is within 0.5 m of the terrain's edge or beyond.
        off_target: The tracker has arrived but the true position misses the goal.
        arrived: The tracker has reached the last waypoint.
        stuck: The rover is stuck: in the scenario's last ``stuck_after`` seconds its body moved
            less than :data:`STUCK_DISTANCE` while its treads turned through at least
            :data:`STUCK_TREAD` (wheels spinning or digging in place; off unless the scenario
            sets ``stuck_after``).
    """

    gt: GroundTruth
    progress_gain: float
    cross_track: float
    heading_error: float
    wheel_radius: float
    dt: float
    tipped: bool
    left_terrain: bool
    off_target: bool
    arrived: bool
    stuck: bool = False


#: Less than this much true movement of the body [m] ...
STUCK_DISTANCE = 0.1
#: ... while the treads turned through at least this much [m] (mean of the wheels) is stuck.
STUCK_TREAD = 0.5


@dataclass(frozen=True)
class Termination:
    """A reason an episode ends.

    Attributes:
        name: ``info["termination"]``.
        failure: The mission failed (the ``failure`` term applies), else it succeeded.
        holds: Whether it ends the episode at this step.
        description: One line for the docs.
    """

    name: str
    failure: bool
    holds: Callable[[StepFacts], bool]
    description: str


#: The termination reasons, in the order they are tested: the first that holds names the end.
TERMINATIONS: tuple[Termination, ...] = (
    Termination("tipped_over", True, lambda f: f.tipped, "the body tilted more than 60 deg"),
    Termination("left_terrain", True, lambda f: f.left_terrain, "the rover came within 0.5 m of the edge"),
    Termination(
        "stuck",
        True,
        lambda f: f.stuck,
        "the body moved under 0.1 m while the treads turned 0.5 m or more (scenarios with stuck_after)",
    ),
    Termination("off_target", True, lambda f: f.off_target, "the tracker arrived, the true position missed"),
    Termination("success", False, lambda f: f.arrived, "the tracker arrived and the true position is there"),
)
#: The reason of a truncated episode (the scenario's duration ran out).
TIME_LIMIT = "time_limit"


@dataclass(frozen=True)
class RewardTerm:
    """One named reward term: ``sign * weight * measure(facts, end)`` (times ``dt`` for a rate).

    Attributes:
        name: Its key in ``info["reward_terms"]`` and its weight's field of :class:`RewardConfig`.
        sign: +1 a reward, -1 a penalty.
        measure: The unweighted measure of the step's true state, given the step's end reason.
        per_second: The measure is a rate, integrated over the control period.
    """

    name: str
    sign: float
    measure: Callable[[StepFacts, Termination | None], float]
    per_second: bool = True


def _slip_speed(f: StepFacts, end: Termination | None = None) -> float:
    """Mean over the wheels of |omega r - v_long| [m/s]."""
    return float(np.mean(np.abs(f.gt.wheel_rate * f.wheel_radius - f.gt.wheel_v_long)))


#: The reward terms, in ``info["reward_terms"]``'s order.
REWARD_TERMS: tuple[RewardTerm, ...] = (
    RewardTerm("progress", 1.0, lambda f, end: f.progress_gain, per_second=False),  # [m]
    RewardTerm("cross_track", -1.0, lambda f, end: abs(f.cross_track)),  # [m]
    RewardTerm("heading", -1.0, lambda f, end: abs(f.heading_error)),  # [rad]
    RewardTerm("slip", -1.0, lambda f, end: float(np.mean(np.abs(f.gt.slip_ratio)))),  # mean |ratio|
    RewardTerm("slip_speed", -1.0, _slip_speed),  # [m/s]
    RewardTerm("energy", -1.0, lambda f, end: wheel_power(f.gt)),  # [W]
    RewardTerm("time", -1.0, lambda f, end: 1.0),
    RewardTerm("success", 1.0, lambda f, end: float(end is not None and not end.failure), per_second=False),
    RewardTerm("failure", -1.0, lambda f, end: float(end is not None and end.failure), per_second=False),
)
REWARD_TERM_NAMES: tuple[str, ...] = tuple(t.name for t in REWARD_TERMS)
if REWARD_TERM_NAMES != tuple(RewardConfig.__dataclass_fields__):
    raise AssertionError("every reward term has one weight in RewardConfig, in the same order")


@dataclass(frozen=True)
class Verdict:
    """The judge's score of one control step.

    Attributes:
        terms: Each reward term by name (weighted, signed).
        reward: Their sum.
        end: The termination reason that holds, or None.
        truncated: The duration ran out (and no reason holds).
    """

    terms: dict[str, float]
    reward: float
    end: Termination | None
    truncated: bool

    @property
    def terminated(self) -> bool:
        """The episode ended for a reason of :data:`TERMINATIONS`."""
        return self.end is not None

    @property
    def success(self) -> bool:
        """The episode ended in success."""
        return self.end is not None and not self.end.failure

    @property
    def reason(self) -> str | None:
        """``info["termination"]``: the reason's name, ``"time_limit"``, or None."""
        return self.end.name if self.end is not None else (TIME_LIMIT if self.truncated else None)


class Judge:
    """Scores control steps on the truth with ``weights``.

    Args:
        weights: The reward terms' weights.
        duration: The episode's time limit [s].
    """

    def __init__(self, weights: RewardConfig, duration: float) -> None:
        self.weights = weights
        self.duration = float(duration)

    def end(self, facts: StepFacts) -> Termination | None:
        """The first reason of :data:`TERMINATIONS` that holds, or None."""
        return next((r for r in TERMINATIONS if r.holds(facts)), None)

    def __call__(self, facts: StepFacts) -> Verdict:
        """The verdict on one step."""
        return self.score(facts, self.end(facts))

    def score(self, facts: StepFacts, end: Termination | None) -> Verdict:
        """The verdict on one step that ``end`` (:meth:`end` of the same step) ended or not.

        A term whose measure is zero is +0.0.
        """
        terms = {}
        for t in REWARD_TERMS:
            m = t.measure(facts, end)
            value = t.sign * getattr(self.weights, t.name) * m if m != 0.0 else 0.0
            terms[t.name] = value * facts.dt if t.per_second else value
        truncated = end is None and facts.gt.t >= self.duration - 1e-9
        return Verdict(terms, float(sum(terms.values())), end, truncated)

    @staticmethod
    def zero_terms() -> dict[str, float]:
        """Every term at 0 (the reset's ``info["reward_terms"]``)."""
        return dict.fromkeys(REWARD_TERM_NAMES, 0.0)
