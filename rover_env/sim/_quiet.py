"""Keep PyBullet's C-level chatter ("pybullet build time: ...", "argv[0]=") off the terminal."""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys


@contextlib.contextmanager
def quiet_c_output():
    """Send what C code writes to stdout and stderr inside the block to /dev/null.

    Python exceptions are unaffected (they are printed after the block). Streams that are not
    file descriptors (pytest's capture, a notebook) are left alone.
    """
    fds = []
    for stream in (sys.stdout, sys.stderr):
        try:
            fds.append(stream.fileno())
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    libc = ctypes.CDLL(None)
    saved = [os.dup(fd) for fd in fds]
    try:
        with open(os.devnull, "w") as null:
            for fd in fds:
                os.dup2(null.fileno(), fd)
            try:
                yield
            finally:
                libc.fflush(None)  # C's buffered output goes to /dev/null, not to the restored fds
    finally:
        for fd, keep in zip(fds, saved, strict=True):
            os.dup2(keep, fd)
            os.close(keep)
