"""The SLAM algorithm: front end -> SNAPS -> factor graph (-> map keyframes); frames in, poses out.

The only module that knows the stages' order; it does no file I/O (:mod:`snaps_graph.runner`
does). ``SlamPipeline.process`` takes one ``StereoFrame`` and returns its pose at once, ``finish``
runs the optional batch refinement. Stream positions k key everything inside, the dataset's frame
numbers are kept beside them. A frame ``process`` rejects raises ``SnapsGraphError`` before any
state changes. The same config and input give bit-identical poses, loops and graph.
"""

from __future__ import annotations

import hashlib
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
from .geometry import inv
from .loop.prior import PriorMap
from .loop.snaps import SnapsLoopCloser, SnapsStep
from .mapping.depth import map_depth
from .mapping.outputs import BEST_ORDER
from .mapping.tsdf import FusedMap
from .session.store import Factors, Session, check_compatible, check_image_size, loop_settings
from .trajectory_io import PoseFile
from .types import FrameRecord, FrontEnd, LoopEvent, StereoFrame, VOResult
from .verification.features import LoopFeatureBank
from .verification.mono import MonoFeatureBank
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
    # With prior sessions: per prior its relocalisation (SlamPipeline.relocalisation), and each
    # relocalised prior's trajectory in the outputs' frame (prior index -> (N_i, 4, 4)).
    sessions: list[dict] = field(default_factory=list)
    prior_trajectories: dict[int, np.ndarray] = field(default_factory=dict)

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
        priors: list[Session] | None = None,
        same_start: bool = False,
    ):
        """``cfg`` is copied, never changed; ``loops``/``refine``/``build_map`` override it in the
        copy (``self.cfg``, what ran). ``frontend``: any ``FrontEnd`` (the paper: "it is possible to substitute the visual odometry part with
        any desired model"); default: ``StereoOdometry`` configured by ``cfg.frontend``.
        ``priors``: earlier sessions (``session.read_session``) to relocalise against and close
        loops with; ``same_start``: the run starts where they started (no appearance search)."""
        self.cfg = (cfg or Config()).resolved(loops=loops, refine=refine, build_map=build_map)
        self.loops_mode = self.cfg.loops
        self.refine = self.cfg.graph.refine

        self.camera = camera
        self.vo: FrontEnd = frontend if frontend is not None else StereoOdometry(camera, self.cfg.frontend)
        # Loop verification's features and answers (None without SNAPS), given to the loop closer.
        self.verifier = LoopVerifier(camera, self.cfg.frontend, self.cfg.verification) if self.loops_mode == "snaps" else None
        self.priors = list(priors or [])
        if self.priors and self.verifier is None:
            raise SnapsGraphError("a prior session needs loop closure: run with loops = snaps")
        maps = [self._prior_map(s) for s in self.priors]
        self.snaps = (
            SnapsLoopCloser(self.cfg.loop, self.cfg.odometry, LoopVerifier.reference_every, verifier=self.verifier, priors=maps)
            if self.verifier is not None
            else None
        )
        self._frame_prior: int | None = None  # the prior whose frame the outputs are in, once relocalised
        if same_start:
            for m in maps:  # the run's first frame is the prior's first
                m.relocalise(inv(m.poses[0]), (0, 0))
            self._frame_prior = 0 if maps else None
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
            for prior in self.priors:
                check_image_size(prior, (w, h))

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
                return self.to_output(est)
        return self.to_output(heuristic)

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
        k_cur = self._k_of_frame[loop.frame]
        if loop.session:
            self._add_session_loop(k_cur, loop)
            return
        k_ref = self._k_of_frame.get(loop.reference, -1)
        cov = self.verifier.covariance(loop.reference) if loop.verified else None
        self.graph.add_loop(k_ref, k_cur, loop.q, loop.T_ref_cur if loop.verified else None, covariance=cov)
        self.loops.append(loop)

    def _prior_map(self, s: Session) -> PriorMap:
        """A prior session for the loop closer; its reference features go to the verifier."""
        assert self.verifier is not None
        check_compatible(s, self.camera, loop_settings(self.cfg))
        bank: LoopFeatureBank = (
            MonoFeatureBank(self.camera, self.cfg.frontend, self.cfg.verification)
            if s.monocular
            else LoopFeatureBank(self.camera, self.cfg.frontend, self.cfg.verification, background=False)
        )
        bank.load(s.references(), s.vo_poses)
        self.verifier.add_prior(bank, s.frame_ids, s.vo_poses)
        return PriorMap(s.name, s.poses, s.driven, s.frame_ids, s.thumbs, self.cfg.loop.window)

    def _add_session_loop(self, k_cur: int, loop: LoopEvent) -> None:
        """A verified loop to a prior, held fixed where the run placed it: a robust unary factor
        on the frame (the graph's batch and iSAM2 alike); the first relocalisation sets the
        outputs' frame."""
        assert self.snaps is not None and self.verifier is not None
        prior = self.snaps.priors[loop.prior]
        j = prior.position(loop.reference)
        cov = self.verifier.covariance(loop.reference, loop.prior)
        self.graph.add_anchor(k_cur, prior.pose_own(j) @ np.asarray(loop.T_ref_cur, float), cov)
        if self._frame_prior is None:
            self._frame_prior = loop.prior
        self.loops.append(loop)

    @property
    def frame_prior(self) -> int | None:
        """The prior whose frame the outputs are in (None: the run's own)."""
        return self._frame_prior

    def output_frame(self) -> np.ndarray:
        """T_out_own: the outputs' frame (the first prior relocalised against, else this run's own)
        from the run's own frame, where the loop closer and the graph work."""
        if self._frame_prior is None or self.snaps is None:
            return np.eye(4)
        T = self.snaps.priors[self._frame_prior].T_own_prior
        return np.eye(4) if T is None else inv(T)

    def placed_priors(self) -> list[tuple[int, np.ndarray]]:
        """(prior, T_out_prior) of every relocalised prior: where its frame lies in the outputs'."""
        if self.snaps is None:
            return []
        T = self.output_frame()
        return [(i, T @ m.T_own_prior) for i, m in enumerate(self.snaps.priors) if m.T_own_prior is not None]

    def prior_trajectories(self) -> dict[int, np.ndarray]:
        """Every relocalised prior's trajectory, (N, 4, 4), in the outputs' frame."""
        return {i: T @ self.priors[i].poses for i, T in self.placed_priors()}

    def to_output(self, poses: np.ndarray) -> np.ndarray:
        """Poses (one or many) of the run's own frame in the outputs' frame; unchanged, not even
        multiplied by the identity, while the run has its own frame."""
        return poses if self._frame_prior is None else self.output_frame() @ poses

    def relocalisation(self) -> list[dict]:
        """Per prior: its folder, whether the run relocalised against it, at which frame of each,
        and T_prior_run (the run's own frame in the prior's)."""
        out = []
        for i, m in enumerate(self.snaps.priors if self.snaps is not None else []):
            first = next((lp for lp in self.loops if lp.prior == i and lp.relocalised), None)
            entry: dict = {"session": m.name, "relocalised": m.relocalised, "loops": sum(lp.prior == i for lp in self.loops)}
            entry["outputs_frame"] = i == self._frame_prior  # the outputs are in this prior's frame
            if m.T_own_prior is not None:
                entry["T_prior_run"] = [float(v) for v in inv(m.T_own_prior)[:3, :4].ravel()]
                entry["frame"] = None if first is None else first.frame
                entry["reference"] = None if first is None else first.reference
            out.append(entry)
        return out

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
        trajs = {name: self.to_output(poses) for name, poses in trajs.items()}
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
            sessions=self.relocalisation(),
            prior_trajectories=self.prior_trajectories(),
        )
        if self.observer is not None:
            self.observer.on_finish(self, result)
        return result

    def session(self, result: RunResult) -> Session | None:
        """What a later run needs of this one (``session.write_session`` writes it); None without
        SNAPS (no thumbnails, no verifier) or before the first frame."""
        if self.snaps is None or self.verifier is None or self.verifier.bank is None or self._shape is None:
            return None
        refs = self.verifier.bank.stored()
        feats = [f for _, f in refs]
        start = np.concatenate([[0], np.cumsum([len(f.uv) for f in feats])]).astype(np.int64)
        empty_desc = np.zeros((0, 32), np.uint8) if self.cfg.verification.detector == "orb" else np.zeros((0, 128), np.float32)
        best = next(n for n in BEST_ORDER if n in result.trajectories)
        pairs, measured, cov, robust = self.graph.factors()
        h, w = self._shape
        return Session(
            name="",
            camera=self.camera,
            image_size=(int(w), int(h)),
            monocular=bool(self._monocular),
            loop_settings=loop_settings(self.cfg),
            config_digest=hashlib.sha256(self.cfg.dumps().encode()).hexdigest(),
            trajectory=best,
            frame_ids=np.array(self._frame_ids, np.int64),
            timestamps=np.array(self._timestamps),
            poses=result.trajectories[best],
            vo_poses=np.array(self._vo_poses),
            driven=self.snaps.traj.s[: len(self.snaps)].copy(),
            thumbs=np.stack([self.snaps.thumbs[k] for k in range(len(self.snaps))]),
            refs=np.array([k for k, _ in refs], np.int64),
            ref_start=start,
            ref_uv=np.concatenate([f.uv for f in feats]) if feats else np.zeros((0, 2), np.float32),
            ref_pts=np.concatenate([f.pts3d for f in feats]) if feats else np.zeros((0, 3), np.float32),
            ref_desc=np.concatenate([f.desc for f in feats]) if feats else empty_desc,
            factors=Factors(pairs, measured, cov, robust),
        )

    @property
    def frame_ids(self) -> list[int]:
        return list(self._frame_ids)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array(self._timestamps)
