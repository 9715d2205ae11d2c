"""Rendering: one :class:`Renderer` interface, with OpenGL and TinyRenderer behind it.

:func:`renderer_for` gives a simulation's renderer (made on first use, released with the
simulation); the sensors draw through it.
"""

from __future__ import annotations

import functools
import logging

from rover_env.config.cameras import RENDERER_NAMES, RendererName, check_renderer
from rover_env.rendering.base import FisheyeView, Lighting, RenderedView, Renderer, look_at, view_planes
from rover_env.sim.simulation import RoverSim

log = logging.getLogger(__name__)


def resolve_renderer(name: RendererName) -> RendererName:
    """The renderer that ``name`` (``"auto"``, ``"gl"`` or ``"tiny"``) selects on this machine.

    ``"auto"`` is ``"gl"`` where a headless EGL OpenGL context can be created, else ``"tiny"``
    (with one warning per process naming what is missing).

    Raises:
        ValueError: Unknown name.
        rover_env.rendering.gl.GLUnavailableError: ``"gl"`` where it cannot start.
    """
    check_renderer(name)
    if name == "tiny":
        return name
    from rover_env.rendering.gl import GLUnavailableError, usable_here

    ok, why = usable_here()
    if ok:
        return "gl"
    if name == "gl":
        raise GLUnavailableError(f"renderer='gl': {why}; or use renderer='tiny'")
    _warn_fallback(why)
    return "tiny"


@functools.lru_cache(maxsize=1)
def _warn_fallback(why: str) -> None:
    log.warning("OpenGL rendering is not available, so TinyRenderer draws the cameras (slower): %s", why)


def make_renderer(sim: RoverSim) -> Renderer:
    """A new renderer of ``sim``'s scene, of the kind ``sim.renderer`` selects (:func:`resolve_renderer`)."""
    rv = sim.rover
    ruts = rv.ruts if rv.soil is not None else None  # the map exists only with soil
    if resolve_renderer(sim.renderer) == "gl":
        from rover_env.rendering.gl import GLRenderer

        return GLRenderer(
            sim.client,
            sim.terrain,
            link_textures={(rv.body_id, link): path for link, path in rv.link_textures.items()},
            ruts=ruts,
        )
    from rover_env.rendering.tiny import TinyRenderer

    return TinyRenderer(sim.client, sim.terrain, shadow_body=rv.body_id, ruts=ruts)


def renderer_for(sim: RoverSim) -> Renderer:
    """``sim``'s renderer: made at the first call (a GL context then, in the calling process).

    It stays attached to the simulation: it removes what it added to the scene before each
    reset restores the saved state, and :meth:`RoverSim.close` releases it.
    """
    return sim.attachment("renderer", lambda: make_renderer(sim))


def focus_on_rover(sim: RoverSim, ground_range: float | None = None) -> Renderer:
    """``sim``'s renderer, its ground drawn for views from the rover now (see :meth:`Renderer.focus`)."""
    renderer = renderer_for(sim)
    (x, y, _), _ = sim.base_pose()
    renderer.focus(x, y, ground_range)
    return renderer


__all__ = [
    "RENDERER_NAMES",
    "FisheyeView",
    "Lighting",
    "RenderedView",
    "Renderer",
    "RendererName",
    "focus_on_rover",
    "look_at",
    "make_renderer",
    "renderer_for",
    "resolve_renderer",
    "view_planes",
]
