"""Camera and IMU streams from robot logs: ROS 1 bags, ROS 2 bag folders and MCAP files.

Read with the ``rosbags`` library (pure Python, no ROS installation). Messages:

- ``sensor_msgs/Image`` (encodings mono8, mono16, 8UC1, 16UC1, rgb8, bgr8, rgba8, bgra8, 8UC3)
  and ``sensor_msgs/CompressedImage`` (any format OpenCV decodes: JPEG, PNG, ...);
- ``sensor_msgs/CameraInfo``: the intrinsics (K, plumb-bob distortion, image size);
- ``sensor_msgs/Imu``: angular velocity [rad/s] and linear acceleration [m/s^2].

Times are the messages' header stamps [s] (the bag's receive time where a stamp is zero), so
no frame rate is needed. Writers of ``nav_msgs/Odometry`` and ``sensor_msgs/JointState`` into an
MCAP file (ROS 2 CDR, playable by Foxglove and ``ros2 bag play``) are at the end.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
IMU_TYPE = "sensor_msgs/msg/Imu"
#: Most pixels of one image message (the same budget as image files).
MAX_MESSAGE_PIXELS = 8192 * 8192


def is_log(path: str | Path) -> bool:
    """Whether ``path`` is a robot log: a ``.bag`` (ROS 1) or ``.mcap`` file, or a ROS 2 bag folder."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in (".bag", ".mcap", ".db3")
    return p.is_dir() and (p / "metadata.yaml").is_file()


def _reader(path: Path):
    """An open-able rosbags reader of ``path`` (ValueError naming it if it is not a log)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not (path.exists()):
        raise FileNotFoundError(f"{path}: no such log")
    store = get_typestore(Stores.ROS2_HUMBLE)
    return AnyReader([path], default_typestore=store)


def _open(path: Path):
    reader = _reader(path)
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own errors for every kind of damage
        raise ValueError(f"{path}: not a readable ROS 1 bag, ROS 2 bag or MCAP file ({exc})") from None
    return reader


def topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} of a log."""
    reader = _open(Path(path))
    try:
        out: dict[str, tuple[str, int]] = {}
        for c in reader.connections:
            n = out.get(c.topic, (c.msgtype, 0))[1] + c.msgcount
            out[c.topic] = (c.msgtype, n)
        return out
    finally:
        reader.close()


