"""Output folders that never lose a user's files: staged writes, one commit, named errors.

An :class:`OutputFolder` is where an offline tool puts its results. It

- refuses a folder that holds the input, or results of an earlier run unless ``overwrite``;
- writes every product to a temporary file beside it and renames them all into place at
  :meth:`OutputFolder.commit`, so a crash, a full disk or an error leaves the earlier results
  or nothing, never half a file;
- removes only what it wrote in this run (its temporary files, and the folder itself if it
  created it and it is empty): a user's files in the folder, whatever their names, stay;
- names the file in every write error.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

log = logging.getLogger(__name__)


def _umask() -> int:
    """The process's file-creation mask."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _inside(child: Path, parent: Path) -> bool:
    """Whether ``child`` is ``parent`` or lies under it (both resolved)."""
    c, p = child.resolve(), parent.resolve()
    return c == p or p in c.parents


class OutputFolder:
    """A results folder for one run of a tool.

    Args:
        path: The folder (created if missing).
        products: The file names the tool may write there (its own results).
        overwrite: Replace the results of an earlier run. Without it, a folder that holds any
            of ``products`` is refused. With it, an earlier product that this run does not
            write again is removed at :meth:`commit` (it is the tool's own, and would
            otherwise sit beside the new results as if it were one of them).
        inputs: Paths the run reads; a folder that is or contains one of them is refused.

    Raises:
        ValueError: The folder is an input or holds one, is a file, or holds earlier results
            without ``overwrite``.
        OSError: The folder cannot be created or written (the message names it).

    Use as a context manager: on an exception the staged files are discarded (and the folder
    removed if this run created it and nothing else is in it); on success, :meth:`commit` must
    have been called.
    """

    def __init__(
        self,
        path: str | Path,
        products: Iterable[str],
        overwrite: bool = False,
        inputs: Iterable[str | Path | None] = (),
    ) -> None:
        self.path = Path(path)
        self.products = tuple(products)
        self.overwrite = overwrite
        for src in inputs:
            if src is not None and Path(src).exists() and _inside(Path(src), self.path):
                raise ValueError(
                    f"--out {self.path}: holds the input {src}; choose an output folder outside the input"
                )
        if self.path.is_symlink() and not self.path.exists():
            raise ValueError(
                f"--out {self.path}: a symbolic link to {os.readlink(self.path)}, which does not exist"
            )
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"--out {self.path}: exists and is not a folder")
        self.earlier = [p for p in self.products if (self.path / p).exists()]
        if self.earlier and not overwrite:
            raise ValueError(
                f"--out {self.path} holds results of an earlier run ({', '.join(self.earlier)}); pass "
                "--overwrite to replace them, or choose another folder"
            )
        self._created: list[Path] = []  # folders this run made, outermost first
        missing = [p for p in (self.path, *self.path.parents) if not p.exists()]
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self._created = list(reversed(missing))
            with tempfile.NamedTemporaryFile(dir=self.path, prefix=".write-check-"):
                pass
        except OSError as exc:
            self._remove_created()
            raise OSError(f"--out {self.path}: cannot write there ({exc.strerror or exc})") from None
        self._staged: dict[str, Path] = {}  # product -> its temporary file or folder
        self.committed = False

    # ------------------------------------------------------------------ writing
    def _check(self, name: str) -> None:
        if name not in self.products:
            raise ValueError(f"{name}: not one of this tool's products {self.products}")
        if self.committed:
            raise RuntimeError(f"{self.path}: already committed")

    def stage(self, name: str) -> Path:
        """A temporary path in the folder for the product ``name`` (renamed into place at commit)."""
        self._check(name)
        fd, tmp = tempfile.mkstemp(dir=self.path, prefix=f".{name}.", suffix=".part")
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())  # as open() would make it, not mkstemp's 0600
        self._staged[name] = Path(tmp)
        return Path(tmp)

    @contextlib.contextmanager
    def writing(self, name: str) -> Iterator[Path]:
        """The staged path of the product ``name``, for a writer that takes a path; errors name the file."""
        tmp = self.stage(name)
        try:
            yield tmp
        except OSError as exc:
            if str(self.path / name) in str(exc):
                raise
            raise OSError(f"{self.path / name}: cannot write ({exc.strerror or exc})") from None

    @contextlib.contextmanager
    def open(self, name: str, mode: str = "w", **kwargs) -> Iterator[IO]:
        """Open the product ``name`` for writing (a staged temporary file); errors name the file."""
        tmp = self.stage(name)
        try:
            with open(tmp, mode, **kwargs) as fh:
                yield fh
        except OSError as exc:
            raise OSError(f"{self.path / name}: cannot write ({exc.strerror or exc})") from None

    def write_text(self, name: str, text: str) -> Path:
        """Stage the product ``name`` with ``text``; returns its final path."""
        with self.open(name, "w", encoding="utf-8") as fh:
            fh.write(text)
        return self.path / name

    # ------------------------------------------------------------------ ending
    def commit(self) -> list[Path]:
        """Put every staged product in place, all or none; with ``overwrite``, drop stale earlier ones.

        The earlier results this run replaces are first moved aside, then the new ones renamed
        into place; if any step fails, the new ones are taken out and the earlier ones put back
        (the error names the file), so the folder holds the earlier results or the new ones,
        never a mix.

        Returns:
            The final paths of the products written.
        """
        aside: list[tuple[Path, Path]] = []  # (final, the earlier result moved aside)
        placed: list[Path] = []
        try:
            for name, tmp in self._staged.items():
                final = self.path / name
                if final.exists() or final.is_symlink():
                    if final.is_dir() and not final.is_symlink():
                        raise IsADirectoryError(21, "a folder is in the way", str(final))
                    keep = self.path / f".{name}.{uuid.uuid4().hex[:8]}.earlier"
                    os.replace(final, keep)
                    aside.append((final, keep))
                os.replace(tmp, final)
                placed.append(final)
        except OSError as exc:
            for final in placed:  # roll back: the new ones out, the earlier ones in again
                with contextlib.suppress(OSError):
                    final.unlink()
            for final, keep in aside:
                with contextlib.suppress(OSError):
                    os.replace(keep, final)
            where = exc.filename or self.path
            raise OSError(f"{where}: cannot write ({exc.strerror or exc}); the folder is as it was") from None
        for _, keep in aside:
            with contextlib.suppress(OSError):
                keep.unlink()
        stale = [p for p in self.earlier if p not in self._staged]
        for name in stale:  # the earlier run's own product, which this run did not remake
            old = self.path / name
            if old.is_file():
                old.unlink()
                log.warning(
                    "--out %s: removed %s of the earlier run (this run does not make it)", self.path, name
                )
        self._staged.clear()
        self.committed = True
        return placed

    def discard(self) -> None:
        """Remove what this run staged, and the folder if this run created it and it is empty."""
        for tmp in self._staged.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self._staged.clear()
        self._remove_created()

    def _remove_created(self) -> None:
        for d in reversed(self._created):  # innermost first; only if empty
            with contextlib.suppress(OSError):
                d.rmdir()
        self._created = []

    def __enter__(self) -> OutputFolder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None or not self.committed:
            self.discard()
