"""Stream a run to the rerun viewer (``--viewer``) and/or record it to an ``.rrd`` file (``--rrd``).

``RerunLogger`` is a ``SlamPipeline`` observer (``on_frame`` after each frame, ``on_finish`` at
the end) that reads what the pipeline already has and computes nothing the run needs; without
``--viewer``/``--rrd`` rerun is not even imported. What it logs: docs/usage.md, "run".
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from ..errors import SnapsGraphError
from ..locks import writer_lock

TRAJ_COLOURS = {"gt": (150, 150, 150), "vo": (230, 80, 60), "snaps": (60, 140, 240), "refined": (60, 200, 90)}
PRIOR_COLOUR = (120, 120, 200)  # a prior session's trajectory


def _import_rerun():
    try:
        import rerun as rr
        import rerun.blueprint as rrb
    except ImportError:
        raise SnapsGraphError("--viewer/--rrd need the 'rerun-sdk' package: pip install 'snaps_graph[viewer]'") from None
    return rr, rrb


def _check_display() -> None:
    """The viewer is a desktop window: on Linux without a display it cannot open (it would fail in
    its own process while the run streams into nothing), so say so before the run starts."""
    import os
    import sys

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise SnapsGraphError(
            "--viewer: no display (DISPLAY/WAYLAND_DISPLAY unset); record with --rrd FILE and open it with `rerun FILE`"
        )


def _viewer_on_path() -> None:
    """rerun's spawn looks for the ``rerun`` executable on PATH; a venv used without activating it
    has it beside its python, so that folder is appended to PATH."""
    import os
    import sys

    here = os.path.dirname(sys.executable)
    if os.path.isfile(os.path.join(here, "rerun")) and here not in os.environ.get("PATH", "").split(os.pathsep):
        os.environ["PATH"] = os.environ.get("PATH", "") + os.pathsep + here


def blueprint():
    """The layout the viewer opens on: 3D trajectories and map left; image, plots, loops right."""
    _rr, rrb = _import_rerun()
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="trajectories and map"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="left image, tracked features"),
                rrb.TimeSeriesView(origin="metrics", contents=["metrics/frame_ms", "metrics/vo_ms"], name="frame time (ms)"),
                rrb.TimeSeriesView(origin="metrics", contents=["metrics/inliers"], name="PnP inliers"),
                rrb.TimeSeriesView(origin="metrics", contents=["metrics/q"], name="loop Q"),
                rrb.TextLogView(origin="loops", name="loops"),
                row_shares=[3, 1, 1, 1, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


RRD_JPEG_QUALITY = 75  # `run --rrd` images: a KITTI frame 0.46 MB raw, about 0.1 MB as JPEG 75


class RerunLogger:
    """Log a run to rerun. ``spawn``: start a viewer and stream to it; ``rrd``: record to a file
    (both may be given). ``recording``: an existing ``rr.RecordingStream`` (tests)."""

    def __init__(
        self,
        camera,
        *,
        spawn: bool = False,
        rrd: str | Path | None = None,
        name: str = "snaps_graph",
        gt_poses: np.ndarray | None = None,
        path_every: int = 10,
        max_map_points: int = 4000,
        recording=None,
        image_every: int = 1,
        jpeg_quality: int | None = None,
    ):
        """With ``rrd``, a recording thinned for its size (a raw KITTI image is 0.46 MB): the camera
        image (and its features) every ``image_every`` frames, JPEG-compressed at ``jpeg_quality``
        (default ``RRD_JPEG_QUALITY``). A viewer alone gets every image, raw."""
        if rrd is None:
            image_every = 1
        elif jpeg_quality is None:
            jpeg_quality = RRD_JPEG_QUALITY
        rr, _rrb = _import_rerun()
        self.rr = rr
        self.camera = camera
        self.path_every = max(1, int(path_every))
        self.image_every = max(1, int(image_every))
        self.jpeg_quality = None if jpeg_quality is None else int(jpeg_quality)
        self.max_map_points = int(max_map_points)
        self._n_map = 0
        self._vo_poses: list[np.ndarray] = []
        self._k_of_frame: dict[int, int] = {}
        self._series: dict[str, list] = {"frame": [], "time": [], "frame_ms": [], "vo_ms": [], "inliers": []}
        self._loop_segments: list[np.ndarray] = []
        self._loop_labels: list[str] = []
        self._rrd: Path | None = None
        self._rrd_tmp: Path | None = None
        self._lock = contextlib.ExitStack()
        if recording is not None:
            self.rec = recording
        else:
            self.rec = rr.RecordingStream("snaps_graph", recording_id=None)
            bp = blueprint()
            sinks = []
            if spawn:
                _check_display()
                _viewer_on_path()
                try:
                    self.rec.spawn(connect=False)
                except Exception as exc:  # no viewer binary, no display
                    raise SnapsGraphError(
                        f"--viewer: cannot start the rerun viewer ({str(exc).strip().splitlines()[0]})"
                    ) from None
                sinks.append(rr.GrpcSink())
            if rrd is not None:  # written under a temporary name, renamed by close(): whole or absent
                self._rrd = Path(rrd)
                self._rrd.parent.mkdir(parents=True, exist_ok=True)
                self._lock.enter_context(writer_lock(self._rrd))  # one run per recording, until close()
                self._rrd_tmp = self._rrd.parent / f".{self._rrd.name}.tmp-{os.getpid()}"
                sinks.append(rr.FileSink(str(self._rrd_tmp)))
            self.rec.set_sinks(*sinks, default_blueprint=bp)
            self.rec.send_recording_name(name)
        self._log_static(gt_poses)

    # ---- static content ----
    def _log_static(self, gt_poses) -> None:
        rr, rec, cam = self.rr, self.rec, self.camera
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        # Styling once, as static components: per frame only the data is logged.
        rec.log(
            "world/camera/image/features",
            rr.Points2D.from_fields(colors=[(255, 200, 0)], radii=rr.Radius.ui_points(2.0)),
            static=True,
        )
        rec.log(
            "world/camera/image",
            rr.Pinhole(
                image_from_camera=cam.K,
                resolution=[cam.width or 2 * cam.cx, cam.height or 2 * cam.cy],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.5,
            ),
            static=True,
        )
        rec.log("metrics/frame_ms", rr.SeriesLines(names="frame ms", colors=[(230, 160, 40)]), static=True)
        rec.log("metrics/vo_ms", rr.SeriesLines(names="VO ms", colors=[(120, 120, 220)]), static=True)
        rec.log("metrics/inliers", rr.SeriesLines(names="inliers", colors=[(60, 200, 90)]), static=True)
        rec.log("metrics/q", rr.SeriesPoints(names="Q", colors=[(240, 60, 200)], markers="circle", marker_sizes=4), static=True)
        if gt_poses is not None:
            rec.log(
                "world/trajectory/gt",
                rr.LineStrips3D([gt_poses[:, :3, 3]], colors=[TRAJ_COLOURS["gt"]], radii=rr.Radius.ui_points(1.0)),
                static=True,
            )

    # ---- observer hooks ----
    def on_frame(self, pipe, frame, out) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=int(frame.index))
        rec.set_time("time", duration=float(frame.timestamp))
        pose = np.asarray(out.pose)
        self._vo_poses.append(np.asarray(out.vo.pose))  # the run's own frame: shown in the outputs' frame
        self._k_of_frame[int(out.frame)] = int(out.k)
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        if out.k % self.image_every == 0:
            image = rr.Image(frame.left, color_model="L")
            rec.log("world/camera/image", image if self.jpeg_quality is None else image.compress(jpeg_quality=self.jpeg_quality))
            feats = out.vo.features
            uv = feats.uv if feats is not None else np.zeros((0, 2), np.float32)
            rec.log("world/camera/image/features", rr.Points2D.from_fields(positions=uv))
        row = pipe.records[-1] if pipe.records else None
        ser = self._series
        ser["frame"].append(int(frame.index))
        ser["time"].append(float(frame.timestamp))
        ser["frame_ms"].append(float(row.t_total_ms) if row is not None else np.nan)
        ser["vo_ms"].append(float(row.t_vo_ms) if row is not None else np.nan)
        ser["inliers"].append(float(out.vo.inliers))
        if out.loop is not None:
            self._log_loop(pipe, out.loop)
        if pipe.map is not None and len(pipe.map) > self._n_map:
            self._log_keyframe(pipe, out)
        if out.loop is not None or out.k % self.path_every == 0:
            self._log_paths(pipe)
            self._send_series()

    def on_finish(self, pipe, result) -> None:
        trajs = result.trajectories
        self._send_series()
        self._log_paths(pipe, trajs)
        refined = trajs.get("batch", trajs.get("isam2", trajs.get("snaps", trajs["vo"])))
        if pipe.map is not None:  # re-pose the keyframe clouds with the final trajectory
            for k in pipe.map.keyframes:
                self._log_kf_pose(k, refined[k])

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush and disconnect. A viewer that went away (closed, or no display to open on) costs
        a one-line warning, never the run."""
        import sys

        try:
            self.rec.flush(timeout_sec=timeout_s)
        except Exception as exc:
            print(f"warning: rerun: {str(exc).strip().splitlines()[0]}", file=sys.stderr)
        self.rec.disconnect()
        if self._rrd_tmp is not None and self._rrd is not None:
            os.replace(self._rrd_tmp, self._rrd)
            self._rrd_tmp = None
        self._lock.close()

    def abort(self) -> None:
        """The run failed: disconnect and delete the unfinished recording."""
        self.rec.disconnect()
        if self._rrd_tmp is not None:
            self._rrd_tmp.unlink(missing_ok=True)
            self._rrd_tmp = None
        self._lock.close()

    # ---- pieces ----
    def _positions(self, pipe, trajs: dict | None = None) -> dict[str, np.ndarray]:
        if trajs is not None:
            out = {"vo": trajs["vo"][:, :3, 3]}
            if "snaps" in trajs:
                out["snaps"] = trajs["snaps"][:, :3, 3]
            for name in ("batch", "isam2"):
                if name in trajs:
                    out["refined"] = trajs[name][:, :3, 3]
                    break
            return out
        # The pipeline's own frame, shown in the outputs' (a prior's, once the run relocalised).
        out = {"vo": pipe.to_output(np.array(self._vo_poses))[:, :3, 3]}
        if pipe.snaps is not None:
            out["snaps"] = pipe.to_output(np.asarray(pipe.snaps.poses))[:, :3, 3]
        if pipe.refine in ("isam2", "both"):
            est = pipe.graph.estimates()
            if len(est) and np.all(np.isfinite(est)):
                out["refined"] = pipe.to_output(np.asarray(est))[:, :3, 3]
        for i, poses in pipe.prior_trajectories().items():
            out[f"prior{i}"] = poses[:, :3, 3]
        return out

    def _send_series(self) -> None:
        """The time series gathered since the last call, as columns (one message per series)."""
        ser = self._series
        if not ser["frame"]:
            return
        rr = self.rr
        idx = [rr.TimeColumn("frame", sequence=ser["frame"]), rr.TimeColumn("time", duration=ser["time"])]
        for name in ("frame_ms", "vo_ms", "inliers"):
            self.rec.send_columns(f"metrics/{name}", indexes=idx, columns=rr.Scalars.columns(scalars=ser[name]))
        for v in ser.values():
            v.clear()

    def _log_paths(self, pipe, trajs: dict | None = None) -> None:
        rr = self.rr
        for name, xyz in self._positions(pipe, trajs).items():
            if len(xyz) >= 2:
                self.rec.log(
                    f"world/trajectory/{name}",
                    rr.LineStrips3D([xyz], colors=[TRAJ_COLOURS.get(name, PRIOR_COLOUR)], radii=rr.Radius.ui_points(1.5)),
                )

    def _log_loop(self, pipe, loop) -> None:
        rr, snaps = self.rr, pipe.snaps
        k_cur = self._k_of_frame.get(loop.frame)
        ref = None  # the reference's pose in the run's own frame
        if loop.session and snaps is not None:  # a prior's frame: where the run placed it
            prior = snaps.priors[loop.prior]
            ref = prior.pose_own(prior.position(loop.reference))
        elif snaps is not None and loop.reference in self._k_of_frame:
            ref = snaps.pose(self._k_of_frame[loop.reference])
        if snaps is not None and ref is not None and k_cur is not None:
            # Only the segment's two ends, not the whole heuristic trajectory, in the outputs' frame.
            self._loop_segments.append(pipe.to_output(np.stack([snaps.pose(k_cur), ref]))[:, :3, 3])
            self._loop_labels.append(f"Q {loop.q:.2f}")
            self.rec.log(
                "world/loops",
                rr.LineStrips3D(
                    self._loop_segments, colors=[(240, 60, 200)], labels=self._loop_labels, radii=rr.Radius.ui_points(2.0)
                ),
            )
        text = (
            f"frame {loop.frame} -> {loop.reference}: Q {loop.q:.3f} = correlation {loop.correlation:.3f} x luminance "
            f"{loop.luminance:.3f} x contrast {loop.contrast:.3f}; {'verified (' + str(loop.verify_inliers) + ' inliers)' if loop.verified else 'unverified'}, "
            f"moved {float(np.linalg.norm(loop.delta)):.2f} m, {loop.n_corrected} poses corrected"
        )
        self.rec.log("loops", rr.TextLog(text, level="INFO"))
        self.rec.log("metrics/q", rr.Scalars(float(loop.q)))

    def _log_keyframe(self, pipe, out) -> None:
        rr, k = self.rr, out.k
        self._n_map = len(pipe.map)
        if k not in pipe.map.keyframes:
            return
        xyz, colour = pipe.map.keyframe_cloud(k)
        if len(xyz) > self.max_map_points:
            pick = np.linspace(0, len(xyz) - 1, self.max_map_points).astype(np.int64)
            xyz = xyz[pick]
            colour = colour[pick] if colour is not None else None
        if colour is not None and colour.ndim == 1:
            colour = np.repeat(colour[:, None], 3, axis=1)
        self.rec.log(f"world/map/kf_{k}", rr.Points3D(xyz, colors=colour, radii=rr.Radius.ui_points(1.0)))
        self._log_kf_pose(k, out.pose)

    def _log_kf_pose(self, k: int, pose: np.ndarray) -> None:
        pose = np.asarray(pose)
        self.rec.log(f"world/map/kf_{k}", self.rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
