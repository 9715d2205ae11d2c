"""The ground-texture presets a scenario may name (made by :mod:`rover_env.sim.textures`)."""

from __future__ import annotations

#: Procedural ground textures, by name.
TEXTURE_PRESETS: tuple[str, ...] = ("regolith", "sand", "gravel", "concrete", "checkerboard")
