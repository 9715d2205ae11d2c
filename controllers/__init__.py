"""Controllers that drive the rover from observations (never from the simulator)."""
