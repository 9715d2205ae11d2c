"""Configuration: scenarios, cameras, the IMU and the renderer choice, read and checked.

The lowest layer of ``rover_env``: plain, frozen dataclasses and YAML with one error type
(:class:`ConfigError`); it imports nothing else of the package.
"""