def _pick(
    path: Path, found: dict[str, tuple[str, int]], types: tuple[str, ...], topic: str | None, what: str
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
    raise ValueError(f"{path}: {len(fit)} {what} topics {sorted(fit)}; choose one with --topic")


def _stamp(msg, bag_ns: int) -> float:
    """The header stamp [s], or the bag's time where the stamp is zero."""
    st = msg.header.stamp
    t = int(st.sec) + 1e-9 * int(st.nanosec)
    return t if t > 0 else 1e-9 * bag_ns


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
        return img, ""
    enc = str(msg.encoding).lower()
    layouts = {
        "mono8": (np.uint8, 1), "8uc1": (np.uint8, 1), "mono16": (np.uint16, 1), "16uc1": (np.uint16, 1),
        "bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3), "8uc3": (np.uint8, 3),
        "bgra8": (np.uint8, 4), "rgba8": (np.uint8, 4),
    }  # fmt: skip
    if enc not in layouts:
        return None, f"image encoding {msg.encoding!r} is not one of {sorted(layouts)}"
    dtype, ch = layouts[enc]
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
    if enc == "rgb8":
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif enc == "rgba8":
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    return img, ""


@dataclass(frozen=True)
class LogImages:
    """An image topic of a log: its frames in time order (read lazily by :meth:`frames`).

    Attributes:
        path: The log.
        topic: The image topic.
        msgtype: ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage``.
        count: Messages on the topic.
    """

    path: Path
    topic: str
    msgtype: str
    count: int

    def frames(self) -> Iterator[tuple[float, np.ndarray | None, str]]:
        """(time [s], image or None, why not) per message, in the order of the log."""
        reader = _open(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for conn, bag_ns, raw in reader.messages(connections=conns):
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:  # a damaged message: flagged, the run goes on
                    yield math.nan, None, f"message at {1e-9 * bag_ns:.6f} s does not deserialise ({exc})"
                    continue
                img, why = decode_image(msg, conn.msgtype)
                yield _stamp(msg, bag_ns), img, why
        finally:
            reader.close()


def log_images(path: str | Path, topic: str | None = None) -> LogImages:
    """The image topic ``topic`` of a log (default: its only image topic)."""
    p = Path(path)
    found = topics(p)
    name = _pick(p, found, IMAGE_TYPES, topic, "image")
    return LogImages(p, name, found[name][0], found[name][1])


def camera_info(path: str | Path, image_topic: str) -> dict | None:
    """The first ``sensor_msgs/CameraInfo`` beside ``image_topic``, or None if the log has none.

    Beside: in the image topic's namespace, else the log's only one. Returned as
    {"image_size": (w, h), "K": (3, 3), "distortion": (5,), "topic": name}.
    """
    p = Path(path)
    found = topics(p)
    infos = [t for t, (ty, _) in found.items() if ty == CAMERA_INFO_TYPE]
    ns = image_topic.rsplit("/", 1)[0]
    near = [t for t in infos if t.rsplit("/", 1)[0] == ns]
    pick = near[0] if near else (infos[0] if len(infos) == 1 else None)
    if pick is None:
        return None
    reader = _open(p)
    try:
        conns = [c for c in reader.connections if c.topic == pick]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            k_, d_ = (msg.k, msg.d) if hasattr(msg, "k") else (msg.K, msg.D)  # ROS 2, ROS 1 names
            K = np.asarray(k_, dtype=np.float64).reshape(3, 3)
            d = np.zeros(5)
            dist = np.asarray(d_, dtype=np.float64)
            if str(msg.distortion_model) not in ("plumb_bob", "rational_polynomial", "") and dist.any():
                raise ValueError(f"{p}: {pick}: distortion model {msg.distortion_model!r}; use plumb_bob")
            d[: min(5, dist.size)] = dist[:5]
            if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
                raise ValueError(f"{p}: {pick}: K {K.tolist()} has no positive focal lengths")
            return {"image_size": (int(msg.width), int(msg.height)), "K": K, "distortion": d, "topic": pick}
    finally:
        reader.close()
    return None


def log_imu(path: str | Path, topic: str | None = None) -> tuple[np.ndarray, str]:
    """(N, 7) IMU samples of a log (t [s], gyro xyz [rad/s], accel xyz [m/s^2]) and the topic.

    Samples with a non-finite value are left out (and counted in the log's warning).
    """
    p = Path(path)
    found = topics(p)
    name = _pick(p, found, (IMU_TYPE,), topic, "IMU")
    reader = _open(p)
    rows, bad = [], 0
    try:
        conns = [c for c in reader.connections if c.topic == name]
        for conn, bag_ns, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            w, a = m.angular_velocity, m.linear_acceleration
            row = [_stamp(m, bag_ns), w.x, w.y, w.z, a.x, a.y, a.z]
            if all(math.isfinite(v) for v in row):
                rows.append(row)
            else:
                bad += 1
    finally:
        reader.close()
    if bad:
        log.warning("%s: %s: %d IMU samples with non-finite values left out", p, name, bad)
    data = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return data[np.argsort(data[:, 0], kind="stable")], name


# ---------------------------------------------------------------------------- writing


class McapWriter:
    """A ROS 2 MCAP file of ``nav_msgs/Odometry`` and ``sensor_msgs/JointState`` messages.

    Use as a context manager; :meth:`odometry` and :meth:`joints` add one message each.

    Args:
        path: The ``.mcap`` file to write (replaced if it exists).
        frame_id: The odometry's fixed frame (``odom``).
        child_frame_id: The body frame (``base_link``).
    """

    def __init__(self, path: str | Path, frame_id: str = "odom", child_frame_id: str = "base_link") -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self._store = get_typestore(Stores.ROS2_HUMBLE)
        self._dir = self.path.with_suffix("")  # rosbags writes a bag folder; the .mcap is moved out
        for old in (self._dir, self.path):
            if old.is_dir():
                import shutil

                shutil.rmtree(old)
            elif old.exists():
                old.unlink()
        self._writer = Writer(self._dir, version=9, storage_plugin=StoragePlugin.MCAP)
        self._conns: dict[str, object] = {}
        self.count = {"odometry": 0, "joints": 0}

    def __enter__(self) -> McapWriter:
        self._writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()
        files = sorted(self._dir.glob("*.mcap"))
        if files:
            files[0].replace(self.path)
        import shutil

        shutil.rmtree(self._dir, ignore_errors=True)

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

    def _write(self, topic: str, msgtype: str, msg, t: float) -> None:
        conn = self._conn(topic, msgtype)
        data = self._store.serialize_cdr(msg, msgtype)
        self._writer.write(conn, max(0, int(round(t * 1e9))), data)
