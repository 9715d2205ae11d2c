"""Compiling the few numerical kernels that run per frame or per physics substep."""

from __future__ import annotations


def compiled(f):
    """``f`` compiled by numba (cached on disk); without numba the same code runs as Python.

    numba's on-disk cache follows a function's own file only: a kernel that calls another
    belongs in that one's file.
    """
    try:
        from numba import njit
    except ImportError:  # pragma: no cover
        return f
    return njit(cache=True)(f)
