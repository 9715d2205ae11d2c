"""Output folders that never lose a user's files: staged writes, one commit, named errors.

An :class:`OutputFolder` is where a tool puts its results; every command that writes results
writes through one. It

- refuses an empty name (which would be the current folder), a folder that holds the input,
  and a folder that holds results of an earlier run unless ``overwrite`` (or ``keep``, to add
  to them: a resumed sweep);
- never writes through a symbolic link: a product whose path is a link (or lies under one), or
  a folder where a file is due, is refused before any work;
- writes every file product to a temporary file beside it and renames them all into place at
  :meth:`OutputFolder.commit`, so a crash, a full disk or an error leaves the earlier results
  or nothing, never half a file;
- removes only what it wrote in this run (its temporary files, and the folders it created if
  they are empty): a user's files in the folder stay, whatever their names, and so does an
  earlier run's product that this run does not make again (with a warning);
- names the file in every write error.

Folder products (names ending in ``/``) are for work that must survive an interruption as it
goes (a sweep's runs, a training's checkpoints): :meth:`OutputFolder.subfolder` makes one, and
what is written there goes through an :class:`OutputFolder` of its own or is the tool's
incremental output.
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


def check_out(path: str | Path) -> Path:
    """``path`` as an output folder's path, or ValueError if it names none (empty, blank)."""
    if not str(path).strip():
        raise ValueError("--out: empty; name the output folder (it is created if missing)")
    return Path(path)


