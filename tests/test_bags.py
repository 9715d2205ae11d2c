"""Robot logs: ROS 1 bags, ROS 2 bags and MCAP files written with rosbags from rendered frames, run
through ``rover odometry`` and ``rover kinematics``, against the truth the frames were made from."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Ros1Writer  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Ros2Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from test_markers import fisheye, render_markers, rover_model  # noqa: E402
from test_odometry import START, make_ground, mast_camera, pose_after, render  # noqa: E402

from perception.logs import bags  # noqa: E402
from rover_env.tools.cli import main  # noqa: E402

T0 = 1_700_000_000.25  # stamps of a real log: seconds since 1970
TWIST, FPS, N = (1.2, 0.1, 0.3), 60.0, 16


class LogWriter:
    """One log of any of the three kinds, with a stamp per message."""

    def __init__(self, path: Path, kind: str, compression: str | None = None) -> None:
        self.kind, self.path = kind, path
        self.store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
        if kind == "ros1":
            self.w = Ros1Writer(path)
            if compression:  # "bz2" or "lz4" chunks
                self.w.set_compression(Ros1Writer.CompressionFormat[compression.upper()])
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.w = Ros2Writer(
                path if kind == "ros2" else path.with_suffix(""), version=9, storage_plugin=plugin
            )
        self.conns: dict = {}

    def __enter__(self):
        self.w.open()
        return self

    def __exit__(self, *exc):
        self.w.close()
        if self.kind == "mcap":  # a bare .mcap file, as recorders and Foxglove write them
            folder = self.path.with_suffix("")
            next(folder.glob("*.mcap")).replace(self.path)

    def header(self, t):
        T = self.store.types
        sec = int(math.floor(t))
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))
        extra = {"seq": 0} if self.kind == "ros1" else {}
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id="camera", **extra)

    def write(self, topic, msgtype, msg, t):
        ser = self.store.serialize_ros1 if self.kind == "ros1" else self.store.serialize_cdr
        self.write_raw(topic, msgtype, ser(msg, msgtype), t)

    def write_raw(self, topic, msgtype, data, t):
        """Bytes as a message of ``msgtype`` received at ``t`` (a damaged message, if they are garbage)."""
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.store)
        self.w.write(self.conns[topic], int(round(t * 1e9)), bytes(data))

    def image(self, topic, t, img, encoding=None, compressed=None, stamp=None):
        """An image received at ``t`` [s] with the header stamp ``stamp`` (default ``t``)."""
        T = self.store.types
        stamp = t if stamp is None else stamp
        if compressed:
            ok, buf = cv2.imencode(f".{compressed}", img)
            assert ok
            msg = T["sensor_msgs/msg/CompressedImage"](
                header=self.header(stamp), format=compressed, data=buf.ravel()
            )
            self.write(topic, "sensor_msgs/msg/CompressedImage", msg, t)
            return
        h, w = img.shape[:2]
        ch = 1 if img.ndim == 2 else img.shape[2]
        msg = T["sensor_msgs/msg/Image"](
            header=self.header(stamp), height=h, width=w, encoding=encoding, is_bigendian=0,
            step=w * ch * img.itemsize, data=np.ascontiguousarray(img).view(np.uint8).ravel(),
        )  # fmt: skip
        self.write(topic, "sensor_msgs/msg/Image", msg, t)

    def camera_info(self, topic, t, cam, model="plumb_bob", K=None):
        T = self.store.types
        w, h = cam.image_size
        names = {
            "k": (cam.K if K is None else np.asarray(K, dtype=np.float64)).ravel(),
            "d": np.asarray(cam.distortion),
            "r": np.eye(3).ravel(),
            "p": np.zeros(12),
        }
        if self.kind == "ros1":
            names = {k.upper(): v for k, v in names.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        msg = T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t), height=h, width=w, distortion_model=model, binning_x=0, binning_y=0,
            roi=roi, **names,
        )  # fmt: skip
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, t)

    def imu(self, topic, t, gyro, accel):
        T = self.store.types
        V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        z9 = np.zeros(9)
        msg = T["sensor_msgs/msg/Imu"](
            header=self.header(t),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=z9,
            angular_velocity=V3(x=gyro[0], y=gyro[1], z=gyro[2]),
            angular_velocity_covariance=z9,
            linear_acceleration=V3(x=accel[0], y=accel[1], z=accel[2]),
            linear_acceleration_covariance=z9,
        )
        self.write(topic, "sensor_msgs/msg/Imu", msg, t)


@pytest.fixture(scope="module")
def frames():
    ground = make_ground()
    pose, out = START, []
    for k in range(N):
        if k:
            pose = pose_after(pose, TWIST, 1 / FPS)
        out.append(render(mast_camera(), ground, pose, rng=np.random.default_rng(k)))
    return out


def _odometry_messages(path: Path) -> int:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        return sum(
            1 for schema, _, _ in make_reader(fh).iter_messages() if schema.name == "nav_msgs/msg/Odometry"
        )


@pytest.mark.parametrize(
    ("kind", "name", "how"),
    [("ros1", "drive.bag", "mono8"), ("ros2", "drive_ros2", "png"), ("mcap", "drive.mcap", "mono8")],
)
def test_rover_odometry_reads_ros1_ros2_and_mcap_logs(tmp_path, frames, kind, name, how):
    cam = mast_camera()
    log_path = tmp_path / name
    with LogWriter(log_path, kind) as lw:
        for k, img in enumerate(frames):
            t = T0 + k / FPS
            if how == "png":
                lw.image("/down/image_raw/compressed", t, img, compressed="png")
            else:
                lw.image("/down/image_raw", t, img, encoding=how)
            lw.camera_info("/down/camera_info", t, cam)
        for j in range(int((N / FPS + 0.1) * 200)):  # a gyro at 200 Hz with a 0.01 rad/s bias
            t = T0 - 0.05 + j / 200
            lw.imu("/imu/data", t, (0.0, 0.0, TWIST[2] + 0.01), (0.0, 0.0, 9.81))
        lw.image("/other/image", T0, frames[0], encoding="mono8")  # a second image topic
    assert bags.is_log(log_path)
    # intrinsics from the log's CameraInfo: the calibration holds only the mount and the ground
    calib = yaml.safe_load(cam.save(tmp_path / "full.yaml").read_text())
    (tmp_path / "mount.yaml").write_text(
        yaml.safe_dump({k: calib[k] for k in ("T_body_cam", "ground_plane")})
    )
    topic = "/down/image_raw/compressed" if how == "png" else "/down/image_raw"
    out = tmp_path / "out"
    argv = ["odometry", str(log_path), "--calib", str(tmp_path / "mount.yaml"), "--out", str(out)]
    assert main(argv) == 2  # two image topics: --topic chooses
    assert main([*argv, "--topic", topic, "--imu-topic", "/imu/data"]) == 0
    rows = np.genfromtxt(out / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert len(rows) == N - 1 and rows["valid"].all()
    np.testing.assert_allclose(rows["t"], T0 + np.arange(1, N) / FPS, atol=1e-6, rtol=0)  # the stamps
    np.testing.assert_allclose(rows["v_x"], TWIST[0], rtol=0.01)
    np.testing.assert_allclose(rows["omega"], TWIST[2], atol=math.radians(0.5))
    np.testing.assert_allclose(rows["omega_imu"], TWIST[2], atol=1e-3)  # the bias fitted and taken out
    assert (out / "trajectory_imu.tum").is_file()
    assert _odometry_messages(out / "odometry.mcap") == N - 1  # one nav_msgs/Odometry per estimate
    # and they decode (with the message definitions the file carries) to the CSV's numbers
    from rosbags.highlevel import AnyReader

    with AnyReader([out / "odometry.mcap"], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages()]
    np.testing.assert_allclose([m.twist.twist.linear.x for m in msgs], rows["v_x"], atol=1e-6)
    np.testing.assert_allclose(
        [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs], rows["t"], atol=1e-6
    )
    assert msgs[0].header.frame_id == "odom" and msgs[0].child_frame_id == "base_link"


@pytest.mark.parametrize(
    ("kind", "name", "how"),
    [("ros1", "fisheye.bag", "rgb8"), ("ros2", "fisheye_ros2", "png"), ("mcap", "fisheye.mcap", "bgr8")],
)
def test_rover_kinematics_reads_ros1_ros2_and_mcap_logs_and_writes_joint_states(tmp_path, kind, name, how):
    from mcap.reader import make_reader

    model = rover_model()
    cam = fisheye(model)
    psis = [(0.02 * k, -0.01 * k) for k in range(4)]
    path = tmp_path / name
    with LogWriter(path, kind) as lw:
        for k, psi in enumerate(psis):
            rgb = render_markers(model, cam, psi, (0.15, 0.15), model.wheel_angles(0.1, -0.1))
            t = T0 + k / 30
            if how == "png":
                lw.image(
                    "/fisheye/image_raw/compressed", t, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), compressed="png"
                )
            elif how == "bgr8":
                lw.image("/fisheye/image_raw", t, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), encoding="bgr8")
            else:
                lw.image("/fisheye/image_raw", t, rgb, encoding="rgb8")
    out = tmp_path / "out"
    argv = ["kinematics", str(path), "--camera", str(cam.save(tmp_path / "omni.yaml"))]
    argv += ["--rover", str(model.save(tmp_path / "rover.yaml")), "--out", str(out)]
    assert main(argv) == 0
    rows = np.genfromtxt(out / "kinematics.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert len(rows) == 4
    np.testing.assert_allclose(rows["t"], T0 + np.arange(4) / 30, atol=1e-6, rtol=0)
    np.testing.assert_allclose(rows["psi_F"], [p[0] for p in psis], atol=math.radians(0.2))
    np.testing.assert_allclose(rows["psi_R"], [p[1] for p in psis], atol=math.radians(0.2))
    with open(out / "kinematics.mcap", "rb") as fh:
        msgs = [m for s, _, m in make_reader(fh).iter_messages() if s.name == "sensor_msgs/msg/JointState"]
    assert len(msgs) == 4


def test_a_log_without_the_topic_or_fps_for_a_folder_is_a_one_line_error(tmp_path, capsys):
    path = tmp_path / "empty.bag"
    with LogWriter(path, "ros1") as lw:
        lw.imu("/imu/data", T0, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
    calib = mast_camera().save(tmp_path / "calib.yaml")
    assert main(["odometry", str(path), "--calib", str(calib), "--out", str(tmp_path / "o")]) == 2
    assert "no image topic" in capsys.readouterr().err
    assert (
        main(
            [
                "odometry",
                str(path),
                "--calib",
                str(calib),
                "--topic",
                "/imu/data",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "holds sensor_msgs/msg/Imu" in capsys.readouterr().err
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    assert (
        main(["odometry", str(tmp_path / "junk.bag"), "--calib", str(calib), "--out", str(tmp_path / "o")])
        == 2
    )
    assert "not a readable ROS 1 bag" in capsys.readouterr().err
    (tmp_path / "imgs").mkdir()
    assert (
        main(["odometry", str(tmp_path / "imgs"), "--calib", str(calib), "--out", str(tmp_path / "o")]) == 2
    )
    assert "needs --fps" in capsys.readouterr().err


def test_a_calibration_without_a_ground_plane_says_how_to_measure_it(tmp_path, capsys):
    import yaml

    data = yaml.safe_load(mast_camera().save(tmp_path / "calib.yaml").read_text())
    del data["ground_plane"]
    (tmp_path / "noplane.yaml").write_text(yaml.safe_dump(data))
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.zeros((480, 640), np.uint8))
    argv = ["odometry", str(tmp_path / "imgs"), "--calib", str(tmp_path / "noplane.yaml"), "--fps", "30"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "ground_plane: not set" in err and "[0, 0, -h]" in err and "measure" in err
