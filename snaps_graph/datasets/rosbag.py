"""ROS 1 (``.bag``) and ROS 2 (sqlite3 or MCAP, a bag folder or a bare ``.db3``/``.mcap``) stereo
reader through the ``rosbags`` library (pure Python, no ROS install; the ``bags`` extra).

Images (``Image`` or ``CompressedImage``) become 8-bit grey; each image topic's CameraInfo
calibrates it (``calib`` where the bag has none), pairs match by header stamp, topics are found
by name unless given, and one image topic makes a monocular sequence. The rules: docs/usage.md,
"Inputs in detail".
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from ..errors import SnapsGraphError
from ..io_utils import parse_frame_range
from ..types import StereoFrame
from ._selection import FrameSelection
from .rectify import StereoRectifier, match_stamps, to_grey

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
# (left word, right word) pairs that name the two cameras of a stereo rig in topic names.
_SIDES = (("left", "right"), ("cam0", "cam1"), ("infra1", "infra2"))


def is_bag(path: str | Path) -> bool:
    p = Path(path)
    if p.is_file():
        return p.suffix in (".bag", ".mcap", ".db3")
    return p.is_dir() and (p / "metadata.yaml").is_file()


def _import_rosbags():
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise SnapsGraphError("reading ROS bags needs the 'rosbags' package: pip install 'snaps_graph[bags]'") from None
    return AnyReader, Stores, get_typestore


def _side_key(topic: str) -> tuple[str, int] | None:
    """(topic with its side word replaced, 0 = left / 1 = right), or None."""
    low = topic.lower()
    for lw, rw in _SIDES:
        for side, word in ((0, lw), (1, rw)):
            pat = rf"(?<![a-z0-9]){word}(?![a-z0-9])"
            if re.search(pat, low):
                return re.sub(pat, "{side}", low, count=1) + f"|{lw}", side
    return None


def find_stereo_topics(image_topics: list[str]) -> list[tuple[str, str]]:
    """Candidate (left, right) topic pairs among image topics, by name."""
    by_key: dict[str, list[list[str]]] = {}
    for t in image_topics:
        sk = _side_key(t)
        if sk is None:
            continue
        by_key.setdefault(sk[0], [[], []])[sk[1]].append(t)
    pairs = []
    for lefts, rights in by_key.values():
        if len(lefts) == 1 and len(rights) == 1:
            pairs.append((lefts[0], rights[0]))
    return sorted(pairs)


def _camera_info_topic(image_topic: str, info_topics: list[str]) -> str | None:
    """The CameraInfo topic beside an image topic: walk up its namespaces."""
    parts = image_topic.rstrip("/").split("/")
    for n in range(len(parts) - 1, 0, -1):
        cand = "/".join(parts[:n]) + "/camera_info"
        if cand in info_topics:
            return cand
    return None


def decode_image(msg, msgtype: str, source: str = "image") -> np.ndarray:
    """A ROS Image or CompressedImage message as uint8 grey."""
    if msgtype.endswith("CompressedImage"):
        buf = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SnapsGraphError(f"{source}: compressed image ({msg.format}) cannot be decoded")
        return to_grey(img, "", source)
    enc = msg.encoding.lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, np.uint8)
    channels = {
        "mono8": 1,
        "8uc1": 1,
        "mono16": 1,
        "16uc1": 1,
        "rgb8": 3,
        "bgr8": 3,
        "8uc3": 3,
        "rgba8": 4,
        "bgra8": 4,
        "8uc4": 4,
    }
    if enc not in channels:
        raise SnapsGraphError(
            f"{source}: image encoding '{msg.encoding}' is not supported (mono8, mono16, rgb8, bgr8, rgba8, bgra8)"
        )
    c = channels[enc]
    bpp = 2 if enc in ("mono16", "16uc1") else 1
    if h <= 0 or w <= 0 or step < w * c * bpp or data.size < h * step:
        raise SnapsGraphError(f"{source}: image {w}x{h}, step {step} does not fit its {data.size} bytes")
    rows = data[: h * step].reshape(h, step)
    if bpp == 2:
        img = rows[:, : w * 2].copy().view(">u2" if msg.is_bigendian else "<u2").astype(np.uint16)
    else:
        img = rows[:, : w * c]
        if c > 1:
            img = img.reshape(h, w, c)
    return to_grey(img, enc if enc.startswith(("rgb", "bgr")) else "", source)


class RosbagSequence(FrameSelection):
    """A stereo image pair stream from a ROS 1 or ROS 2 bag (the dataset protocol)."""

    def __init__(
        self,
        path: str | Path,
        frames: str | None = None,
        gt: str | Path | None = None,
        left_topic: str | None = None,
        right_topic: str | None = None,
        calib: str | Path | None = None,
    ):
        """``calib``: a calib.txt or a folder with cam0/ and cam1/ sensor.yaml, for bags without
        CameraInfo (EuRoC's own bags have none)."""
        AnyReader, Stores, get_typestore = _import_rosbags()
        self.path = Path(path)
        if not self.path.exists():
            raise SnapsGraphError(f"{self.path}: bag not found")
        self.notes: list[str] = []
        try:
            self._reader = AnyReader([self.path], default_typestore=get_typestore(Stores.LATEST))
            self._reader.open()
        except Exception as exc:  # rosbags raises several error types for unreadable bags
            raise SnapsGraphError(f"{self.path}: cannot open bag ({_one_line(exc)})") from None
        conns = self._reader.connections
        image_topics = sorted({c.topic for c in conns if c.msgtype in IMAGE_TYPES})
        info_topics = sorted({c.topic for c in conns if c.msgtype == INFO_TYPE})
        left_topic, right_topic = self._choose_topics(image_topics, left_topic, right_topic)
        self.left_topic: str = left_topic
        self.right_topic: str | None = right_topic
        self.source_info = {"left_topic": left_topic} | ({"right_topic": right_topic} if right_topic else {})
        self.stereo = right_topic is not None
        topics = [left_topic] if right_topic is None else [left_topic, right_topic]
        self._conn = {t: [c for c in conns if c.topic == t] for t in topics}
        self._msgtype = {t: self._conn[t][0].msgtype for t in topics}

        infos = self._camera_infos(topics, info_topics) if calib is None else {}
        self._pair_messages(topics)
        self._calibrate(calib, infos)
        n_all = len(self._pair_stamps)
        self._gt_all = None if gt is None else self._read_gt(Path(gt), n_all)
        rng = parse_frame_range(frames, n_all)
        self.start, self.stop = (0, n_all) if rng is None else (rng[0], rng[1] if rng[1] is not None else n_all)
        self[0]  # decode one pair now: an unsupported encoding or a size mismatch stops before the run

    # ---- set-up helpers ----
    def _camera_infos(self, topics: list[str], info_topics: list[str]) -> dict:
        """The first CameraInfo message beside each image topic."""
        infos = {}
        for t in topics:
            it = _camera_info_topic(t, info_topics)
            if it is None:
                raise SnapsGraphError(
                    f"{self.path}: no sensor_msgs/CameraInfo topic beside {t}; give the calibration with --calib "
                    "(a calib.txt, or a folder with cam0/ and cam1/ sensor.yaml)"
                )
            infos[t] = self._first_message(it)
        return infos

    def _pair_messages(self, topics: list[str]) -> None:
        """One pass over the image messages: header stamps and bag times, no pixels kept; the
        left and right messages paired by stamp."""
        left_topic, right_topic = self.left_topic, self.right_topic
        stamps: dict[str, list[int]] = {t: [] for t in topics}
        bag_t: dict[str, list[int]] = {t: [] for t in topics}
        for conn, t_bag, raw in self._reader.messages(connections=[c for t in topics for c in self._conn[t]]):
            msg = self._deserialize(raw, conn)
            st = msg.header.stamp
            stamps[conn.topic].append(int(st.sec) * 1_000_000_000 + int(st.nanosec))
            bag_t[conn.topic].append(int(t_bag))
        sl, sr = (np.array(stamps[t], np.int64) for t in (topics[0], topics[-1]))
        bl, br = (np.array(bag_t[t], np.int64) for t in (topics[0], topics[-1]))
        if len(sl) == 0 or len(sr) == 0:
            raise SnapsGraphError(f"{self.path}: no messages on {left_topic if len(sl) == 0 else right_topic}")
        ol, orr = np.argsort(sl, kind="stable"), np.argsort(sr, kind="stable")
        il, ir = match_stamps(sl[ol], sr[orr])
        if len(il) == 0:
            raise SnapsGraphError(f"{self.path}: no {left_topic} and {right_topic} messages share a stamp")
        if len(il) < len(sl) or len(ir) < len(sr):
            self.notes.append(
                f"{self.path}: {len(sl) - len(il)} left and {len(sr) - len(ir)} right images have no partner (dropped)"
            )
        self._pair_stamps = np.stack([sl[ol][il], sr[orr][ir]], 1)
        self._pair_bag_t = np.stack([bl[ol][il], br[orr][ir]], 1)
        self._times_all = (self._pair_stamps[:, 0] - self._pair_stamps[0, 0]) * 1e-9
        self.t0_ns = int(self._pair_stamps[0, 0])  # the absolute time of timestamp 0 (pose files with absolute stamps)

    def _calibrate(self, calib: str | Path | None, infos: dict) -> None:
        """The camera and rectifier: from the CameraInfo messages, or from ``calib``."""
        left_topic, right_topic = self.left_topic, self.right_topic
        if calib is None and right_topic is None:
            self.rectifier, self.camera = self._mono_camera(infos[left_topic])
        elif calib is None:
            assert right_topic is not None
            self.rectifier, self.camera = self._make_camera(infos[left_topic], infos[right_topic])
        else:  # the bag's CameraInfo (if any) is ignored
            from .euroc import load_calibration

            camera, self.rectifier = load_calibration(calib)
            self.camera = camera if camera is not None else self.rectifier.camera
            if not self.camera.width:  # a calib.txt carries no size: the images tell it
                first = self._first_message(left_topic)
                h, w = decode_image(first, self._msgtype[left_topic], f"{self.path}: {left_topic}").shape
                self.camera = self.camera.with_size(w, h)

    def _read_gt(self, gp: Path, n_all: int) -> np.ndarray:
        from ..trajectory_io import read_kitti_poses

        if not gp.is_file():
            raise SnapsGraphError(f"{gp}: ground-truth file not found")
        g = read_kitti_poses(gp)
        if len(g) != n_all:
            raise SnapsGraphError(f"{gp}: {len(g)} poses for {n_all} stereo pairs in the bag")
        return g

    def _choose_topics(self, image_topics, left, right) -> tuple[str, str | None]:
        if not image_topics:
            raise SnapsGraphError(f"{self.path}: no sensor_msgs/Image or CompressedImage topics")
        for t, flag in ((left, "--left-topic"), (right, "--right-topic")):
            if t is not None and t not in image_topics:
                raise SnapsGraphError(f"{self.path}: {flag} {t} is not an image topic here (have: {', '.join(image_topics)})")
        if left and right:
            if left == right:
                raise SnapsGraphError(f"{self.path}: --left-topic and --right-topic are the same topic")
            return left, right
        if len(image_topics) == 1 and not right:
            return image_topics[0], None  # monocular
        pairs = find_stereo_topics(image_topics)
        if left or right:
            pairs = [p for p in pairs if left in p or right in p]
        if left and not right and not pairs:
            return left, None  # monocular: the named topic has no right partner
        if not pairs:
            raise SnapsGraphError(
                f"{self.path}: no stereo pair among the image topics ({', '.join(image_topics)}); name them with --left-topic/--right-topic"
            )
        if len(pairs) > 1:
            listed = "; ".join(f"{a} + {b}" for a, b in pairs)
            raise SnapsGraphError(f"{self.path}: several stereo pairs ({listed}); choose one with --left-topic/--right-topic")
        return pairs[0]

    def _deserialize(self, raw, conn):
        try:
            return self._reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise SnapsGraphError(f"{self.path}: {conn.topic}: message cannot be decoded ({_one_line(exc)})") from None

    def _first_message(self, topic: str):
        conns = [c for c in self._reader.connections if c.topic == topic]
        for conn, _t, raw in self._reader.messages(connections=conns):
            return self._deserialize(raw, conn)
        raise SnapsGraphError(f"{self.path}: {topic} has no messages")

    def _mono_camera(self, info):
        """(undistorter or None, camera of baseline 0) of a monocular topic's CameraInfo."""
        from ..camera import StereoCamera
        from .euroc import MonoUndistorter

        size = (int(info.width), int(info.height))
        K, D, _R, P = _info_mats(info)
        if K.size != 9 or not np.all(np.isfinite(K)) or size[0] <= 0 or size[1] <= 0:
            raise SnapsGraphError(f"{self.path}: {self.left_topic} CameraInfo needs a finite K and an image size")
        if "rect" in (self.left_topic or "").lower() or not np.any(D):
            Kp = P.reshape(3, 4)[:, :3] if P.size == 12 and P[0] > 0 else K.reshape(3, 3)
            return None, StereoCamera(float(Kp[0, 0]), float(Kp[1, 1]), float(Kp[0, 2]), float(Kp[1, 2]), 0.0, *size)
        und = MonoUndistorter(K.reshape(3, 3), D, size, f"{self.path}: {self.left_topic} CameraInfo")
        return und, und.camera

    def _make_camera(self, info_l, info_r):
        src = f"{self.path}: {self.right_topic} CameraInfo"
        size = (int(info_l.width), int(info_l.height))
        if (int(info_r.width), int(info_r.height)) != size:
            raise SnapsGraphError(
                f"{src}: size {info_r.width}x{info_r.height} differs from the left camera's {size[0]}x{size[1]}"
            )
        Kl, Dl, Rl, Pl = _info_mats(info_l)
        Kr, Dr, Rr, Pr = _info_mats(info_r)
        for name, arr, n in (("K", Kl, 9), ("R", Rl, 9), ("P", Pl, 12), ("K", Kr, 9), ("R", Rr, 9), ("P", Pr, 12)):
            if arr.size != n or not np.all(np.isfinite(arr)):
                raise SnapsGraphError(f"{self.path}: CameraInfo {name} must hold {n} finite numbers")
        if size[0] <= 0 or size[1] <= 0:
            raise SnapsGraphError(f"{self.path}: {self.left_topic} CameraInfo has no image size")
        if Pr.reshape(3, 4)[0, 3] == 0:
            raise SnapsGraphError(f"{src}: P[0,3] = 0, so the baseline is unknown (a stereo right camera has P[0,3] = -fx*B)")
        for info in (info_l, info_r):
            if info.distortion_model not in ("plumb_bob", "rational_polynomial", "") and np.any(_info_mats(info)[1] != 0):
                raise SnapsGraphError(
                    f"{self.path}: distortion model '{info.distortion_model}' is not supported (plumb_bob, rational_polynomial)"
                )
        rectified_topics = "rect" in (self.left_topic or "").lower() and "rect" in (self.right_topic or "").lower()
        identity = all(
            np.allclose(r.reshape(3, 3), np.eye(3)) and not np.any(d) and np.allclose(k.reshape(3, 3), p.reshape(3, 4)[:, :3])
            for k, d, r, p in ((Kl, Dl, Rl, Pl), (Kr, Dr, Rr, Pr))
        )  # nothing to undo: the raw images are already the rectified ones
        if rectified_topics or identity:
            from ..camera import StereoCamera

            return None, StereoCamera.from_projections(Pl.reshape(3, 4), Pr.reshape(3, 4), *size, source=src)
        rect = StereoRectifier.from_rectification(Kl, Dl, Rl, Pl, Kr, Dr, Rr, Pr, size, source=src)
        return rect, rect.camera

    def _pair(self, lmsg, lconn, rmsg, rconn, k: int) -> StereoFrame:
        left = decode_image(lmsg, lconn.msgtype, f"{self.path}: {lconn.topic}")
        if rmsg is None:  # monocular
            right = np.zeros((0, 0), np.uint8)
        else:
            right = decode_image(rmsg, rconn.msgtype, f"{self.path}: {rconn.topic}")
        want = (self.camera.height, self.camera.width)
        for img, conn in ((left, lconn), (right, rconn)) if rmsg is not None else ((left, lconn),):
            if img.shape != want:
                raise SnapsGraphError(
                    f"{self.path}: {conn.topic}: image {img.shape[1]}x{img.shape[0]} differs from its CameraInfo {want[1]}x{want[0]}"
                )
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        return StereoFrame(k, float(self._times_all[k]), left, right)

    def _stream(self, k0: int, k1: int) -> Iterator[StereoFrame]:
        """Pairs k0..k1-1 in order, from one sweep over the bag's messages in that time range."""
        lt, rt = self.left_topic, self.right_topic
        assert lt is not None  # every opened bag has a left topic
        want = {lt: {int(s): k for k, s in enumerate(self._pair_stamps[k0:k1, 0], k0)}}
        if rt is not None:
            want[rt] = {int(s): k for k, s in enumerate(self._pair_stamps[k0:k1, 1], k0)}
        got: dict[int, list] = {}
        nxt = k0
        t_lo = int(self._pair_bag_t[k0:k1].min())
        t_hi = int(self._pair_bag_t[k0:k1].max()) + 1
        conns = [c for t in want for c in self._conn[t]]
        for conn, _t, raw in self._reader.messages(connections=conns, start=t_lo, stop=t_hi):
            msg = self._deserialize(raw, conn)
            st = msg.header.stamp
            k = want[conn.topic].get(int(st.sec) * 1_000_000_000 + int(st.nanosec))
            if k is None:
                continue
            slot = got.setdefault(k, [None, None] if rt is not None else [None, (None, None)])
            slot[0 if conn.topic == lt else 1] = (msg, conn)
            while nxt in got and None not in got[nxt]:
                (lm, lc), (rm, rc) = got.pop(nxt)
                yield self._pair(lm, lc, rm, rc, nxt)
                nxt += 1
        if nxt < k1:
            raise SnapsGraphError(f"{self.path}: pair {nxt} could not be read back from the bag")

    # ---- dataset protocol ----
    def __getitem__(self, i: int) -> StereoFrame:
        k = self._position(i)
        return next(self._stream(k, k + 1))

    def __iter__(self) -> Iterator[StereoFrame]:
        if len(self):
            yield from self._stream(self.start, self.stop)

    def close(self) -> None:
        self._reader.close()


def _info_mats(info) -> list[np.ndarray]:
    """K, D, R, P of a CameraInfo (ROS 2 names them k, d, r, p; ROS 1 K, D, R, P)."""
    return [np.asarray(getattr(info, f) if hasattr(info, f) else getattr(info, f.upper()), float).reshape(-1) for f in "kdrp"]


def _one_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:200]
