"""Write a stereo ROS bag from a dataset with rosbags' own writers (test helper)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from conftest import need_extra


def write_stereo_bag(
    path: Path,
    seq,
    kind: str = "mcap",
    compressed: bool = False,
    encoding: str = "mono8",
    prefix: str = "/stereo",
    n: int | None = None,
    camera_info: bool = True,
    extra_topics=(),
    infos=None,
    raw_pairs=None,
) -> Path:
    """kind: 'mcap' | 'sqlite3' (ROS 2 bag folder) or 'ros1' (a .bag file). ``seq``: a dataset
    (rectified: CameraInfo from its camera, D = 0, R = I); or ``raw_pairs`` [(t s, left, right)]
    with ``infos`` ((K, D, R, P) left, (K, D, R, P) right) of raw cameras. A test that writes a
    bag skips where rosbags (the bags extra) is not installed."""
    need_extra("rosbags")
    from rosbags.typesys import Stores, get_typestore

    if kind == "ros1":
        from rosbags.rosbag1 import Writer

        ts = get_typestore(Stores.ROS1_NOETIC)
        writer: Writer | Writer2 = Writer(path)
        ser = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        ts = get_typestore(Stores.LATEST)
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
        ser = ts.serialize_cdr
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    Image, CImage, Info, Roi = (T[f"sensor_msgs/msg/{m}"] for m in ("Image", "CompressedImage", "CameraInfo", "RegionOfInterest"))

    def header(t_ns: int, frame: str):
        stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        return Header(seq=0, stamp=stamp, frame_id=frame) if kind == "ros1" else Header(stamp=stamp, frame_id=frame)

    if raw_pairs is None:
        cam = seq.camera
        count = len(seq) if n is None else n
        raw_pairs = [(f.timestamp, f.left, f.right) for f in (seq[i] for i in range(count))]
        infos = tuple(
            (P[:, :3].reshape(-1).copy(), np.zeros(5), np.eye(3).reshape(-1), P.reshape(-1).copy()) for P in (cam.P0, cam.P1)
        )
    itype = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with writer:
        conns = {}
        for side in ("left", "right"):
            topic = f"{prefix}/{side}/image_raw" + ("/compressed" if compressed else "")
            conns[side] = writer.add_connection(topic, itype, typestore=ts)
            if camera_info:
                conns[side + "_info"] = writer.add_connection(
                    f"{prefix}/{side}/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts
                )
        for topic in extra_topics:
            conns[topic] = writer.add_connection(topic, "sensor_msgs/msg/Image", typestore=ts)
        for t_s, left, right in raw_pairs:
            t_ns = 1_600_000_000_000_000_000 + int(round(t_s * 1e9))
            for side, img, info in (("left", left, infos[0]), ("right", right, infos[1])):
                h = header(t_ns, f"cam_{side}")
                if compressed:
                    ok, buf = cv2.imencode(".png", img)
                    msg = CImage(header=h, format="mono8; png compressed", data=np.frombuffer(buf.tobytes(), np.uint8))
                else:
                    msg = make_image(Image, h, img, encoding)
                writer.write(conns[side], t_ns, ser(msg, itype))
                if camera_info:
                    kw = dict(
                        header=h,
                        height=img.shape[0],
                        width=img.shape[1],
                        distortion_model="plumb_bob",
                        binning_x=0,
                        binning_y=0,
                        roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
                    )
                    mats = dict(zip("kdrp", (np.asarray(m, np.float64).reshape(-1) for m in info)))
                    kw.update({k.upper(): v for k, v in mats.items()} if kind == "ros1" else mats)
                    writer.write(conns[side + "_info"], t_ns, ser(Info(**kw), "sensor_msgs/msg/CameraInfo"))
            for topic in extra_topics:
                writer.write(
                    conns[topic], t_ns, ser(make_image(Image, header(t_ns, "x"), left, "mono8"), "sensor_msgs/msg/Image")
                )
    return path


def make_image(Image, h, grey: np.ndarray, encoding: str):
    """A sensor_msgs/Image holding ``grey`` in ``encoding`` (mono8, mono16, rgb8, bgr8)."""
    if encoding == "mono8":
        data, step = grey, grey.shape[1]
    elif encoding == "mono16":
        data = (grey.astype(np.uint16) << 8) | 0x55  # the high byte holds the grey value
        data = data.astype("<u2").view(np.uint8)
        step = grey.shape[1] * 2
    elif encoding in ("rgb8", "bgr8"):
        data = np.repeat(grey[:, :, None], 3, axis=2)
        step = grey.shape[1] * 3
    else:
        data = grey
        step = grey.shape[1]
    return Image(
        header=h,
        height=grey.shape[0],
        width=grey.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.ascontiguousarray(data).reshape(-1),
    )
