"""The simulation core: one PyBullet client with the terrain and the rover, and the exact ground truth.

Every other layer reaches PyBullet through :class:`rover_env.sim.simulation.RoverSim`'s methods.
"""
