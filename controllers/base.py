"""The controller protocol: anything with ``reset()`` and ``act(obs) -> action``."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Controller(Protocol):
    """Maps an environment observation to an action in [-1, 1]."""

    def reset(self) -> None:
        """Forget internal state at the start of an episode."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Action (float32, in [-1, 1]) for observation ``obs``."""
