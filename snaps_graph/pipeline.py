"""The frame loop: front end -> SNAPS -> factor graph -> map; timings; the results folder.

This is the only module that knows the order of the stages. ``SlamPipeline`` is streaming: feed
it one ``StereoFrame`` at a time with ``process`` (a live source works as well as a folder) and
it returns that frame's pose at once; ``finish`` runs the optional batch refinement and
``write_results`` writes the results folder.

Stream positions ``k = 0, 1, 2, ...`` key everything internally (graph variables, map
keyframes); the dataset's own frame index is kept beside them (``frame`` in frames.csv,
``frame``/``reference`` in loops.jsonl), so a run over ``--frames 100:200`` reports file numbers.

Results folder (every file written atomically, after the run)::

    poses_vo.txt / .tum        pure VO chain
    poses_snaps.txt / .tum     SNAPS heuristic trajectory (loops = snaps)
    poses_isam2.txt / .tum     iSAM2 estimate after the last frame (refine = isam2)
    poses_batch.txt / .tum     batch optimisation (refine = batch; both = isam2 and batch)
    poses_gt.txt               ground truth of the processed frames, re-based (when known)
    frames.csv                 one row per frame: timings, VO quality, loop columns
    loops.jsonl                one JSON object per closed loop
    graph.g2o                  the factor graph (gtsam's writer)
    config.toml                every parameter used
    metrics.json               metrics per trajectory (when ground truth is known) and latency
    map.ply, map.png           the point-cloud map and its top-down picture (with --map)

Determinism: the same config and input give bit-identical pose files, loops.jsonl and
graph.g2o; only the timing columns of frames.csv (and latency figures) vary between runs.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .camera import StereoCamera
from .config import Config
from .datasets.kitti import StereoFrame
from .errors import SnapsGraphError
from .evaluation.trajectory import write_kitti_poses, write_tum_poses
from .io_utils import atomic_write_text
from .types import FrameFeatures, LoopEvent, VOResult

REFINE_MODES = ("none", "isam2", "batch", "both")  # both = iSAM2 online + batch at the end
LOOP_MODES = ("snaps", "none")

FRAME_COLUMNS = [
    "frame",
    "timestamp",
    "t_total_ms",
    "t_vo_ms",
    "vo_ok",
    "vo_inliers",
    "vo_reason",
    "t_loop_ms",
    "loop_candidates",
    "loop_closed",
    "t_verify_ms",
    "t_graph_ms",
    "graph_ok",
    "t_map_ms",
]


@dataclass
class FrameOutput:
    """What ``SlamPipeline.process`` returns for one frame."""

    k: int  # stream position
    frame: int  # dataset frame index
    pose: np.ndarray  # best pose available now: iSAM2 estimate, else SNAPS heuristic, else VO
    vo: VOResult
    loop: LoopEvent | None


@dataclass
class RunResult:
    trajectories: dict[str, np.ndarray]  # name -> (N,4,4)
    loops: list[LoopEvent]
    rows: list[dict]
    graph_failures: list = field(default_factory=list)
    wall_s: float = 0.0


class SlamPipeline:
    def __init__(
        self,
        camera: StereoCamera,
        cfg: Config | None = None,
        *,
        loops: str | None = None,
        refine: str | None = None,
        build_map: bool | None = None,
        frontend=None,
    ):
        """``frontend``: any object with ``process(frame) -> VOResult`` and ``close()`` (the
        paper: "it is possible to substitute the visual odometry part with any desired model");
        default: ``StereoOdometry`` configured by ``cfg.frontend``."""
        from .backend.pose_graph import PoseGraph

        self.cfg = cfg or Config()
        self.loops_mode = loops or self.cfg.loops
        self.refine = refine or self.cfg.graph.refine
        if self.loops_mode not in LOOP_MODES:
            raise SnapsGraphError(f"--loops must be one of {', '.join(LOOP_MODES)}, not '{self.loops_mode}'")
        if self.refine not in REFINE_MODES:
            raise SnapsGraphError(f"--refine must be one of {', '.join(REFINE_MODES)}, not '{self.refine}'")
        # Record what actually ran in the dumped config.
        self.cfg.loops = self.loops_mode
        self.cfg.graph.refine = self.refine
        if build_map is not None:
            self.cfg.map.enabled = bool(build_map)

        self.camera = camera
        if frontend is None:
            from .frontend.odometry import StereoOdometry

            frontend = StereoOdometry(camera, self.cfg.frontend)
        self.vo = frontend
        self.snaps = None
        if self.loops_mode == "snaps":
            from .loop.snaps import SnapsLoopCloser

            self.snaps = SnapsLoopCloser(self.cfg.loop)
        self.graph = PoseGraph(self.cfg.graph, mode="isam2" if self.refine == "both" else self.refine)
        self.map = None
        if self.cfg.map.enabled:
            from .mapping.cloud_map import CloudMap

            self.map = CloudMap(camera, self.cfg.map)

        self._features: list[FrameFeatures | None] = []
        self._frame_ids: list[int] = []
        self._k_of_frame: dict[int, int] = {}
        self._timestamps: list[float] = []
        self._vo_poses: list[np.ndarray] = []
        self.loops: list[LoopEvent] = []
        self.rows: list[dict] = []
        self._t_start = time.perf_counter()

    # ---- streaming ----
    def process(self, frame: StereoFrame) -> FrameOutput:
        t0 = time.perf_counter()
        k = len(self._frame_ids)
        if frame.index in self._k_of_frame:
            raise SnapsGraphError(f"frame {frame.index} was already processed")
        self._frame_ids.append(frame.index)
        self._k_of_frame[frame.index] = k
        self._timestamps.append(float(frame.timestamp))

        vo = self.vo.process(frame)
        t1 = time.perf_counter()
        self._vo_poses.append(vo.pose)
        self._features.append(vo.features)

        loop: LoopEvent | None = None
        candidates = 0
        t_loop_ms = t_verify_ms = 0.0
        if self.snaps is not None:
            step = self.snaps.step(frame.index, vo.T_rel, frame.left, verify=lambda ref: self._verify(ref, vo))
            heuristic = step.pose
            loop, candidates, t_loop_ms, t_verify_ms = step.loop, step.candidates, step.t_ms, step.t_verify_ms
        else:
            heuristic = vo.pose

        tg = time.perf_counter()
        self.graph.add_frame(k, heuristic, None if k == 0 else vo.T_rel, inliers=vo.inliers, ok=vo.ok)
        if loop is not None:
            self._add_loop_factor(loop, vo)
        n_fail = len(self.graph.failures)
        self.graph.update()
        graph_ok = len(self.graph.failures) == n_fail
        t_graph_ms = (time.perf_counter() - tg) * 1e3

        t_map_ms = 0.0
        if self.map is not None and self.map.should_add(k):
            tm = time.perf_counter()
            self._add_map_keyframe(k, frame)
            t_map_ms = (time.perf_counter() - tm) * 1e3

        t_total_ms = (time.perf_counter() - t0) * 1e3
        self.rows.append(
            {
                "frame": frame.index,
                "timestamp": frame.timestamp,
                "t_total_ms": t_total_ms,
                "t_vo_ms": (t1 - t0) * 1e3,
                "vo_ok": int(vo.ok),
                "vo_inliers": vo.inliers,
                "vo_reason": vo.reason,
                "t_loop_ms": t_loop_ms,
                "loop_candidates": candidates,
                "loop_closed": int(loop is not None),
                "t_verify_ms": t_verify_ms,
                "t_graph_ms": t_graph_ms,
                "graph_ok": int(graph_ok),
                "t_map_ms": t_map_ms,
            }
        )
        pose = heuristic
        if self.refine in ("isam2", "both"):
            est = self.graph.estimate(k)
            if np.all(np.isfinite(est)):
                pose = est
        return FrameOutput(k, frame.index, pose, vo, loop)

    def _verify(self, ref_index: int, vo: VOResult):
        """Geometric verification of a SNAPS loop: PnP from the reference frame's 3D points to
        this frame's keypoints. Returns (T_ref_cur, inliers) or None; never raises."""
        from .frontend.verify import verify_loop

        k_ref = self._k_of_frame.get(ref_index)
        ref_feat = None if k_ref is None else self._features[k_ref]
        if ref_feat is None or vo.features is None:
            return None
        try:
            return verify_loop(ref_feat, vo.features, self.camera, self.cfg.frontend)
        except Exception as exc:  # best effort: an unverifiable candidate is not a loop
            self.graph.failures.append((len(self._frame_ids) - 1, f"loop verification raised {type(exc).__name__}: {exc}"))
            return None

    def _add_loop_factor(self, loop: LoopEvent, vo: VOResult) -> None:
        """A loop-closure factor for a SNAPS loop: measured by verification when it succeeded
        (done once, inside the SNAPS step), else the paper's same-place assumption."""
        k_ref = self._k_of_frame.get(loop.reference, -1)
        k_cur = self._k_of_frame[loop.frame]
        self.graph.add_loop(k_ref, k_cur, loop.q, loop.T_ref_cur if loop.verified else None)
        self.loops.append(loop)

    def _add_map_keyframe(self, k: int, frame: StereoFrame) -> None:
        from .frontend.depth import dense_depth

        try:
            depth = dense_depth(frame.left, frame.right, self.camera, self.cfg.frontend)
        except Exception as exc:  # a bad frame must not end the run: the keyframe is skipped
            self.graph.failures.append((k, f"map depth failed: {type(exc).__name__}: {exc}"))
            return
        self.map.add_keyframe(k, depth, frame.left)

    # ---- end of run ----
    def finish(self) -> RunResult:
        self.vo.close()
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
        return RunResult(trajs, self.loops, self.rows, list(self.graph.failures), time.perf_counter() - self._t_start)

    @property
    def frame_ids(self) -> list[int]:
        return list(self._frame_ids)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array(self._timestamps)

    def write_results(self, out_dir: str | Path, result: RunResult, gt_poses: np.ndarray | None = None) -> dict:
        """Write the results folder; returns the metrics dict (also in metrics.json)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        times = self.timestamps
        for name, poses in result.trajectories.items():
            write_kitti_poses(out / f"poses_{name}.txt", poses)
            write_tum_poses(out / f"poses_{name}.tum", poses, times)
        if gt_poses is not None:
            write_kitti_poses(out / "poses_gt.txt", gt_poses)
        atomic_write_text(out / "frames.csv", _rows_csv(result.rows))
        atomic_write_text(out / "loops.jsonl", "".join(json.dumps(l.to_json()) + "\n" for l in result.loops))
        self.cfg.dump(out / "config.toml")
        try:
            self.graph.save_g2o(out / "graph.g2o")
        except Exception as exc:  # the graph file is a convenience; never lose the run for it
            result.graph_failures.append((-1, f"graph.g2o not written: {exc}"))

        metrics = run_metrics(result, gt_poses)
        metrics["graph"] = self.graph.stats.summary()  # factor counts, solve times, gravity directions
        atomic_write_text(out / "metrics.json", _json_text(metrics))

        if self.map is not None and self.map.num_stored_points() > 0:
            name = self._map_trajectory_name(result)
            poses = result.trajectories[name]
            cloud = self.map.build(poses)  # built once, for both the PLY and the picture
            self.map.write_ply(out / "map.ply", poses, cloud=cloud)
            trajs = dict(result.trajectories)
            if gt_poses is not None:
                trajs = {"gt": gt_poses, **trajs}
            self.map.render_topdown_png(out / "map.png", poses, trajs, cloud=cloud)
            if self.cfg.map.per_trajectory:  # re-posed from the stored keyframe clouds
                for tname, tposes in result.trajectories.items():
                    self.map.write_ply(out / f"map_{tname}.ply", tposes)
            metrics["map"] = {"trajectory": name, "keyframes": len(self.map), "bytes": self.map.memory_bytes()}
            metrics["peak_rss_mb"] = peak_rss_mb()
            atomic_write_text(out / "metrics.json", _json_text(metrics))
        return metrics

    def _map_trajectory_name(self, result: RunResult) -> str:
        want = self.cfg.map.trajectory
        if want == "best":
            for name in ("batch", "isam2", "snaps", "vo"):
                if name in result.trajectories:
                    return name
        if want not in result.trajectories:
            raise SnapsGraphError(
                f"map.trajectory = '{want}' was not computed in this run (have: {', '.join(result.trajectories)})"
            )
        return want


def run_metrics(result: RunResult, gt_poses: np.ndarray | None) -> dict:
    """Per-trajectory metrics (with ground truth) and latency summaries."""
    metrics: dict = {"frames": len(result.rows), "loops": len(result.loops), "wall_s": result.wall_s}
    if gt_poses is not None:
        from .evaluation.metrics import evaluate

        metrics["trajectories"] = {name: evaluate(p, gt_poses) for name, p in result.trajectories.items()}
    metrics["latency_ms"] = latency_summary(result.rows)
    metrics["peak_rss_mb"] = peak_rss_mb()
    metrics["graph_failures"] = [{"k": k, "reason": r} for k, r in result.graph_failures]
    return metrics


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports ru_maxrss in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def latency_summary(rows: list[dict]) -> dict:
    """metrics.json's ``latency_ms`` from the per-frame rows (one implementation: the report's)."""
    from .evaluation.report import latency_summary as _summary

    cols = ("t_total_ms", "t_vo_ms", "t_loop_ms", "loop_candidates", "loop_closed", "t_graph_ms")
    return _summary({c: np.array([r[c] for r in rows], float) for c in cols})


def _rows_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=FRAME_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.4f}" if isinstance(v, float) and k != "timestamp" else v) for k, v in r.items()})
    return buf.getvalue()


def _json_text(obj) -> str:
    """Strict JSON: a metric that cannot be computed (NaN) is written as null."""
    from .evaluation.report import json_clean

    return json.dumps(json_clean(obj), indent=2) + "\n"


def run_sequence(
    dataset,
    out_dir: str | Path,
    cfg: Config | None = None,
    *,
    loops: str | None = None,
    refine: str | None = None,
    build_map: bool | None = None,
    on_frame: Callable[[FrameOutput], None] | None = None,
) -> tuple[RunResult, dict]:
    """Run a whole dataset (KittiSequence or SyntheticSequence) and write the results folder."""
    pipe = SlamPipeline(dataset.camera, cfg, loops=loops, refine=refine, build_map=build_map)
    for frame in dataset:
        out = pipe.process(frame)
        if on_frame is not None:
            on_frame(out)
    result = pipe.finish()
    metrics = pipe.write_results(out_dir, result, dataset.gt_poses)
    return result, metrics
