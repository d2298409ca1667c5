"""KLT mode: corners tracked from the reference into the current frame with pyramidal LK, PnP and
the stereo BA on the tracks, re-detection where tracks ran out, an ORB retry at speed
(docs/frontend.md)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..types import StereoFrame
from . import depth as depth_mod
from . import features as feat
from .depth import offset_gain
from .keyframe import MIN_STEREO_POINTS, Keyframe, Stereo, conclude, make_keyframe, reject
from .motion import MIN_INLIERS, Flag, pnp_ransac, project, refine_motion
from .threads import Workers

KLT_MIN_TRACKS = 600  # re-detect corners when fewer tracks with depth than this survive
KLT_RETRY_FEATURES = 4000  # ORB keypoints per image when a failed KLT frame is retried on ORB matches
KLT_WEAK_QUALITY = 0.001  # goodFeaturesToTrack quality of the weak-texture re-detection

# (keyframe of this frame, T_ref_cur, inliers, matches, the stereo BA's covariance of the step)
Estimate = tuple[Keyframe, np.ndarray, int, int, np.ndarray | None]


class KltTracker:
    """Frame-to-frame KLT tracking with persistent landmark ids (the local BA's tracks)."""

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig, stereo: Stereo, workers: Workers):
        self.camera, self.cfg, self.stereo, self.workers = camera, cfg, stereo, workers
        self._next_id = 0

    def estimate(
        self,
        frame: StereoFrame,
        ref: Keyframe | None,
        first: bool,
        predict: Callable[[int], np.ndarray | None],
        sharp: float,
        timings: dict[str, float],
    ) -> Estimate:
        """Track ``ref`` into ``frame``; ``predict(gap)`` is the constant-velocity T_cur_ref (or None). Raises Flag."""
        cfg, cam = self.cfg, self.camera
        if first or ref is None:
            z, d = self._stereo_tracked(frame, np.zeros((0, 2), np.float32), None, timings)
            new_uv, z2, d2 = self._detect_new(frame, np.zeros((0, 2), np.float32), z, timings)
            kf = make_keyframe(frame, new_uv, z2, d2, None, sharp, cam, cfg, timings, ids=self._new_ids(len(new_uv)))
            if not first:
                reject(kf, "no reference frame to track from", cfg)
            elif len(kf.uv) < MIN_STEREO_POINTS:
                raise Flag("too few keypoints with stereo depth")
            return kf, np.eye(4), 0, 0, None
        gap = max(1, frame.index - ref.index)
        t0 = time.perf_counter()
        pred = predict(gap)
        guess = None
        dguess = ref.disp
        if pred is not None:
            guess, zp = project(pred, ref.pts3d, cam)
            guess = np.where((zp > 0)[:, None], guess, ref.uv)
            if depth_mod.STEREO_GUESS_LEVELS < depth_mod.STEREO_LEVELS:  # predict the disparity too
                dp = cam.fx * cam.baseline_m / np.maximum(zp, 1e-6)
                gain = offset_gain(guess[:, 0], dp, cam)
                dguess = np.where(zp > 0, dp + self.stereo.offset() * gain, ref.disp)
        uv_cur, ok = feat.track_klt(ref.left, frame.left, ref.uv, feat.KLT, guess)
        idx = np.flatnonzero(ok)
        timings["match"] = (time.perf_counter() - t0) * 1000.0
        stereo = self.workers.submit(self._stereo_tracked, frame, uv_cur[idx], dguess[idx], timings)
        t1 = time.perf_counter()
        pnp = pnp_ransac(ref.pts3d[idx], uv_cur[idx], cam, cfg)
        timings["pnp"] = (time.perf_counter() - t1) * 1000.0
        z, d = stereo.result()
        detection = self.workers.submit(self._detect_new, frame, uv_cur[idx], z, timings)
        cov = None
        if pnp is None:
            keep = np.ones(len(idx), bool)
            T_cur_ref, n_inl = None, 0
        else:
            T_cur_ref, inl = pnp
            T_cur_ref, inl, cov = refine_motion(
                T_cur_ref, inl, ref.uv[idx], ref.disp[idx], uv_cur[idx], d, cam, cfg, self.stereo.true, timings
            )
            n_inl = len(inl)
            keep = np.zeros(len(idx), bool)
            keep[inl] = True  # drop PnP outliers: mostly bad tracks
        if n_inl < MIN_INLIERS and ref.right is not None:
            retry = self._orb_retry(ref, frame, (ref.pts3d[idx], ref.uv[idx], ref.disp[idx], uv_cur[idx], d), timings)
            if retry is not None and len(retry[1]) > n_inl:
                T_cur_ref, n_inl, cov = retry[0], len(retry[1]), retry[2]
                keep = np.zeros(len(idx), bool)  # keep the KLT tracks among the inliers
                keep[retry[1][retry[1] < len(idx)]] = True
                timings["retry_ok"] = 1.0
        new_uv, z2, d2 = detection.result()
        uv_next = np.concatenate([uv_cur[idx][keep], new_uv])
        z_next = np.concatenate([z[keep], z2])
        d_next = np.concatenate([d[keep], d2])
        ids_next = np.concatenate([ref.ids[idx][keep], self._new_ids(len(new_uv))])
        kf = make_keyframe(frame, uv_next, z_next, d_next, None, sharp, cam, cfg, timings, ids=ids_next)
        T_ref_cur = conclude(kf, T_cur_ref, n_inl, gap, f"PnP failed ({len(idx)} tracks)", cfg)
        return kf, T_ref_cur, n_inl, len(idx), cov

    def _new_ids(self, n: int) -> np.ndarray:
        """Fresh landmark ids for ``n`` newly detected points."""
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def _stereo_tracked(self, frame: StereoFrame, uv: np.ndarray, guess: np.ndarray | None, timings: dict[str, float]):
        """Stereo (depth, disparity) at the tracked points."""
        t0 = time.perf_counter()
        z, d = self.stereo.depth(frame.left, frame.right, uv, guess)
        timings["depth"] = (time.perf_counter() - t0) * 1000.0
        return z, d

    def _detect_new(self, frame: StereoFrame, uv: np.ndarray, z: np.ndarray, timings: dict[str, float]):
        """If fewer tracked points ``uv`` than ``KLT_MIN_TRACKS`` have depth ``z``: new corners
        away from them, with their stereo (new uv, depth, disparity); once more at
        ``KLT_WEAK_QUALITY`` in weak texture under a far field."""
        n_valid = int(np.count_nonzero(z > 0))
        new_uv = np.zeros((0, 2), np.float32)
        z2, d2 = np.zeros(0, np.float32), np.zeros(0, np.float32)
        ms = {"depth": 0.0, "features": 0.0}

        def add_corners(quality: float) -> None:
            nonlocal new_uv, z2, d2
            t = time.perf_counter()
            n = feat.KLT.features - n_valid - int(np.count_nonzero(z2 > 0))
            qcfg = feat.KLT if quality == feat.KLT.quality else dataclasses.replace(feat.KLT, quality=quality)
            extra = feat.detect_corners(frame.left, n, qcfg, avoid=np.concatenate([uv[z > 0], new_uv]))
            t_det = time.perf_counter()
            if len(extra):
                z3, d3 = self.stereo.depth(frame.left, frame.right, extra)
                new_uv, z2, d2 = np.concatenate([new_uv, extra]), np.concatenate([z2, z3]), np.concatenate([d2, d3])
            ms["features"] += (t_det - t) * 1000.0
            ms["depth"] += (time.perf_counter() - t_det) * 1000.0

        if n_valid < KLT_MIN_TRACKS:
            add_corners(feat.KLT.quality)
            # Only where the far field took the ranking: most new corners lie beyond max_depth_m
            # (a valid disparity); where stereo failed on them, more corners would not help.
            far = int(np.count_nonzero((d2 > 0) & (z2 <= 0)))
            weak = n_valid + int(np.count_nonzero(z2 > 0)) < feat.KLT.weak_points and 2 * far > len(new_uv)
            if weak and KLT_WEAK_QUALITY < feat.KLT.quality:
                add_corners(KLT_WEAK_QUALITY)
        timings["depth"] = timings.get("depth", 0.0) + ms["depth"]
        timings["features"] = ms["features"]
        return new_uv, z2, d2

    def _orb_retry(self, ref: Keyframe, frame: StereoFrame, klt: tuple, timings: dict[str, float]):
        """Motion from ``KLT_RETRY_FEATURES`` ORB keypoints detected afresh in the reference and
        this frame, matched by descriptor (scale-invariant, so they survive the looming and the
        large flow of a fast drive that KLT does not), together with the KLT correspondences
        ``klt`` = (ref points 3D, ref uv, ref disparity, cur uv, cur disparity): PnP RANSAC on
        the union, then the stereo BA. (T_cur_ref, inliers: indices into the union, the KLT ones
        first, covariance) or None."""
        cfg, cam = self.cfg, self.camera
        assert ref.right is not None
        t0 = time.perf_counter()
        uv_r, desc_r = feat.detect_orb(ref.left, KLT_RETRY_FEATURES)
        z_r, d_r = self.stereo.depth(ref.left, ref.right, uv_r)
        has_depth = np.flatnonzero(z_r > 0)
        uv_c, desc_c = feat.detect_orb(frame.left, KLT_RETRY_FEATURES)
        ia, ib = feat.match_descriptors(desc_r[has_depth], desc_c, feat.RATIO_TEST)
        ia = has_depth[ia]
        k_pts, k_ruv, k_rd, k_cuv, k_cd = klt
        res = None
        if len(ia) + len(k_pts) >= max(6, MIN_INLIERS):
            pts = np.concatenate([k_pts, cam.backproject(uv_r[ia, 0], uv_r[ia, 1], z_r[ia])]).astype(np.float64)
            cur_uv = np.concatenate([k_cuv, uv_c[ib]]).astype(np.float32)
            res = pnp_ransac(pts, cur_uv, cam, cfg)
        out: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None if res is None else (res[0], res[1], None)
        if res is not None and cfg.motion == "stereo_ba":
            _, d_c = depth_mod.sparse_depth(frame.left, frame.right, uv_c[ib], cam, cfg)
            out = refine_motion(
                res[0],
                res[1],
                np.concatenate([k_ruv, uv_r[ia]]).astype(np.float32),
                np.concatenate([k_rd, d_r[ia]]).astype(np.float32),
                cur_uv,
                np.concatenate([k_cd, d_c]).astype(np.float32),
                cam,
                cfg,
                self.stereo.true,
                timings,
            )
        timings["retry"] = (time.perf_counter() - t0) * 1000.0
        return out
