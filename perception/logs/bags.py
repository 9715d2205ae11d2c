"""Camera and IMU streams from robot logs: ROS 1 bags, ROS 2 bag folders and MCAP files.

Messages (deserialised with the ``rosbags`` type system; no ROS installation needed):

- ``sensor_msgs/Image`` (mono8/16, 8UC1, 16UC1, rgb8, bgr8, rgba8, bgra8, 8UC3, the Bayer
  encodings and packed YUV 4:2:2) and ``sensor_msgs/CompressedImage`` (any format OpenCV
  decodes: JPEG, PNG, ...);
- ``sensor_msgs/CameraInfo``: the intrinsics (K, ``plumb_bob`` or ``rational_polynomial``
  distortion, image size);
- ``sensor_msgs/Imu``: angular velocity [rad/s] and linear acceleration [m/s^2].

Logs are streams that can be damaged. ROS 1 bags are read with ``rosbags``; ROS 2 SQLite bags
row by row with the standard library's ``sqlite3``; MCAP files record by record with ``mcap``.
A message that does not deserialise is skipped with a warning naming its topic, its index and
its time. A damaged MCAP chunk or SQLite message row loses only itself. Damage that breaks a
file's structure (a ROS 1 chunk, an SQLite b-tree page, a cut-off MCAP) ends the reading at
the last good message, with a warning naming the file and the position (docs/logs.md). Frame
times are the header stamps [s], checked against the log's receive times by
:mod:`perception.logs.log_time`.

Writers of ``nav_msgs/Odometry`` and ``sensor_msgs/JointState`` into an MCAP file (ROS 2 CDR,
playable by Foxglove and ``ros2 bag play``) are at the end.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import shutil
import sqlite3
import tempfile
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
IMU_TYPE = "sensor_msgs/msg/Imu"
#: Most pixels of one image message (the same budget as image files).
MAX_MESSAGE_PIXELS = 8192 * 8192
#: Largest MCAP record read into memory [bytes]: a damaged length field claims more.
MAX_RECORD_BYTES = 1 << 30


def is_log(path: str | Path) -> bool:
    """Whether ``path`` is a robot log: a ``.bag``, ``.mcap`` or ``.db3`` file, or a ROS 2 bag folder.

    A ROS 2 bag folder holds ``.db3`` or ``.mcap`` storage files (with its ``metadata.yaml``, or
    without it where a killed recorder never wrote it); a folder of images with a
    ``metadata.yaml`` of its own is not one.
    """
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in (".bag", ".mcap", ".db3")
    return p.is_dir() and bool(_storage_files(p)[0] or _storage_files(p)[1])


def _natural(path: Path) -> list:
    """A sort key that puts ``bag_2`` before ``bag_10``."""
    import re

    return [int(x) if x.isdigit() else x for x in re.split(r"(\d+)", path.name)]


def _storage_files(folder: Path) -> tuple[list[Path], list[Path]]:
    """The folder's .db3 and .mcap files, in natural name order (the order a recorder splits in)."""
    return (
        sorted(folder.glob("*.db3"), key=_natural),
        sorted(folder.glob("*.mcap"), key=_natural),
    )


_warned: set[str] = set()


def new_run() -> None:
    """Start a run: forget the warnings given so far, remove the repaired copies an earlier run made.

    Each warning is then given again, once.
    """
    _warned.clear()
    for tmp in _REPAIRED.values():
        tmp.cleanup()
    _REPAIRED.clear()


def _warn_once(msg: str, *args) -> None:
    """A warning that the several opens of one log in a run give only once."""
    text = msg % args
    if text not in _warned:
        _warned.add(text)
        log.warning(text)


@functools.lru_cache(maxsize=2)
def _typestore(which: str):
    """The type store (rosbags') of ROS 1 (Noetic) or ROS 2 (Humble) messages, built once."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if which == "ros1" else Stores.ROS2_HUMBLE)


def _ros2_name(name: str) -> str:
    """A message type in ROS 2 form: ``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image``."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


@dataclass(frozen=True)
class LogMessage:
    """One message of a log, not yet deserialised.

    Attributes:
        topic: Its topic.
        msgtype: Its type, ROS 2 form (``sensor_msgs/msg/Image``).
        index: Its number on the topic, from 0, in the order read.
        log_ns: The log's receive time [ns].
        data: The serialised message.
        encoding: ``"cdr"`` (ROS 2) or ``"ros1"``.
    """

    topic: str
    msgtype: str
    index: int
    log_ns: int
    data: bytes
    encoding: str


def _where(m: LogMessage) -> str:
    return f"{m.topic} message {m.index} (log time {1e-9 * m.log_ns:.6f} s)"


class RobotLog:
    """An open log: its topics and a message stream that survives damage.

    Use :func:`open_log`; as a context manager it closes the file.
    """

    path: Path

    def topics(self) -> dict[str, tuple[str, int | None]]:
        """{topic: (message type, message count or None where the log does not say)}."""
        raise NotImplementedError

    def messages(self, topics: Collection[str]) -> Iterator[LogMessage]:
        """The messages of ``topics`` in the log's order; damage is skipped or ends the stream (warned)."""
        raise NotImplementedError

    def span(self) -> float | None:
        """How long the log lasts on its receive clock [s], or None where it does not say."""
        return None

    def decode(self, m: LogMessage):
        """The deserialised message, or None (with a warning naming it) if it does not deserialise."""
        try:
            return self._decode(m)
        except Exception as exc:  # any damage: the message is skipped, the run goes on
            _warn_once("%s: %s does not deserialise (%s); skipped", self.path, _where(m), _short(exc))
            return None

    def _decode(self, m: LogMessage):
        if m.encoding == "ros1":
            return _typestore("ros1").deserialize_ros1(m.data, m.msgtype)
        return _typestore("ros2").deserialize_cdr(m.data, m.msgtype)

    def close(self) -> None:
        """Release the file."""

    def __enter__(self) -> RobotLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _ended(self, where: str, after: LogMessage | None, exc: Exception) -> None:
        pos = f"after {_where(after)}" if after is not None else "before its first message"
        _warn_once(
            "%s: damaged %s (%s); reading ends there: everything read so far is used",
            where, pos, _short(exc),
        )  # fmt: skip


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:200]}" if text else type(exc).__name__