class OutputFolder:
    """A results folder for one run of a tool.

    Args:
        path: The folder (created if missing, with its parents).
        products: The names the tool may write there: files (``"report.md"``, or under a
            subfolder it owns: ``"slip_aware/metrics.json"``) and folders (``"runs/"``, with a
            trailing slash; see :meth:`subfolder`).
        overwrite: Replace the results of an earlier run. Without it (and without ``keep``), a
            folder that holds any of ``products`` (a folder product: one that is not empty) is
            refused.
        inputs: Paths the run reads; a folder that is or contains one of them is refused.
        keep: Add to an earlier run's results (a resumed run): they are neither refused nor
            replaced unless written again.
        announce: Log a warning naming the earlier results that ``overwrite`` replaces (False:
            a folder inside another tool's, whose replacement the user already asked for).
        within: A folder this one is made inside (a tool's own subfolder: a sweep's run): the
            path from it down to ``path`` must hold no symbolic link either.

    Raises:
        ValueError: The name is empty; the folder is an input or holds one, is a file, holds
            earlier results without ``overwrite``, or a product's path is a symbolic link or
            a folder where a file is due.
        OSError: The folder cannot be created or written (the message names it).

    Use as a context manager: on an exception the staged files are discarded (and the folders
    this run created removed if nothing else is in them); on success, :meth:`commit` must have
    been called.
    """

    def __init__(
        self,
        path: str | Path,
        products: Iterable[str],
        overwrite: bool = False,
        inputs: Iterable[str | Path | None] = (),
        keep: bool = False,
        announce: bool = True,
        within: str | Path | None = None,
    ) -> None:
        self.path = check_out(path)
        if within is not None:
            self._check_within(Path(within))
        self.products = tuple(products)
        self.overwrite = overwrite
        self.keep = keep
        self.announce = announce
        for name in self.products:
            parts = Path(name.rstrip("/")).parts
            if not parts or Path(name).is_absolute() or ".." in parts or name.startswith("."):
                raise ValueError(f"{name!r}: a product is a relative name inside the folder")
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
        for name in self.products:
            self._check_product_path(name)
        self.earlier = [p for p in self.products if self._exists(p)]
        if self.earlier and not (overwrite or keep):
            raise ValueError(
                f"--out {self.path} holds results of an earlier run ({', '.join(self.earlier)}); pass "
                "--overwrite to replace them, or choose another folder"
            )
        if self.earlier and overwrite and announce:
            log.warning("--out %s: replacing %s", self.path, ", ".join(self.earlier))
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
        self._staged: dict[str, Path] = {}  # product -> its temporary file
        self.committed = False

    def add_products(self, names: Iterable[str]) -> None:
        """Declare more products once the tool knows them, with the checks of the first ones.

        Raises:
            ValueError: As the constructor does: a product's path is a link or a folder where a
                file is due, or it holds an earlier run's result without ``overwrite``.
        """
        new = [n for n in names if n not in self.products]
        for name in new:
            self._check_product_path(name)
        earlier = [n for n in new if self._exists(n)]
        if earlier and not (self.overwrite or self.keep):
            raise ValueError(
                f"--out {self.path} holds results of an earlier run ({', '.join(earlier)}); pass "
                "--overwrite to replace them, or choose another folder"
            )
        self.products += tuple(new)
        self.earlier += earlier

    # ------------------------------------------------------------------ checks
    def _check_within(self, within: Path) -> None:
        try:
            rel = self.path.relative_to(within)
        except ValueError:
            raise ValueError(f"{self.path}: not inside {within}") from None
        for k in range(1, len(rel.parts) + 1):
            p = within.joinpath(*rel.parts[:k])
            if p.is_symlink():
                raise ValueError(
                    f"{p}: a symbolic link (to {os.readlink(p)}) where this tool keeps its own folder; "
                    "results are never written through a link: remove it"
                )

    def _exists(self, name: str) -> bool:
        p = self.path / name.rstrip("/")
        if name.endswith("/"):
            return p.is_dir() and any(p.iterdir())
        return p.exists() or p.is_symlink()

    def _check_product_path(self, name: str) -> None:
        """A product's path must not be, or lie under, a link; a file's must not be a folder."""
        rel = Path(name.rstrip("/"))
        for k in range(1, len(rel.parts) + 1):
            p = self.path.joinpath(*rel.parts[:k])
            if p.is_symlink():
                target = os.readlink(p)
                raise ValueError(
                    f"--out {self.path}: {Path(*rel.parts[:k])} is a symbolic link (to {target}); results "
                    "are never written through a link: remove it or choose another folder"
                )
            last = k == len(rel.parts)
            folder_due = not last or name.endswith("/")
            if p.exists() and folder_due and not p.is_dir():
                raise ValueError(
                    f"--out {self.path}: {Path(*rel.parts[:k])} is a file where this tool writes a folder; "
                    "move it or choose another folder"
                )
            if p.exists() and not folder_due and p.is_dir():
                raise ValueError(
                    f"--out {self.path}: {name} is a folder where this tool writes a file; move it or "
                    "choose another folder"
                )

    def _check(self, name: str) -> None:
        if name not in self.products or name.endswith("/"):
            raise ValueError(f"{name}: not one of this tool's file products {self.products}")
        if self.committed:
            raise RuntimeError(f"{self.path}: already committed")

    def _make_parents(self, rel: Path) -> Path:
        """The folder of a product (made, and remembered as this run's, where missing)."""
        parent = self.path
        for part in rel.parts[:-1]:
            parent = parent / part
            if not parent.exists():
                parent.mkdir()
                self._created.append(parent)
        return parent

    # ------------------------------------------------------------------ writing
    def stage(self, name: str) -> Path:
        """A temporary path in the folder for the file product ``name`` (renamed into place at commit).

        The temporary file keeps the product's extension (writers that choose a format by it
        work), and its name starts with a dot.
        """
        self._check(name)
        rel = Path(name)
        parent = self._make_parents(rel)
        fd, tmp = tempfile.mkstemp(dir=parent, prefix=f".{rel.stem}.", suffix=f".part{rel.suffix}")
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())  # as open() would make it, not mkstemp's 0600
        if name in self._staged:
            with contextlib.suppress(OSError):
                self._staged[name].unlink()
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

    def write_bytes(self, name: str, data: bytes) -> Path:
        """Stage the product ``name`` with ``data``; returns its final path."""
        with self.open(name, "wb") as fh:
            fh.write(data)
        return self.path / name

    def unstage(self, name: str) -> None:
        """Drop what was staged for ``name`` (it will not be committed)."""
        tmp = self._staged.pop(name, None)
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()

    def subfolder(self, name: str) -> Path:
        """The folder product ``name`` (``"runs/"``), made if missing; what is in it is kept on discard."""
        if name not in self.products or not name.endswith("/"):
            raise ValueError(f"{name}: not one of this tool's folder products {self.products}")
        rel = Path(name.rstrip("/"))
        self._make_parents(rel)
        p = self.path / rel
        if not p.exists():
            p.mkdir()
            self._created.append(p)
        return p

    # ------------------------------------------------------------------ ending
    def commit(self) -> list[Path]:
        """Put every staged product in place, all or none.

        The earlier results this run replaces are first moved aside, then the new ones renamed
        into place; if any step fails, the new ones are taken out and the earlier ones put back
        (the error names the file), so the folder holds the earlier results or the new ones,
        never a mix. An earlier product that this run did not write again is left as it was.

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
                    keep = final.parent / f".{final.name}.{uuid.uuid4().hex[:8]}.earlier"
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
        stale = [p for p in self.earlier if p not in self._staged and not p.endswith("/")]
        for name in stale if self.announce else ():
            log.warning(
                "--out %s: %s is not from this run (this run does not make it); left as it was",
                self.path,
                name,
            )
        self._staged.clear()
        self.committed = True
        return placed

    def discard(self) -> None:
        """Remove what this run staged, and the folders this run created if they are empty."""
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
