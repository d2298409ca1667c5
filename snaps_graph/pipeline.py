"""The SLAM algorithm: front end -> SNAPS -> factor graph (-> map keyframes); frames in, poses out.

The only module that knows the stages' order; it does no file I/O (:mod:`snaps_graph.runner`
does). ``SlamPipeline.process`` takes one ``StereoFrame`` and returns its pose at once, ``finish``
runs the optional batch refinement. Stream positions k key everything inside, the dataset's frame
numbers are kept beside them. A frame ``process`` rejects raises ``SnapsGraphError`` before any
state changes. The same config and input give bit-identical poses, loops and graph.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .backend.pose_graph import PoseGraph
from .camera import StereoCamera
from .config import Config
from .errors import SnapsGraphError
from .frontend.depth import ORDER_MAX_FRAMES, check_stereo_pair, stereo_order
from .frontend.external import PoseFileOdometry, time_origin
from .frontend.odometry import StereoOdometry
from .loop.snaps import SnapsLoopCloser, SnapsStep
from .mapping.depth import map_depth
from .mapping.tsdf import FusedMap
from .trajectory_io import PoseFile
from .types import FrameRecord, FrontEnd, LoopEvent, StereoFrame, VOResult
from .verification.verifier import LoopVerifier


@dataclass
class FrameOutput:
    """What ``SlamPipeline.process`` returns for one frame."""

    k: int  # stream position
    frame: int  # dataset frame number
    pose: np.ndarray  # best pose available now: iSAM2 estimate, else SNAPS heuristic, else VO
    vo: VOResult
    loop: LoopEvent | None


@dataclass
class RunResult:
    """What ``SlamPipeline.finish`` returns: everything the runner writes."""

    trajectories: dict[str, np.ndarray]  # name -> (N,4,4)
    loops: list[LoopEvent]
    records: list[FrameRecord]  # one per processed frame, in stream order
    frame_ids: list[int]  # the dataset frame numbers, in stream order
    timestamps: np.ndarray  # (N,) seconds
    graph_failures: list = field(default_factory=list)  # (k, reason); k = -1: not tied to a frame
    graph_stats: dict = field(default_factory=dict)  # PoseGraph.stats.summary()
    wall_s: float = 0.0

    @property
    def n_flagged(self) -> int:
        """Frames the front end flagged (its constant-velocity guess stands in for the pose)."""
        return sum(1 for r in self.records if not r.vo_ok)


def pose_file_frontend(
    track: PoseFile, cfg: Config | None, frames, timestamps, origin_s: float | None = None
) -> PoseFileOdometry:
    """The front end of a pose file for a run over ``frames`` (numbers) at ``timestamps`` (s from
    ``origin_s``, the dataset's absolute clock when it has one): TUM stamps matched on the clock
    the file uses (``external.time_origin``), every frame checked for a pose before the first runs."""
    origin = time_origin(track, float(timestamps[0]), origin_s)
    fe = PoseFileOdometry(track, (cfg or Config()).odometry, time_origin_s=origin)
    fe.check(frames, timestamps)
    return fe


def is_monocular(frame: StereoFrame) -> bool:
    """The frame has no right image (None or empty)."""
    return frame.right is None or np.asarray(frame.right).size == 0


class SlamPipeline:
    def __init__(
        self,
        camera: StereoCamera,
        cfg: Config | None = None,
        *,
        loops: str | None = None,
        refine: str | None = None,
        build_map: bool | None = None,
        frontend: FrontEnd | None = None,
    ):
        """``cfg`` is copied, never changed; ``loops``/``refine``/``build_map`` override it in the
        copy (``self.cfg``, what ran). ``frontend``: any ``FrontEnd`` (the paper: "it is possible to substitute the visual odometry part with
        any desired model"); default: ``StereoOdometry`` configured by ``cfg.frontend``."""
        self.cfg = (cfg or Config()).resolved(loops=loops, refine=refine, build_map=build_map)
        self.loops_mode = self.cfg.loops
        self.refine = self.cfg.graph.refine

        self.camera = camera
        self.vo: FrontEnd = frontend if frontend is not None else StereoOdometry(camera, self.cfg.frontend)
        # Loop verification's features and answers (None without SNAPS), given to the loop closer.
        self.verifier = LoopVerifier(camera, self.cfg.frontend, self.cfg.verification) if self.loops_mode == "snaps" else None
        self.snaps = (
            SnapsLoopCloser(self.cfg.loop, self.cfg.odometry, LoopVerifier.reference_every, verifier=self.verifier)
            if self.verifier is not None
            else None
        )
        self.graph = PoseGraph(
            self.cfg.graph, mode="isam2" if self.refine == "both" else self.refine, drift=self.cfg.odometry.model()
        )
        self.map = FusedMap(camera, self.cfg.map) if self.cfg.map.enabled else None

        self._frame_ids: list[int] = []
        self._timestamps: list[float] = []
        self._vo_poses: list[np.ndarray] = []
        self._shape: tuple[int, int] | None = None  # (H, W) of the first frame
        self._order_pending = True  # no stereo_order verdict yet
        self._monocular: bool | None = None  # set by the first frame
        self._k_of_frame: dict[int, int] = {}
        self.loops: list[LoopEvent] = []
        self.records: list[FrameRecord] = []
        self._t_start = time.perf_counter()
        # Optional observer (the rerun logger): on_frame(pipeline, frame, output) after each
        # frame, on_finish(pipeline, result) at the end. None: nothing is called.
        self.observer = None
        self._finished = False  # finish() closed the front end's workers: no more frames

    # ---- streaming ----
    def check_frame(self, frame: StereoFrame) -> None:
        """SnapsGraphError if ``frame`` cannot be processed next; changes nothing."""
        if not isinstance(frame, StereoFrame):
            raise SnapsGraphError(f"process() takes a StereoFrame, not {type(frame).__name__}")
        if self._finished:
            raise SnapsGraphError("this pipeline is finished (finish() was called); start a new SlamPipeline for more frames")
        index = frame.index
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            raise SnapsGraphError(f"frame {index!r}: the frame number must be a non-negative integer")
        if self._frame_ids and index <= self._frame_ids[-1]:
            raise SnapsGraphError(f"frame {index}: frame numbers must increase (the previous frame was {self._frame_ids[-1]})")
        self._check_time(index, frame.timestamp)
        self._check_images(frame)

    def _check_time(self, index: int, timestamp) -> None:
        try:
            t = float(timestamp)
        except (TypeError, ValueError):
            raise SnapsGraphError(f"frame {index}: timestamp {timestamp!r} is not a number") from None
        if not math.isfinite(t):
            raise SnapsGraphError(f"frame {index}: timestamp {t} is not finite")
        if self._timestamps and t <= self._timestamps[-1]:  # as times.txt: time must increase
            raise SnapsGraphError(f"frame {index}: timestamp {t} does not increase (previous {self._timestamps[-1]})")

    def _check_images(self, frame: StereoFrame) -> None:
        index, mono = frame.index, is_monocular(frame)
        try:
            check_stereo_pair(frame.left, frame.left if mono else frame.right)
        except SnapsGraphError as exc:
            raise SnapsGraphError(f"frame {index}: {exc}") from None
        if mono and isinstance(self.vo, StereoOdometry):
            raise SnapsGraphError(
                f"frame {index}: no right image: the stereo VO needs one (give odometry from elsewhere: --odometry)"
            )
        if mono and self.map is not None:
            raise SnapsGraphError(f"frame {index}: no right image: the map needs stereo depth (run without --map)")
        if self._monocular is not None and mono != self._monocular:
            have = "monocular" if self._monocular else "stereo"
            raise SnapsGraphError(f"frame {index}: {'no' if mono else 'a'} right image in a {have} run")
        h, w = frame.left.shape  # the camera's size is the front end's check (a custom one may differ)
        if self._shape is not None and (h, w) != self._shape:
            raise SnapsGraphError(
                f"frame {index}: image {w}x{h} differs from the first frame's {self._shape[1]}x{self._shape[0]}"
            )
        if self._shape is None and self.snaps is not None:
            self.snaps.check_image(index, (h, w))

    def process(self, frame: StereoFrame) -> FrameOutput:
        """One frame through the stages; returns its best pose now."""
        self.check_frame(frame)
        t0 = time.perf_counter()
        k = self._admit(frame)
        vo = self.vo.process(frame)
        t_vo_ms = (time.perf_counter() - t0) * 1e3
        self._keep(k, frame, vo)
        heuristic, step = self._close_loop(k, frame, vo)
        graph_ok, t_graph_ms = self._update_graph(k, heuristic, vo, step)
        t_map_ms = self._add_to_map(k, frame)
        self.records.append(
            self._record(frame, vo, step, (time.perf_counter() - t0) * 1e3, t_vo_ms, t_graph_ms, graph_ok, t_map_ms)
        )
        output = FrameOutput(k, int(frame.index), self._best_pose(k, heuristic), vo, step.loop if step else None)
        if self.observer is not None:
            self.observer.on_frame(self, frame, output)
        return output

    def _admit(self, frame: StereoFrame) -> int:
        """The frame's stream position; the first frame sets the run up (stereo or monocular),
        the first pairs until one gives a verdict must not have left and right swapped."""
        k = len(self._frame_ids)
        if self._monocular is None:
            self._start_monocular(is_monocular(frame))
        if self._order_pending and k < ORDER_MAX_FRAMES and not self._monocular:
            verdict, why = stereo_order(frame.left, frame.right)
            if verdict == "swapped":
                raise SnapsGraphError(f"frame {frame.index}: left and right look swapped ({why}); swap the two inputs")
            if verdict == "same":
                raise SnapsGraphError(f"frame {frame.index}: {why}; the right input must be the right camera's")
            self._order_pending = verdict == "unknown"
        return k

    def _keep(self, k: int, frame: StereoFrame, vo: VOResult) -> None:
        self._shape = frame.left.shape
        self._frame_ids.append(int(frame.index))
        self._k_of_frame[int(frame.index)] = k
        self._timestamps.append(float(frame.timestamp))
        self._vo_poses.append(vo.pose)

    def _close_loop(self, k: int, frame: StereoFrame, vo: VOResult) -> tuple[np.ndarray, SnapsStep | None]:
        """SNAPS on the frame (the verifier told the frame first): the heuristic pose and the step;
        without SNAPS, the VO pose."""
        if self.snaps is None or self.verifier is None:
            return vo.pose, None
        self.verifier.observe(k, frame, vo)
        step = self.snaps.step(frame.index, vo.T_rel, frame.left)
        self.graph.failures.extend(self.verifier.failures)
        self.verifier.failures.clear()
        return step.pose, step

    def _update_graph(self, k: int, heuristic: np.ndarray, vo: VOResult, step: SnapsStep | None) -> tuple[bool, float]:
        """The frame and its loop into the factor graph, one iSAM2 update: (no new failure, ms)."""
        tg = time.perf_counter()
        self.graph.add_frame(
            k, heuristic, None if k == 0 else vo.T_rel, inliers=vo.inliers, ok=vo.ok, cov=vo.cov, drift_cov=vo.drift_cov
        )
        if step is not None and step.loop is not None:
            self._add_loop_factor(step.loop)
        n_fail = len(self.graph.failures)
        self.graph.update()
        return len(self.graph.failures) == n_fail, (time.perf_counter() - tg) * 1e3

    def _add_to_map(self, k: int, frame: StereoFrame) -> float:
        """A map keyframe when the map wants this frame; the time it took, ms."""
        if self.map is None or not self.map.should_add(k):
            return 0.0
        tm = time.perf_counter()
        self._add_map_keyframe(k, frame)
        return (time.perf_counter() - tm) * 1e3

    def _record(
        self,
        frame: StereoFrame,
        vo: VOResult,
        step: SnapsStep | None,
        t_total_ms: float,
        t_vo_ms: float,
        t_graph_ms: float,
        graph_ok: bool,
        t_map_ms: float,
    ) -> FrameRecord:
        return FrameRecord(
            frame=int(frame.index),
            timestamp=float(frame.timestamp),
            t_total_ms=t_total_ms,
            t_vo_ms=t_vo_ms,
            vo_ok=int(vo.ok),
            vo_inliers=int(vo.inliers),
            vo_reason=vo.reason,
            t_loop_ms=step.t_ms if step else 0.0,
            loop_candidates=int(step.candidates) if step else 0,
            loop_closed=int(step is not None and step.loop is not None),
            t_verify_ms=step.t_verify_ms if step else 0.0,
            t_graph_ms=t_graph_ms,
            graph_ok=int(graph_ok),
            t_map_ms=t_map_ms,
            vo_disparity_offset_px=float(vo.disparity_offset_px),
        )

    def _best_pose(self, k: int, heuristic: np.ndarray) -> np.ndarray:
        """The iSAM2 estimate when it runs and is finite, else the heuristic (SNAPS or VO) pose."""
        if self.refine in ("isam2", "both"):
            est = self.graph.estimate(k)
            if np.all(np.isfinite(est)):
                return est
        return heuristic

    def _start_monocular(self, mono: bool) -> None:
        """At the first frame: a monocular run verifies loops by two-view geometry."""
        self._monocular = mono
        if mono:
            self._order_pending = False
        if self.verifier is not None:
            self.verifier.start(mono)

    def _add_loop_factor(self, loop: LoopEvent) -> None:
        """A loop-closure factor for a SNAPS loop: measured by verification when it succeeded
        (done once, inside the SNAPS step), else the paper's same-place assumption."""
        assert self.verifier is not None
        k_ref = self._k_of_frame.get(loop.reference, -1)
        k_cur = self._k_of_frame[loop.frame]
        cov = self.verifier.covariance(loop.reference) if loop.verified else None
        self.graph.add_loop(k_ref, k_cur, loop.q, loop.T_ref_cur if loop.verified else None, covariance=cov)
        self.loops.append(loop)

    def _add_map_keyframe(self, k: int, frame: StereoFrame) -> None:
        assert self.map is not None
        try:
            depth = map_depth(frame.left, frame.right, self.camera, self.cfg.frontend, self.cfg.map, self.vo.disparity_offset_px)
        except Exception as exc:  # a bad frame must not end the run: the keyframe is skipped
            self.graph.failures.append((k, f"map depth failed: {type(exc).__name__}: {exc}"))
            return
        self.map.add_keyframe(k, depth, frame.left)

    # ---- end of run ----
    def finish(self) -> RunResult:
        if not self._frame_ids:
            raise SnapsGraphError("no frame was processed, nothing to finish")
        self._finished = True
        self.vo.close()
        if self.verifier is not None:
            self.verifier.close()
        trajs: dict[str, np.ndarray] = {"vo": np.array(self._vo_poses)}
        if self.snaps is not None:
            # The loop closer's trajectory, with every eq. 6 correction applied (a pose stored at
            # its arrival would miss the corrections of later loops).
            trajs["snaps"] = self.snaps.poses
        if self.refine in ("isam2", "both"):
            # iSAM2 takes one step per update; a robust loop near the end needs a few more.
            self.graph.converge()
            trajs["isam2"] = self.graph.estimates()
        if self.refine in ("batch", "both"):
            if "snaps" in trajs:  # start from every SNAPS correction, not the poses at arrival
                self.graph.set_initial_estimates(trajs["snaps"])
            trajs["batch"] = self.graph.optimize_batch()
        for name, poses in trajs.items():
            if not np.all(np.isfinite(poses)):  # never a NaN pose in any output
                raise RuntimeError(f"internal error: non-finite pose in the {name} trajectory")
        result = RunResult(
            trajectories=trajs,
            loops=list(self.loops),
            records=list(self.records),
            frame_ids=list(self._frame_ids),
            timestamps=np.array(self._timestamps),
            graph_failures=list(self.graph.failures),
            graph_stats=self.graph.stats.summary(),
            wall_s=time.perf_counter() - self._t_start,
        )
        if self.observer is not None:
            self.observer.on_finish(self, result)
        return result

    @property
    def frame_ids(self) -> list[int]:
        return list(self._frame_ids)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array(self._timestamps)