class _RosbagsLog(RobotLog):
    """A log read with rosbags' AnyReader (ROS 1 bags; compressed ROS 2 bags)."""

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self._reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            self._reader.open()
        except Exception as exc:  # rosbags raises its own errors for every kind of damage
            hint = (
                "; if the recording was cut off, 'rosbag reindex' rebuilds its index"
                if path.suffix == ".bag"
                else ""
            )
            raise ValueError(
                f"{path}: not a readable ROS 1 bag, ROS 2 bag or MCAP file ({_short(exc)}){hint}"
            ) from None

    def topics(self) -> dict[str, tuple[str, int | None]]:
        out: dict[str, tuple[str, int | None]] = {}
        for c in self._reader.connections:
            n = (out.get(c.topic, (c.msgtype, 0))[1] or 0) + c.msgcount
            out[c.topic] = (c.msgtype, n)
        return out

    def messages(self, topics: Collection[str]) -> Iterator[LogMessage]:
        conns = [c for c in self._reader.connections if c.topic in topics]
        if not conns:
            return
        it = self._reader.messages(connections=conns)
        counts: dict[str, int] = {}
        last = None
        while True:
            try:
                conn, ns, raw = next(it)
            except StopIteration:
                return
            except Exception as exc:  # a damaged chunk: the iterator is spent
                self._ended(str(self.path), last, exc)
                return
            k = counts.get(conn.topic, 0)
            counts[conn.topic] = k + 1
            last = LogMessage(conn.topic, conn.msgtype, k, int(ns), bytes(raw), "rosbags")
            yield last

    def _decode(self, m: LogMessage):
        return self._reader.deserialize(m.data, m.msgtype)

    def span(self) -> float | None:
        try:
            return 1e-9 * (self._reader.end_time - self._reader.start_time)
        except Exception:  # noqa: BLE001 - an empty or odd log: unknown
            return None

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._reader.close()


class _SqliteLog(RobotLog):
    """A ROS 2 bag in SQLite storage, read row by row.

    A damaged message row loses only itself; a damaged page of the table's b-tree, the rows
    after it.
    """

    def __init__(self, path: Path, files: list[Path], counts: dict[str, int] | None = None) -> None:
        self.path = path
        self._files = files
        self._meta_counts = counts or {}
        self._dbs: list[sqlite3.Connection] = []
        self._topics: dict[str, tuple[str, str]] = {}  # name -> (type, serialisation)
        self._ids: list[dict[int, str]] = []
        for f in files:
            db, rows = self._open(f)
            self._dbs.append(db)
            ids = {}
            for tid, name, ty, ser in rows:
                ids[int(tid)] = str(name)
                self._topics.setdefault(str(name), (_ros2_name(str(ty)), str(ser)))
            self._ids.append(ids)

    _QUERY = "SELECT id, name, type, serialization_format FROM topics"

    def _open(self, f: Path) -> tuple[sqlite3.Connection, list]:
        """The file's connection and topics.

        A cut-off file, or one on read-only media with a write-ahead log, is read through a
        repaired copy (with a warning).
        """
        try:
            db = sqlite3.connect(f"{f.resolve().as_uri()}?mode=ro", uri=True)
            return db, db.execute(self._QUERY).fetchall()
        except sqlite3.Error as exc:
            first = exc
        try:
            db = self._repaired(f)
            rows = db.execute(self._QUERY).fetchall()
        except (OSError, sqlite3.Error, ValueError) as exc:
            raise ValueError(
                f"{f}: not a readable ROS 2 SQLite bag ({_short(first)}; {_short(exc)})"
            ) from None
        _warn_once("%s: %s; reading a repaired copy of it", f, _short(first))
        return db, rows

    def _repaired(self, f: Path) -> sqlite3.Connection:
        """A connection to a repaired copy of ``f`` (:func:`_repaired_copy`)."""
        return sqlite3.connect(str(_repaired_copy(f)))

    def topics(self) -> dict[str, tuple[str, int | None]]:
        counts: dict[str, int | None] = {}
        for db, ids in zip(self._dbs, self._ids, strict=True):
            try:
                rows = db.execute("SELECT topic_id, count(*) FROM messages GROUP BY topic_id").fetchall()
            except sqlite3.Error:  # damaged: the metadata's counts, or unknown
                return {n: (ty, self._meta_counts.get(n)) for n, (ty, _) in self._topics.items()}
            for tid, n in rows:
                name = ids.get(int(tid))
                if name is not None:
                    counts[name] = (counts.get(name) or 0) + int(n)
        return {n: (ty, counts.get(n, 0)) for n, (ty, _) in self._topics.items()}

    def span(self) -> float | None:
        lo, hi = math.inf, -math.inf
        for db in self._dbs:
            try:
                a, b = db.execute("SELECT MIN(timestamp), MAX(timestamp) FROM messages").fetchone()
            except sqlite3.Error:
                return None
            if a is not None:
                lo, hi = min(lo, a), max(hi, b)
        return 1e-9 * (hi - lo) if hi >= lo else None

    def messages(self, topics: Collection[str]) -> Iterator[LogMessage]:
        counts: dict[str, int] = {}
        for f, db, ids in zip(self._files, self._dbs, self._ids, strict=True):
            want = {tid for tid, name in ids.items() if name in topics}
            if not want:
                continue
            rows = _scan_rows(db, want, f)
            rows.sort()
            for ts, rid, tid in rows:
                name = ids[tid]
                k = counts.get(name, 0)
                counts[name] = k + 1
                try:
                    (data,) = db.execute("SELECT data FROM messages WHERE id = ?", (rid,)).fetchone()
                except (sqlite3.Error, TypeError) as exc:  # a damaged row: only it is lost
                    _warn_once(
                        "%s: %s message %d (log time %.6f s, row %d) is damaged (%s); skipped",
                        f, name, k, 1e-9 * ts, rid, _short(exc),
                    )  # fmt: skip
                    continue
                ty, ser = self._topics[name]
                yield LogMessage(name, ty, k, ts, bytes(data), "ros1" if ser == "ros1" else "cdr")

    def close(self) -> None:
        for db in self._dbs:
            db.close()


def _scan_rows(db: sqlite3.Connection, want: set[int], f: Path) -> list[tuple[int, int, int]]:
    """(timestamp, id, topic id) of the message rows of topics ``want``, in row order.

    The table is read in stretches of row ids. A stretch that does not read (a damaged page of
    the table's b-tree) is read again row by row, each row sought on its own through the
    b-tree's interior pages, so that only the rows the damaged page holds are lost (one warning
    names the file and their ids).
    """
    stretch = 256
    try:
        top = db.execute("SELECT max(id) FROM messages").fetchone()[0]
    except sqlite3.Error:
        top = None  # the rightmost path is damaged: read until the ids run out
    rows: list[tuple[int, int, int]] = []
    lost: list[int] = []
    pos = 0
    damage = ""
    while top is None or pos <= top:
        try:
            batch = db.execute(
                "SELECT id, topic_id, timestamp FROM messages WHERE id >= ? ORDER BY id LIMIT ?",
                (pos, stretch),
            ).fetchall()
        except sqlite3.Error as exc:
            damage = damage or _short(exc)
            found = False
            for rid in range(pos, pos + stretch):
                try:
                    r = db.execute("SELECT topic_id, timestamp FROM messages WHERE id = ?", (rid,)).fetchone()
                except sqlite3.Error:
                    lost.append(rid)
                    continue
                if r is not None:
                    found = True
                    if r[0] in want:
                        rows.append((int(r[1]), rid, int(r[0])))
            pos += stretch
            if top is None and not found:
                break  # no row in a whole stretch, and no end known: the damage runs to the end
            continue
        if not batch:
            break
        rows += [(int(ts), int(rid), int(tid)) for rid, tid, ts in batch if tid in want]
        pos = int(batch[-1][0]) + 1
    if lost:
        spans: list[str] = []
        start: int | None = lost[0]
        for a, b in zip(lost, lost[1:] + [None]):
            if b != a + 1:
                spans.append(f"{start}" if start == a else f"{start} to {a}")
                start = b
        _warn_once(
            "%s: damaged page (%s): message rows %s are lost; every other row is read",
            f, damage, ", ".join(spans[:5]) + (" ..." if len(spans) > 5 else ""),
        )  # fmt: skip
    return rows


