"""SIFT / ORB mode (the paper's front end): keypoints detected in every frame, matched to the
reference's by descriptor with Lowe's ratio test, PnP (+ the stereo BA). Dense depth (BM + WLS,
SGBM) runs beside keypoint detection, sparse depth beside matching + PnP."""

from __future__ import annotations

import time

import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..types import StereoFrame
from . import depth as depth_mod
from . import features as feat
from .keyframe import MIN_STEREO_POINTS, Keyframe, Stereo, conclude, make_keyframe, reject
from .motion import Flag, pnp_ransac, refine_motion
from .threads import Workers
from .tracking import Estimate


class DescriptorMatcher:
    def __init__(self, camera: StereoCamera, cfg: FrontendConfig, stereo: Stereo, workers: Workers):
        self.camera, self.cfg, self.stereo, self.workers = camera, cfg, stereo, workers

    def _detect(self, img: np.ndarray):
        if self.cfg.mode == "sift":
            return feat.detect_sift(img, self.cfg)
        return feat.detect_orb(img)

    def estimate(
        self, frame: StereoFrame, ref: Keyframe | None, first: bool, sharp: float, timings: dict[str, float]
    ) -> Estimate:
        """Match ``ref`` to ``frame``; raises Flag."""
        cfg, cam = self.cfg, self.camera
        dense = cfg.disparity in depth_mod.DENSE_METHODS

        def dense_task():
            t = time.perf_counter()
            dm = depth_mod.dense_disparity(frame.left, frame.right, cfg)
            return dm, (time.perf_counter() - t) * 1000.0

        t0 = time.perf_counter()
        dense_future = self.workers.submit(dense_task) if dense else None
        uv, desc = self._detect(frame.left)
        timings["features"] = (time.perf_counter() - t0) * 1000.0

        def depth_task():
            if dense_future is not None:
                disp_map, ms = dense_future.result()
                t = time.perf_counter()
                disp = depth_mod.sample_depth(disp_map, uv)  # nearest-pixel disparity
                z = depth_mod.depth_from_disparity(self.stereo.true(uv, disp), cam, cfg)
                return z, disp, ms + (time.perf_counter() - t) * 1000.0
            t = time.perf_counter()
            z, disp = self.stereo.depth(frame.left, frame.right, uv)
            return z, disp, (time.perf_counter() - t) * 1000.0

        depth_future = None if dense else self.workers.submit(depth_task)
        result = None
        n_matches = 0
        if not first and ref is not None and ref.desc is not None and len(ref.desc):
            t1 = time.perf_counter()
            ia, ib = feat.match_descriptors(ref.desc, desc, feat.RATIO_TEST)
            timings["match"] = (time.perf_counter() - t1) * 1000.0
            n_matches = len(ia)
            t2 = time.perf_counter()
            result = pnp_ransac(ref.pts3d[ia], uv[ib], cam, cfg)
            timings["pnp"] = (time.perf_counter() - t2) * 1000.0
        z, disp, timings["depth"] = depth_task() if depth_future is None else depth_future.result()
        kf = make_keyframe(frame, uv, z, disp, desc, sharp, cam, cfg, timings)
        if first:
            if len(kf.uv) < MIN_STEREO_POINTS:
                raise Flag("too few keypoints with stereo depth")
            return kf, np.eye(4), 0, 0, None
        if ref is None:
            reject(kf, "no reference frame to match against", cfg)
        gap = max(1, frame.index - ref.index)
        if result is None:
            reject(kf, f"PnP failed ({n_matches} matches)", cfg)
        T_cur_ref, inl = result
        T_cur_ref, inl, cov = refine_motion(
            T_cur_ref, inl, ref.uv[ia], ref.disp[ia], uv[ib], disp[ib], cam, cfg, self.stereo.true, timings
        )
        T_ref_cur = conclude(kf, T_cur_ref, len(inl), gap, "", cfg)
        return kf, T_ref_cur, len(inl), n_matches, cov
