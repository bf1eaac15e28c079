"""Writers the tests use to lay a KITTI sequence out as another recording format: a ROS 2 bag
(MCAP or sqlite3), a ROS 1 bag (both through `rosbags`' own writers and serialisers) and a KITTI
raw drive. The readers under test never see this code."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from d3lvo_deploy.geometry import rot_to_quat


def _msgs(ts, ros1: bool):
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]

    def header(t: float, frame: str):
        stamp = Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        return Header(seq=0, stamp=stamp, frame_id=frame) if ros1 else Header(stamp=stamp, frame_id=frame)

    return T, header


def _messages(ts, ros1: bool, seq, frames, image_frame: str, lidar_frame: str, compressed: bool, stamp_offset: float,
              tf: bool, info: bool, dropped: str | None, info_size: tuple[int, int] | None = None,
              second_info: bool = False):
    """(topic, msgtype, message, time s) for the sequence, in time order."""
    T, header = _msgs(ts, ros1)
    out = []
    P = seq.calib.P2
    K = P[:, :3]
    t0 = 1_700_000_000.0
    if tf:
        Tr = seq.calib.Tr  # lidar -> camera frame: written as the transform parent=camera, child=lidar
        q = rot_to_quat(Tr[:3, :3])  # w, x, y, z
        tfm = T["geometry_msgs/msg/TransformStamped"](
            header=header(t0, image_frame), child_frame_id=lidar_frame,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=Tr[0, 3], y=Tr[1, 3], z=Tr[2, 3]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0])))
        out.append(("/tf_static", "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=[tfm]), t0))
    for i in frames:
        t = t0 + float(seq.times[i])
        rgb = seq.image(i)
        h, w = rgb.shape[:2]
        if info:
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            mats = dict(d=np.zeros(5), k=K.reshape(-1).astype(np.float64), r=np.eye(3).reshape(-1),
                        p=P.reshape(-1).astype(np.float64))
            if ros1:  # ROS 1 spells them D, K, R, P
                mats = {k.upper(): v for k, v in mats.items()}
            iw, ih = info_size if info_size is not None else (w, h)
            cam_info = T["sensor_msgs/msg/CameraInfo"](
                header=header(t, image_frame), height=ih, width=iw, distortion_model="plumb_bob",
                binning_x=0, binning_y=0, roi=roi, **mats)
            out.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", cam_info, t))
            if second_info:  # another camera's, e.g. a second camera that was not recorded
                out.append(("/camera2/camera_info", "sensor_msgs/msg/CameraInfo", cam_info, t))
        if dropped != "image":
            if compressed:
                ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
                msg = T["sensor_msgs/msg/CompressedImage"](header=header(t, image_frame), format="png",
                                                           data=np.frombuffer(png.tobytes(), np.uint8))
                out.append(("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", msg, t))
            else:
                msg = T["sensor_msgs/msg/Image"](header=header(t, image_frame), height=h, width=w, encoding="rgb8",
                                                 is_bigendian=0, step=3 * w,
                                                 data=np.ascontiguousarray(rgb).reshape(-1))
                out.append(("/camera/image_raw", "sensor_msgs/msg/Image", msg, t))
        if dropped != "cloud":
            scan = seq.scan(i)
            F = T["sensor_msgs/msg/PointField"]
            fields = [F(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate(("x", "y", "z", "intensity"))]
            tc = t + stamp_offset
            cloud = T["sensor_msgs/msg/PointCloud2"](
                header=header(tc, lidar_frame), height=1, width=len(scan), fields=fields, is_bigendian=False,
                point_step=16, row_step=16 * len(scan), data=scan.astype(np.float32).view(np.uint8).reshape(-1),
                is_dense=True)
            out.append(("/velodyne_points", "sensor_msgs/msg/PointCloud2", cloud, tc))
    return sorted(out, key=lambda m: m[3])


def write_ros2_bag(seq, out: Path, storage: str = "mcap", frames=None, edit=None, **kw) -> Path:
    """`edit`: a function that changes the messages (a list of `_messages`' tuples) before writing."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    msgs = _messages(ts, False, seq, range(len(seq)) if frames is None else frames, **_defaults(kw))
    if edit is not None:
        edit(msgs)
    with Writer(out, version=9, storage_plugin=plugin) as w:
        _write(w, ts, msgs, ts.serialize_cdr)
    return out


def _write(writer, ts, msgs, serialize) -> None:
    conns = {}
    for topic, mtype, msg, t in msgs:
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, mtype, typestore=ts)
        writer.write(conns[topic], int(t * 1e9), serialize(msg, mtype))


def write_ros1_bag(seq, out: Path, frames=None, **kw) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # noetic's store lacks it; its one-line definition
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    msgs = _messages(ts, True, seq, range(len(seq)) if frames is None else frames, **_defaults(kw))
    with Writer(out) as w:
        _write(w, ts, msgs, ts.serialize_ros1)
    return out