#: Repaired copies of damaged SQLite files, by (file, size, modification time): made once a run.
_REPAIRED: dict[tuple[str, int, int], tempfile.TemporaryDirectory] = {}


def _repaired_copy(f: Path) -> Path:
    """A copy of ``f`` (and its write-ahead log) in a temporary folder, cut to whole pages.

    The header's page count is cleared, so that SQLite counts the pages there are. The copy is
    made once a run (:func:`new_run` and the process's end remove it).
    """
    st = f.stat()
    key = (str(f.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _REPAIRED:
        tmp = tempfile.TemporaryDirectory(prefix="rover-bag-")
        copy = Path(tmp.name) / f.name
        try:
            for suffix in ("", "-wal", "-shm"):
                src = Path(f"{f}{suffix}")
                if src.is_file():
                    shutil.copyfile(src, Path(f"{copy}{suffix}"))
            with open(copy, "r+b") as fh:
                head = fh.read(100)
                if len(head) < 100 or not head.startswith(b"SQLite format 3\x00"):
                    raise ValueError("its SQLite header is damaged")
                page = int.from_bytes(head[16:18], "big")
                page = 65536 if page == 1 else page
                size = fh.seek(0, 2)
                fh.truncate(size - size % page)
                fh.seek(28)
                fh.write(b"\x00\x00\x00\x00")
        except BaseException:
            tmp.cleanup()
            raise
        _REPAIRED[key] = tmp
    return Path(_REPAIRED[key].name) / f.name


class _McapLog(RobotLog):
    """MCAP files read record by record.

    A damaged chunk loses only its records from the damage on; a damaged record header is
    skipped by the summary's chunk index where there is one (else the reading ends there); a
    cut-off file keeps every message before the cut, those of the cut chunk included. Schemas
    and channels come from the summary where it is readable, so a damaged definition in the
    data costs nothing.
    """

    def __init__(self, path: Path, files: list[Path]) -> None:
        self.path = path
        self._files = files
        for f in files:
            try:
                with open(f, "rb") as fh:
                    head = fh.read(8)
            except OSError as exc:
                raise ValueError(f"{f}: not readable ({exc.strerror or exc})") from None
            if head != b"\x89MCAP0\r\n":
                raise ValueError(f"{f}: not an MCAP file (its first bytes are not MCAP's magic)")
        self._summaries: dict[Path, object] = {}
        self._topics: dict[str, tuple[str, int | None]] | None = None

    def _summary(self, f: Path):
        """The file's summary section, or None where it is missing or damaged (a cut-off recording)."""
        if f not in self._summaries:
            from mcap.reader import make_reader

            try:
                with open(f, "rb") as fh:
                    summary = make_reader(fh).get_summary()
            except Exception:  # noqa: BLE001 - any damage: read the data section alone
                summary = None
            self._summaries[f] = summary
        return self._summaries[f]

    def span(self) -> float | None:
        lo, hi = math.inf, -math.inf
        for f in self._files:
            st = getattr(self._summary(f), "statistics", None)
            if st is None:
                return None
            lo, hi = min(lo, st.message_start_time), max(hi, st.message_end_time)
        return 1e-9 * (hi - lo) if hi >= lo else None

    def topics(self) -> dict[str, tuple[str, int | None]]:
        if self._topics is None:
            self._topics = {}
            for f in self._files:
                for name, (ty, n) in self._file_topics(f).items():
                    old = self._topics.get(name, (ty, 0))[1]
                    self._topics[name] = (ty, None if n is None or old is None else old + n)
        return self._topics

    def _file_topics(self, f: Path) -> dict[str, tuple[str, int | None]]:
        """Topics from the summary; where it is damaged or missing (a cut-off recording), from the data."""
        summary = self._summary(f)
        out: dict[str, tuple[str, int | None]] = {}
        if summary is not None and summary.statistics is not None and _definitions_ok(summary, f):
            counts = summary.statistics.channel_message_counts
            for cid, ch in summary.channels.items():
                schema = summary.schemas.get(ch.schema_id)
                ty = _ros2_name(schema.name) if schema is not None else "?"
                out[ch.topic] = (ty, (out.get(ch.topic, (ty, 0))[1] or 0) + int(counts.get(cid, 0)))
            return out
        for (topic, ty, _enc), _msg in self._records(f, quiet=True):
            n = out.get(topic, (ty, 0))[1] or 0
            out[topic] = (ty, n + 1)
        return out

    def _records(self, f: Path, quiet: bool = False) -> Iterator[tuple[tuple[str, str, str], Any]]:
        """((topic, type, encoding), Message) of each readable message of ``f``, in file order."""
        import io
        import os
        import struct

        from mcap.data_stream import ReadDataStream
        from mcap.opcode import Opcode
        from mcap.records import Channel, Chunk, Message, Schema

        last: list = []  # the last message yielded: (topic, log time [ns])

        def warn(fmt: str, *args) -> None:
            if not quiet:
                where = (
                    f" (after the {last[0]} message at log time {1e-9 * last[1]:.6f} s)"
                    if last
                    else " (before its first message)"
                )
                _warn_once(fmt + where, *args)

        summary = self._summary(f)
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str, str]] = {}
        starts: list[int] = []
        if summary is not None:
            if _definitions_ok(summary, f):
                schemas = {i: _ros2_name(sc.name) for i, sc in summary.schemas.items()}
                for i, ch in summary.channels.items():
                    channels[i] = (ch.topic, schemas.get(ch.schema_id, "?"), ch.message_encoding)
            starts = sorted(ci.chunk_start_offset for ci in summary.chunk_indexes)
        orphans = 0

        def handle(rec):
            nonlocal orphans
            if isinstance(rec, Schema):  # the summary's (trusted) definitions win: listing and reading agree
                schemas.setdefault(rec.id, _ros2_name(rec.name))
            elif isinstance(rec, Channel):
                channels.setdefault(
                    rec.id, (rec.topic, schemas.get(rec.schema_id, "?"), rec.message_encoding)
                )
            elif isinstance(rec, Message):
                if rec.channel_id in channels:
                    last[:] = [channels[rec.channel_id][0], rec.log_time]
                    return channels[rec.channel_id], rec
                orphans += 1
            return None

        known = {int(o) for o in Opcode}
        with open(f, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            pos = 8
            while pos < size:
                fh.seek(pos)
                head = fh.read(9)
                if len(head) < 9:
                    warn(
                        "%s: cut off at byte %d (inside a record's header); everything before it is used",
                        f,
                        pos,
                    )
                    break
                opcode, length = struct.unpack("<BQ", head)
                if opcode not in known or length > MAX_RECORD_BYTES:
                    nxt = next((s for s in starts if s > pos), None)
                    if nxt is None:
                        warn(
                            "%s: damaged record header at byte %d; reading ends there: everything read "
                            "so far is used", f, pos,
                        )  # fmt: skip
                        break
                    warn("%s: damaged record header at byte %d; reading resumes at the next chunk (byte %d)",
                         f, pos, nxt)  # fmt: skip
                    pos = nxt
                    continue
                if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                    break
                cut = pos + 9 + length > size
                nxt = next((s for s in starts if s > pos), None)
                if cut and nxt is not None:  # not a cut: a damaged length, and the index knows better
                    warn("%s: the record at byte %d claims %d bytes, past the end; reading resumes at the "
                         "next chunk (byte %d)", f, pos, length, nxt)  # fmt: skip
                    pos = nxt
                    continue
                if cut and opcode != Opcode.CHUNK:
                    warn("%s: cut off at byte %d (a record of %d bytes); everything before it is used",
                         f, pos, length)  # fmt: skip
                    break
                body = fh.read(length)
                stream = ReadDataStream(io.BytesIO(body))
                try:
                    if opcode == Opcode.CHUNK:
                        chunk = Chunk.read(stream)
                        damaged = functools.partial(warn, "%s: the chunk at byte %d: %s", f, pos)
                        for r in _chunk_records(chunk, partial=cut, on_damage=damaged):
                            out = handle(r)
                            if out is not None:
                                yield out
                    elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                        rec = {Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read}.get(opcode)
                        out = handle(rec(stream) if rec is not None else Message.read(stream, length))
                        if out is not None:
                            yield out
                except Exception as exc:  # this record (or the rest of this chunk) is lost
                    what = "chunk" if opcode == Opcode.CHUNK else "record"
                    warn("%s: the %s at byte %d is damaged (%s); its messages from the damage on are skipped",
                         f, what, pos, _short(exc))  # fmt: skip
                if cut:
                    warn(
                        "%s: cut off inside the chunk at byte %d; its messages before the cut are used",
                        f,
                        pos,
                    )
                    break
                pos += 9 + length
        if orphans:
            warn(
                "%s: %d messages on channels whose definition is damaged or missing were skipped", f, orphans
            )

    def messages(self, topics: Collection[str]) -> Iterator[LogMessage]:
        counts: dict[str, int] = {}
        for f in self._files:
            for (topic, ty, enc), msg in self._records(f):
                if topic not in topics:
                    continue
                k = counts.get(topic, 0)
                counts[topic] = k + 1
                yield LogMessage(
                    topic, ty, k, int(msg.log_time), bytes(msg.data), "ros1" if enc == "ros1" else "cdr"
                )


def _definitions_ok(summary, f: Path) -> bool:
    """Whether an MCAP summary's schema names and channel topics are sound (not damaged).

    Names must look like ROS names; a schema name that no ROS message type has is checked
    against the data section's own record of that schema (in the first chunks).
    """
    import re

    name = re.compile(r"^[A-Za-z][A-Za-z0-9_]*/(msg/)?[A-Za-z][A-Za-z0-9_]*$")
    topic = re.compile(r"^/?[A-Za-z0-9_~/]+$")
    if not all(name.match(sc.name) for sc in summary.schemas.values()):
        return False
    if not all(topic.match(ch.topic) for ch in summary.channels.values()):
        return False
    known = set(_typestore("ros2").types) | set(_typestore("ros1").types)
    odd = {i: sc.name for i, sc in summary.schemas.items() if _ros2_name(sc.name) not in known}
    if not odd:
        return True
    seen = _data_schemas(f, set(odd))
    return all(seen.get(i, n) == n for i, n in odd.items())


def _data_schemas(f: Path, ids: set[int], chunks: int = 3) -> dict[int, str]:
    """{id: name} of the schema records ``ids`` in the data section's first ``chunks`` chunks."""
    import io
    import struct

    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Chunk, Schema

    found: dict[int, str] = {}
    try:
        with open(f, "rb") as fh:
            fh.seek(8)
            for _ in range(64):  # the header and the first chunks
                head = fh.read(9)
                if len(head) < 9:
                    break
                opcode, length = struct.unpack("<BQ", head)
                if length > MAX_RECORD_BYTES:
                    break
                body = fh.read(length)
                if opcode == Opcode.SCHEMA:
                    sc = Schema.read(ReadDataStream(io.BytesIO(body)))
                    found[sc.id] = sc.name
                elif opcode == Opcode.CHUNK:
                    for rec in _chunk_records(Chunk.read(ReadDataStream(io.BytesIO(body)))):
                        if isinstance(rec, Schema):
                            found.setdefault(rec.id, rec.name)
                    chunks -= 1
                if ids <= found.keys() or chunks <= 0:
                    break
    except Exception:  # noqa: BLE001 - a damaged data section: whatever was found
        pass
    return found


def _chunk_records(chunk, partial: bool = False, on_damage=None) -> Iterator:
    """The schema, channel and message records of an MCAP chunk, up to any damage (which raises).

    A chunk with a checksum that does not match is refused whole; one without a checksum, or
    ``partial`` (cut off: its checksum cannot match), is read up to its first broken record.
    """
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import get_chunk_data_stream

    if partial:  # what decompresses of the part before the cut
        data = chunk.data
        if chunk.compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif chunk.compression == "lz4":
            import lz4.frame

            data = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif chunk.compression:
            raise ValueError(f"a cut-off {chunk.compression} chunk cannot be decompressed")
        stream, length = ReadDataStream(io.BytesIO(data)), len(data)
    else:
        stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    readers: dict[int, Any] = {Opcode.MESSAGE: None, Opcode.CHANNEL: Channel.read, Opcode.SCHEMA: Schema.read}
    while stream.count < length:
        at = stream.count
        opcode = stream.read1()
        size = stream.read8()
        if size > length - stream.count:
            if partial:
                return  # the record the cut went through
            raise ValueError(f"a record of {size} bytes at byte {at} overruns the chunk")
        body = stream.read(size)
        if opcode not in readers:
            continue
        try:  # a record whose length holds but whose content is damaged costs only itself
            sub = ReadDataStream(io.BytesIO(body))
            read = readers[opcode]
            yield Message.read(sub, size) if read is None else read(sub)
        except Exception as exc:  # noqa: BLE001 - any damage inside the record
            if on_damage is not None:
                on_damage(
                    f"its record at byte {at} is damaged ({_short(exc)}); the chunk's other records are read"
                )


def open_log(path: str | Path) -> RobotLog:
    """Open a ROS 1 bag, a ROS 2 bag folder (or ``.db3`` file) or an MCAP file for reading.

    Raises:
        FileNotFoundError: No such log.
        ValueError: Not a log, or one whose structure cannot be read at all (the message names
            the file and what is wrong).
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such log")
    if p.is_file():
        suffix = p.suffix.lower()
        if suffix == ".mcap":
            return _McapLog(p, [p])
        if suffix == ".db3":
            return _SqliteLog(p, [p])
        return _RosbagsLog(p)
    meta = p / "metadata.yaml"
    info = _bag_metadata(meta) if meta.is_file() else None
    if info is None:  # no or a damaged metadata.yaml: the folder's storage files, in name order
        dbs, mcaps = _storage_files(p)
        if not (dbs or mcaps):
            raise ValueError(
                f"{p}: not a ROS 2 bag folder (no readable metadata.yaml, no .db3 or .mcap files)"
            )
        _warn_once(
            "%s: %s; reading the folder's %s files in name order",
            meta, "not readable" if meta.is_file() else "missing", ".db3" if dbs else ".mcap",
        )  # fmt: skip
        return _SqliteLog(p, dbs) if dbs else _McapLog(p, mcaps)
    storage, compression, files, counts = info
    if compression:  # compressed bags: rosbags decompresses them
        return _RosbagsLog(p)
    paths = [p / f for f in files]
    missing = [str(f) for f in paths if not f.is_file()]
    if missing:
        _warn_once("%s: %s named by metadata.yaml missing; reading the rest", p, ", ".join(missing))
        paths = [f for f in paths if f.is_file()]
        if not paths:
            raise ValueError(f"{p}: none of the storage files metadata.yaml names is there")
    if storage == "sqlite3":
        return _SqliteLog(p, paths, counts)
    if storage == "mcap":
        return _McapLog(p, paths)
    raise ValueError(f"{meta}: storage {storage!r} is not sqlite3 or mcap")


def _bag_metadata(meta: Path) -> tuple[str, str, list[str], dict[str, int]] | None:
    """(storage, compression mode, relative files, {topic: count}) of a ROS 2 bag, or None if unreadable."""
    import yaml

    try:
        info = yaml.safe_load(meta.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        storage = str(info["storage_identifier"])
        files = [str(f) for f in info["relative_file_paths"]]
        compression = str(info.get("compression_mode") or "")
        counts = {
            str(t["topic_metadata"]["name"]): int(t["message_count"])
            for t in info.get("topics_with_message_count") or []
        }
    except Exception:  # noqa: S110 - any damage: the caller falls back to the folder's files
        return None
    return storage, compression, files, counts


def topics(path: str | Path) -> dict[str, tuple[str, int | None]]:
    """{topic: (message type, message count or None)} of a log."""
    with open_log(path) as lg:
        return lg.topics()


#: How a user names a log's topic where the log has several of a kind (``rover odometry`` and
#: ``rover kinematics``: the option; ``rover replay``: the rig file, :func:`perception.logs.replay.load_rig`).
TOPIC_OPTION = "choose one with --topic"


def _pick(
    path: Path,
    found: dict[str, tuple[str, int | None]],
    types: tuple[str, ...],
    topic: str | None,
    what: str,
    choose: str = TOPIC_OPTION,
) -> str:
    """The topic to read: ``topic`` if given and of ``types``, else the only one of ``types``."""
    fit = [t for t, (ty, _) in found.items() if ty in types]
    if topic is not None:
        if topic not in found:
            raise ValueError(f"{path}: no topic {topic!r}; its {what} topics: {fit or 'none'}")
        if found[topic][0] not in types:
            raise ValueError(f"{path}: topic {topic!r} holds {found[topic][0]}, not {' or '.join(types)}")
        return topic
    if len(fit) == 1:
        return fit[0]
    if not fit:
        raise ValueError(f"{path}: no {what} topic ({' or '.join(types)}); topics: {sorted(found)}")
    raise ValueError(f"{path}: {len(fit)} {what} topics {sorted(fit)}; {choose}")


def _stamp(msg) -> float | None:
    """The header stamp [s], or None where it is zero (or not there)."""
    try:
        st = msg.header.stamp
        t = int(st.sec) + 1e-9 * int(st.nanosec)
    except (AttributeError, TypeError, ValueError):
        return None
    return t if t > 0 else None


# ---------------------------------------------------------------------------- images

#: Encodings of ``sensor_msgs/Image`` read as they are: (sample type, channels).
_LAYOUTS = {
    "mono8": (np.uint8, 1), "8uc1": (np.uint8, 1), "mono16": (np.uint16, 1), "16uc1": (np.uint16, 1),
    "bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3), "8uc3": (np.uint8, 3),
    "bgra8": (np.uint8, 4), "rgba8": (np.uint8, 4),
}  # fmt: skip
#: Bayer mosaics (ROS name -> OpenCV demosaicing code; OpenCV names the pattern from the second
#: row's second pixel, ROS from the first row's first, as cv_bridge maps them).
_BAYER = {
    "bayer_rggb": cv2.COLOR_BayerBG2BGR, "bayer_bggr": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg": cv2.COLOR_BayerGR2BGR, "bayer_grbg": cv2.COLOR_BayerGB2BGR,
}  # fmt: skip
#: Packed YUV 4:2:2 (two bytes a pixel): ROS's ``yuv422`` is UYVY.
_YUV = {
    "yuv422": cv2.COLOR_YUV2BGR_UYVY, "uyvy": cv2.COLOR_YUV2BGR_UYVY,
    "yuv422_yuy2": cv2.COLOR_YUV2BGR_YUYV, "yuyv": cv2.COLOR_YUV2BGR_YUYV,
}  # fmt: skip
SUPPORTED_ENCODINGS = tuple(sorted([*_LAYOUTS, *(f"{b}{n}" for b in _BAYER for n in (8, 16)), *_YUV]))


def decode_image(msg, msgtype: str) -> tuple[np.ndarray | None, str]:
    """An image message as an OpenCV array (BGR, BGRA or grey; 8 or 16 bits) and "", or None and why.

    Args:
        msg: A deserialised ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``.
        msgtype: Its type name.
    """
    if msgtype.endswith("CompressedImage"):
        data = np.frombuffer(bytes(msg.data), np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None:
            return None, f"compressed image ({msg.format!r}) does not decode"
        if img.shape[0] * img.shape[1] > MAX_MESSAGE_PIXELS:
            return None, f"{img.shape[1]}x{img.shape[0]} px is beyond the image budget"
        # image_transport's "<encoding>; png compressed ...": a compressed Bayer mosaic is demosaiced
        enc = str(msg.format).split(";")[0].strip().lower() if ";" in str(msg.format) else ""
        bayer = next((b for b in _BAYER if enc in (f"{b}8", f"{b}16")), None)
        if bayer is not None:
            if img.ndim != 2:
                return None, f"a {enc} image that decodes to {img.shape[2]} channels, not a mosaic"
            if img.shape[0] % 2 or img.shape[1] % 2:
                return None, f"a {enc} image of odd size {img.shape[1]}x{img.shape[0]} px"
            img = cv2.cvtColor(img, _BAYER[bayer])
        return img, ""
    enc = str(msg.encoding).lower()
    bayer = next((b for b in _BAYER if enc in (f"{b}8", f"{b}16")), None)
    if enc in _LAYOUTS:
        dtype, ch = _LAYOUTS[enc]
    elif bayer is not None:
        dtype, ch = (np.uint16 if enc.endswith("16") else np.uint8), 1
    elif enc in _YUV:
        dtype, ch = np.uint8, 2
    else:
        return None, (
            f"image encoding {msg.encoding!r} is not a camera image this package decodes "
            f"(supported: {', '.join(SUPPORTED_ENCODINGS)})"
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    if w * h > MAX_MESSAGE_PIXELS or w <= 0 or h <= 0:
        return None, f"{w}x{h} px is not a usable image size"
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if step < w * ch * item or data.size < step * h:
        return None, f"image data of {data.size} bytes does not hold {h} rows of {step} bytes"
    rows = data[: step * h].reshape(h, step)[:, : w * ch * item]
    img = rows.copy().view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")).astype(dtype)
    img = img.reshape(h, w, ch) if ch > 1 else img.reshape(h, w)
    if enc in _YUV and w % 2:
        return None, f"a {enc} image of odd width {w} px: packed YUV 4:2:2 pairs its pixels"
    try:
        if enc == "rgb8":
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        elif enc == "rgba8":
            img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
        elif bayer is not None:
            img = cv2.cvtColor(img, _BAYER[bayer])
        elif enc in _YUV:
            img = cv2.cvtColor(img, _YUV[enc])
    except cv2.error as exc:
        return None, f"a {enc} image of {w}x{h} px does not convert ({' '.join(str(exc).split())[:160]})"
    return img, ""


@dataclass(frozen=True)
class LogFrame:
    """One image message of a log.

    Attributes:
        index: Its number on the topic, from 0.
        stamp: Its header stamp [s] (the receive time where the stamp is zero).
        recv: The log's receive time [s].
        image: The image (BGR, BGRA or grey; 8 or 16 bits), or None.
        why: Why there is no image ("" if there is one).
    """

    index: int
    stamp: float
    recv: float
    image: np.ndarray | None
    why: str


@dataclass(frozen=True)
class LogStamp:
    """When an image message was stamped and received (no image).

    Attributes:
        index: Its number on the topic, from 0.
        stamp: Its header stamp [s] (the receive time where the stamp is zero).
        recv: The log's receive time [s].
        digest: A hash of the serialised message (equal for a message recorded twice).
    """

    index: int
    stamp: float
    recv: float
    digest: int


@dataclass(frozen=True)
class LogImages:
    """An image topic of a log: its frames in the log's order (read lazily by :meth:`frames`).

    Attributes:
        path: The log.
        topic: The image topic.
        msgtype: ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage``.
        count: Messages on the topic (None where the log does not say).
        span: How long the log lasts on its receive clock [s] (None where it does not say).
    """

    path: Path
    topic: str
    msgtype: str
    count: int | None
    span: float | None = None

    def stamps(self) -> list[LogStamp]:
        """The stamp, receive time and a digest of every image message that deserialises.

        A pass over the topic that decodes no image, for :func:`perception.logs.log_time.place` to
        see the whole stream before the images are processed.
        """
        out = []
        with open_log(self.path) as lg:
            for m in lg.messages([self.topic]):
                msg = lg.decode(m)
                if msg is None:
                    continue
                recv = 1e-9 * m.log_ns
                stamp = _stamp(msg)
                out.append(LogStamp(m.index, recv if stamp is None else stamp, recv, hash(m.data)))
        return out

    def frames(self) -> Iterator[LogFrame]:
        """Every image message that deserialises (damaged ones are skipped with a warning)."""
        with open_log(self.path) as lg:
            for m in lg.messages([self.topic]):
                msg = lg.decode(m)
                if msg is None:
                    continue
                img, why = decode_image(msg, m.msgtype)
                recv = 1e-9 * m.log_ns
                stamp = _stamp(msg)
                yield LogFrame(m.index, recv if stamp is None else stamp, recv, img, why)


def log_images(path: str | Path, topic: str | None = None, choose: str = TOPIC_OPTION) -> LogImages:
    """The image topic ``topic`` of a log (default: its only image topic; ``choose``: how to name one)."""
    p = Path(path)
    with open_log(p) as lg:
        found = lg.topics()
        name = _pick(p, found, IMAGE_TYPES, topic, "image", choose)
        return LogImages(p, name, found[name][0], found[name][1], lg.span())


#: Distortion models of ``sensor_msgs/CameraInfo`` the pinhole camera holds, and their lengths.
DISTORTION_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,)}


def camera_info(path: str | Path, image_topic: str) -> dict | None:
    """The first readable ``sensor_msgs/CameraInfo`` beside ``image_topic``, or None if the log has none.

    Beside: in the image topic's namespace, else the log's only one. Returned as
    {"image_size": (w, h), "K": (3, 3), "distortion": (5,) or (8,), "topic": name}. Damaged
    messages are skipped (with a warning).

    Raises:
        ValueError: The CameraInfo holds a distortion model the pinhole camera does not model
            (named), coefficients of the wrong number, or an impossible K; the message names the
            log and the topic.
    """
    p = Path(path)
    with open_log(p) as lg:
        found = lg.topics()
        infos = [t for t, (ty, _) in found.items() if ty == CAMERA_INFO_TYPE]
        base = image_topic
        for transport in ("/compressed", "/compressedDepth", "/theora", "/zstd"):
            base = base.removesuffix(transport)  # image_transport's topics beside the raw one
        ns = base.rsplit("/", 1)[0]
        near = [t for t in infos if t.rsplit("/", 1)[0] == ns]
        pick = near[0] if near else (infos[0] if len(infos) == 1 else None)
        if pick is None:
            return None
        for m in lg.messages([pick]):
            msg = lg.decode(m)
            if msg is None:
                continue
            where = f"{p}: {pick} (message {m.index})"
            try:
                k_, d_ = (msg.k, msg.d) if hasattr(msg, "k") else (msg.K, msg.D)  # ROS 2, ROS 1 names
                K = np.asarray(k_, dtype=np.float64).reshape(3, 3)
                dist = np.asarray(d_, dtype=np.float64).ravel()
                size = (int(msg.width), int(msg.height))
            except (AttributeError, TypeError, ValueError) as exc:
                raise ValueError(f"{where}: not a usable CameraInfo ({_short(exc)})") from None
            if not np.all(np.isfinite(dist)):
                raise ValueError(f"{where}: distortion {dist.tolist()} is not finite")
            model = str(msg.distortion_model) or ("rational_polynomial" if dist.size == 8 else "plumb_bob")
            nonzero = np.flatnonzero(dist)
            used = int(nonzero[-1]) + 1 if nonzero.size else 0  # trailing zeros carry nothing
            if used:
                if model not in DISTORTION_MODELS:
                    raise ValueError(
                        f"{where}: distortion model {model!r} is not one the pinhole camera models "
                        f"({', '.join(DISTORTION_MODELS)}); rectify the images, or give K and distortion "
                        "in the calibration file"
                    )
                if used > max(DISTORTION_MODELS[model]):
                    raise ValueError(
                        f"{where}: {model} has {' or '.join(map(str, DISTORTION_MODELS[model]))} "
                        f"coefficients, this CameraInfo {dist.size}: {dist.tolist()}"
                    )
            d = np.zeros(8 if used > 5 else 5)
            d[:used] = dist[:used]
            if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
                raise ValueError(f"{where}: K {K.tolist()} has no positive focal lengths")
            K, size = _binned(msg, K, size)
            return {"image_size": size, "K": K, "distortion": d, "topic": pick, "where": where}
    log.warning("%s: no readable CameraInfo on %s", p, pick)
    return None


def _binned(msg, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """K and the image size of the images a CameraInfo's binning and region of interest describe.

    A CameraInfo's K, width and height are the full sensor's; with binning (b_x, b_y) and a
    region of interest at (x0, y0) the published images are the region's size over the binning,
    and fx / b_x, (cx - x0) / b_x (likewise in y) their intrinsics (as ROS's image_geometry).
    """
    bx, by = (max(1, int(getattr(msg, name, 0) or 0)) for name in ("binning_x", "binning_y"))
    roi = getattr(msg, "roi", None)
    x0 = y0 = 0
    w, h = size
    if roi is not None and int(roi.width) > 0 and int(roi.height) > 0:
        x0, y0, w, h = int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)
    if (bx, by, x0, y0, w, h) == (1, 1, 0, 0, *size):
        return K, size
    K = K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    K[0] /= bx
    K[1] /= by
    return K, (w // bx, h // by)


@dataclass(frozen=True)
class _ImuSample:
    stamp: float
    recv: float
    values: tuple


def log_imu(
    path: str | Path, topic: str | None = None, choose: str = TOPIC_OPTION, flags: bool = False
) -> tuple[np.ndarray, str]:
    """(N, 7) IMU samples of a log (t [s], gyro xyz [rad/s], accel xyz [m/s^2]) and the topic.

    The times are the header stamps placed on the log's time line by
    :func:`perception.logs.log_time.place`, as the images' are: on one clock, the IMU and the camera
    share the time line whatever each of them dropped. Samples with a non-finite value or a flagged stamp, and
    damaged messages, are left out (with a warning). With ``flags``, (N, 8): an eighth column is
    1 where the sample's angular-velocity or linear-acceleration covariance starts with -1 (ROS's
    "no estimate": a clipped, saturated reading, as ``rover record`` writes one), else 0.
    """
    from perception.logs.log_time import in_stamp_order, place

    p = Path(path)
    samples, bad = [], 0
    with open_log(p) as lg:
        name = _pick(p, lg.topics(), (IMU_TYPE,), topic, "IMU", choose)
        for m in lg.messages([name]):
            msg = lg.decode(m)
            if msg is None:
                continue
            try:
                w, a = msg.angular_velocity, msg.linear_acceleration
                values = tuple(float(v) for v in (w.x, w.y, w.z, a.x, a.y, a.z))
                if flags:
                    cov = (msg.angular_velocity_covariance, msg.linear_acceleration_covariance)
                    values += (float(any(len(c) and float(c[0]) == -1.0 for c in cov)),)
                stamp = _stamp(msg)
            except (AttributeError, TypeError, ValueError):
                bad += 1
                continue
            if not all(math.isfinite(v) for v in values):
                bad += 1
                continue
            recv = 1e-9 * m.log_ns
            samples.append(_ImuSample(recv if stamp is None else stamp, recv, values))
    if bad:
        log.warning("%s: %s: %d IMU samples with non-finite values left out", p, name, bad)
    rows, flagged = [], 0
    for placed in place(in_stamp_order(samples), name=f"{p}: {name}"):
        if placed.why or not math.isfinite(placed.t):
            flagged += 1
            continue
        rows.append([placed.t, *placed.item.values])
    if flagged:
        log.warning("%s: %s: %d IMU samples with a flagged stamp left out", p, name, flagged)
    data = np.array(rows, dtype=np.float64).reshape(-1, 8 if flags else 7)
    return data[np.argsort(data[:, 0], kind="stable")], name


#: ``geometry_msgs/Vector3Stamped``: a sun sensor's direction toward the sun, and the ephemeris's.
VECTOR_TYPE = "geometry_msgs/msg/Vector3Stamped"


def log_vectors(path: str | Path, topic: str) -> np.ndarray:
    """(N, 4) ``geometry_msgs/Vector3Stamped`` samples of ``topic``: t [s] (header stamps), x, y, z.

    Damaged messages are left out (with a warning); a NaN vector is kept (a sun sensor that saw
    no sun). Sorted by time.

    Raises:
        ValueError: The log has no such topic, or it holds another type.
    """
    p = Path(path)
    rows = []
    with open_log(p) as lg:
        name = _pick(p, lg.topics(), (VECTOR_TYPE,), topic, "vector")
        for m in lg.messages([name]):
            msg = lg.decode(m)
            if msg is None:
                continue
            try:
                v = msg.vector
                stamp = _stamp(msg)
                rows.append([1e-9 * m.log_ns if stamp is None else stamp, float(v.x), float(v.y), float(v.z)])
            except (AttributeError, TypeError, ValueError):
                continue
    data = np.array(rows, dtype=np.float64).reshape(-1, 4)
    return data[np.argsort(data[:, 0], kind="stable")]


# ---------------------------------------------------------------------------- writing


class McapWriter:
    """A ROS 2 MCAP file: estimates (``nav_msgs/Odometry``, ``sensor_msgs/JointState``) and sensors.

    Use as a context manager; :meth:`odometry`, :meth:`joints`, :meth:`image`, :meth:`imu` and
    :meth:`vector` add one message each (the header stamp and the log time are the message's
    time). The file is written in a temporary folder beside ``path`` that this writer creates,
    and moved to ``path`` when it closes without an error; nothing else is touched.

    Args:
        path: The ``.mcap`` file to write (replaced at close if it exists).
        frame_id: The odometry's fixed frame (``odom``).
        child_frame_id: The body frame (``base_link``).
    """

    def __init__(self, path: str | Path, frame_id: str = "odom", child_frame_id: str = "base_link") -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self._store = get_typestore(Stores.ROS2_HUMBLE)
        self._tmp = Path(tempfile.mkdtemp(dir=self.path.parent, prefix=f".{self.path.name}."))
        self._writer = Writer(self._tmp / "bag", version=9, storage_plugin=StoragePlugin.MCAP)
        self._conns: dict[str, object] = {}
        self.count = {"odometry": 0, "joints": 0, "image": 0, "imu": 0, "vector": 0}

    def __enter__(self) -> McapWriter:
        try:
            self._writer.open()
        except Exception:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self._writer.close()
            if exc_type is None:
                files = sorted((self._tmp / "bag").glob("*.mcap"))
                if not files:
                    raise OSError(f"{self.path}: the MCAP writer produced no file")
                files[0].replace(self.path)
        except OSError as err:
            if exc_type is None:
                raise OSError(f"{self.path}: cannot write ({err.strerror or err})") from None
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)  # this writer's own folder

    def _conn(self, topic: str, msgtype: str):
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        return self._conns[topic]

    def _header(self, t: float, frame_id: str):
        T = self._store.types
        sec = math.floor(t)
        stamp = T["builtin_interfaces/msg/Time"](
            sec=int(sec), nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000
        )
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def odometry(self, t: float, pose, twist, twist_cov=None, topic: str = "/odometry") -> None:
        """One ``nav_msgs/Odometry`` at ``t`` [s].

        Args:
            t: Time [s] (the header stamp and the log time).
            pose: (x, y, yaw) in the odometry frame [m, m, rad] (planar: z, roll, pitch 0).
            twist: (v_x, v_y, omega) in the body frame [m/s, m/s, rad/s] (NaN: unknown, written
                with an infinite variance).
            twist_cov: (3, 3) covariance of the twist, if known.
            topic: The topic.
        """
        T = self._store.types
        x, y, yaw = (float(v) for v in pose)
        vx, vy, wz = (float(v) for v in twist)
        known = all(math.isfinite(v) for v in (vx, vy, wz))
        tc = np.full(36, 0.0)
        if not known:
            vx = vy = wz = 0.0
            tc[[0, 7, 35]] = np.inf
        elif twist_cov is not None:
            C = np.asarray(twist_cov, dtype=np.float64)
            for i, a in enumerate((0, 1, 5)):
                for j, b in enumerate((0, 1, 5)):
                    tc[6 * a + b] = C[i, j]
        q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
        p = T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0)
        pose = T["geometry_msgs/msg/Pose"](position=p, orientation=q)
        pose_msg = T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
        V3 = T["geometry_msgs/msg/Vector3"]
        tw = T["geometry_msgs/msg/Twist"](linear=V3(x=vx, y=vy, z=0.0), angular=V3(x=0.0, y=0.0, z=wz))
        msg = T["nav_msgs/msg/Odometry"](
            header=self._header(t, self.frame_id),
            child_frame_id=self.child_frame_id,
            pose=pose_msg,
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=tw, covariance=tc),
        )
        self._write(topic, "nav_msgs/msg/Odometry", msg, t)
        self.count["odometry"] += 1

    def joints(self, t: float, names, position, velocity=None, topic: str = "/joint_states") -> None:
        """One ``sensor_msgs/JointState`` at ``t`` [s] (NaN where a joint was not measured)."""
        T = self._store.types
        pos = np.asarray(position, dtype=np.float64)
        vel = np.zeros(0) if velocity is None else np.asarray(velocity, dtype=np.float64)
        msg = T["sensor_msgs/msg/JointState"](
            header=self._header(t, self.child_frame_id), name=list(names), position=pos, velocity=vel,
            effort=np.zeros(0),
        )  # fmt: skip
        self._write(topic, "sensor_msgs/msg/JointState", msg, t)
        self.count["joints"] += 1

    def image(
        self,
        t: float,
        rgb: np.ndarray,
        topic: str,
        frame_id: str,
        mosaic: np.ndarray | None = None,
        compress: bool = True,
    ) -> None:
        """One camera frame at ``t`` [s]: ``sensor_msgs/CompressedImage`` (PNG, lossless) or ``Image``.

        Args:
            t: Time [s].
            rgb: The (H, W, 3) uint8 RGB image.
            topic: The topic.
            frame_id: The camera's frame.
            mosaic: The (H, W) uint8 RGGB Bayer mosaic ``rgb`` was demosaiced from (OpenCV's
                bilinear demosaicing); written in its place (``bayer_rggb8``: a third of the bytes,
                demosaiced again into the same image), or None.
            compress: PNG-compress it (image_transport's format ``"<encoding>; png compressed
                <encoding>"``); False: a raw ``sensor_msgs/Image``.
        """
        T = self._store.types
        img, enc = (mosaic, "bayer_rggb8") if mosaic is not None else (rgb, "rgb8")
        if compress:
            ok, buf = cv2.imencode(".png", img if mosaic is not None else img[..., ::-1])
            if not ok:  # pragma: no cover - OpenCV encodes any 8-bit image
                raise ValueError(f"{topic}: a {img.shape} image does not encode as PNG")
            fmt = f"{enc}; png compressed {enc if mosaic is not None else 'bgr8'}"
            msg = T["sensor_msgs/msg/CompressedImage"](
                header=self._header(t, frame_id), format=fmt, data=buf.ravel()
            )
            self._write(topic, "sensor_msgs/msg/CompressedImage", msg, t)
        else:
            h, w = img.shape[:2]
            ch = 1 if img.ndim == 2 else img.shape[2]
            msg = T["sensor_msgs/msg/Image"](
                header=self._header(t, frame_id), height=h, width=w, encoding=enc, is_bigendian=0,
                step=w * ch, data=np.ascontiguousarray(img).ravel(),
            )  # fmt: skip
            self._write(topic, "sensor_msgs/msg/Image", msg, t)
        self.count["image"] += 1

    def imu(self, t: float, gyro, accel, topic: str, frame_id: str, saturated: bool = False) -> None:
        """One ``sensor_msgs/Imu`` at ``t`` [s]: gyro [rad/s] and accelerometer [m/s^2] in its frame.

        It has no orientation (its covariance starts with -1); a ``saturated`` sample (a reading
        clipped at the range) has -1 at the start of both other covariances too.
        """
        T = self._store.types
        V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        no = np.zeros(9)
        no[0] = -1.0
        flag = no if saturated else np.zeros(9)
        g, a = (float(v) for v in gyro), (float(v) for v in accel)
        msg = T["sensor_msgs/msg/Imu"](
            header=self._header(t, frame_id), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=no, angular_velocity=V3(*g), angular_velocity_covariance=flag,
            linear_acceleration=V3(*a), linear_acceleration_covariance=flag.copy(),
        )  # fmt: skip
        self._write(topic, "sensor_msgs/msg/Imu", msg, t)
        self.count["imu"] += 1

    def vector(self, t: float, v, topic: str, frame_id: str) -> None:
        """One ``geometry_msgs/Vector3Stamped`` at ``t`` [s] (NaN components are kept)."""
        T = self._store.types
        x, y, z = (float(c) for c in v)
        msg = T["geometry_msgs/msg/Vector3Stamped"](
            header=self._header(t, frame_id), vector=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)
        )
        self._write(topic, VECTOR_TYPE, msg, t)
        self.count["vector"] += 1

    def _write(self, topic: str, msgtype: str, msg, t: float) -> None:
        conn = self._conn(topic, msgtype)
        data = self._store.serialize_cdr(msg, msgtype)
        try:
            self._writer.write(conn, max(0, int(round(t * 1e9))), data)
        except OSError as exc:
            raise OSError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