def _defaults(kw: dict) -> dict:
    d = dict(image_frame="camera", lidar_frame="velodyne", compressed=False, stamp_offset=0.004, tf=True, info=True,
             dropped=None)
    d.update(kw)
    return d


def write_kitti_raw(seq, date_dir: Path, drive: str = "2011_09_26_drive_0001_sync") -> Path:
    """The date folder's calib files (R_rect_00 = I, so Tr = [R|T] = the sequence's Tr) and the
    drive's image_02/data, velodyne_points/data and timestamps."""
    d = date_dir / drive
    (d / "image_02" / "data").mkdir(parents=True)
    (d / "velodyne_points" / "data").mkdir(parents=True)

    def row(m):
        return " ".join(f"{v:.12e}" for v in np.asarray(m).reshape(-1))

    P2, Tr = seq.calib.P2, seq.calib.Tr
    (date_dir / "calib_cam_to_cam.txt").write_text(
        f"calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\nR_rect_00: {row(np.eye(3))}\n"
        f"P_rect_00: {row(P2 * 0 + np.hstack([P2[:, :3], np.zeros((3, 1))]))}\nP_rect_02: {row(P2)}\n")
    (date_dir / "calib_velo_to_cam.txt").write_text(
        f"calib_time: 15-Mar-2012 11:37:16\nR: {row(Tr[:3, :3])}\nT: {row(Tr[:3, 3])}\n"
        "delta_f: 0.000000e+00 0.000000e+00\ndelta_c: 0.000000e+00 0.000000e+00\n")
    stamps = []
    for i in range(len(seq)):
        name = f"{i:010d}"
        (d / "image_02" / "data" / f"{name}.png").write_bytes(seq.image_path(i).read_bytes())
        (d / "velodyne_points" / "data" / f"{name}.bin").write_bytes(seq.scan_path(i).read_bytes())
        t = float(seq.times[i])
        stamps.append(f"2011-09-26 13:02:{25 + int(t):02d}.{int(round((t % 1) * 1e9)):09d}")
    (d / "image_02" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    return d


def write_scan_folder(seq, out: Path, ext: str) -> Path:
    """images/ + scans/ in `ext` (.pcd via pypcd4, .ply via plyfile, .npy via numpy), calib.txt as
    K + T_cam_lidar of the image_2 camera (so poses come out in that camera's frame), times.txt."""
    (out / "images").mkdir(parents=True)
    (out / "scans").mkdir()
    for i in range(len(seq)):
        name = f"{i:06d}"
        (out / "images" / f"{name}.png").write_bytes(seq.image_path(i).read_bytes())
        scan = seq.scan(i)
        p = out / "scans" / f"{name}{ext}"
        if ext == ".pcd":
            from pypcd4 import PointCloud

            PointCloud.from_xyzi_points(scan).save(p)
        elif ext == ".ply":
            from plyfile import PlyData, PlyElement

            v = np.empty(len(scan), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")])
            for k, n in enumerate(("x", "y", "z", "intensity")):
                v[n] = scan[:, k]
            PlyData([PlyElement.describe(v, "vertex")]).write(str(p))
        else:
            np.save(p, scan)
    K = seq.calib.K2
    T = seq.calib.T_cam2_velo

    def row(m):
        return " ".join(repr(float(v)) for v in np.asarray(m).reshape(-1))

    (out / "calib.txt").write_text(f"K: {row(K)}\nT_cam_lidar: {row(T[:3])}\n")
    (out / "times.txt").write_text("".join(f"{t:.6f}\n" for t in seq.times))
    return out


def bag_twin(seq, out: Path):
    """The sequence as a KITTI folder whose Tr is what a bag can carry: its rotation through a unit
    quaternion (/tf_static), so that a bag run and this folder's run see the same calibration.
    Images and scans are links to the originals."""
    from d3lvo_deploy.geometry import quat_to_rot
    from d3lvo_deploy.sequence import KittiSequence

    out.mkdir(parents=True)
    for sub in ("image_2", "velodyne"):
        (out / sub).symlink_to((seq.root / sub).resolve())
    Tr = seq.calib.Tr.copy()
    Tr[:3, :3] = quat_to_rot(rot_to_quat(Tr[:3, :3]))
    rows = [f"{k}: " + " ".join(repr(float(v)) for v in np.asarray(m).reshape(-1))
            for k, m in (("P0", seq.calib.P0 if seq.calib.P0 is not None else seq.calib.P2), ("P2", seq.calib.P2),
                         ("Tr", Tr[:3]))]
    (out / "calib.txt").write_text("\n".join(rows) + "\n")
    if (seq.root / "times.txt").is_file():
        (out / "times.txt").write_bytes((seq.root / "times.txt").read_bytes())
    return KittiSequence.open(out)
