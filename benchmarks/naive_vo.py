"""The paper's front end written plainly (sequential, full-image dense depth): the yardstick of
``bench_frontend.py`` and ``bench_pipeline.py``. A module, not a script."""

from __future__ import annotations

import time

import cv2
import numpy as np

from snaps_graph.config import FrontendConfig
from snaps_graph.frontend.depth import BM_BLOCK_SIZE, WLS_LAMBDA, WLS_SIGMA
from snaps_graph.frontend.features import RATIO_TEST, SIFT_FEATURES
from snaps_graph.frontend.motion import PNP_CONFIDENCE, PNP_ITERATIONS, PNP_REPROJECTION_PX
from snaps_graph.geometry import inv


class NaiveVO:
    """The paper's front end, written plainly (sequential, full-image dense depth)."""

    def __init__(self, camera, cfg: FrontendConfig):
        self.cam, self.cfg = camera, cfg
        self.bm = cv2.StereoBM.create(cfg.num_disparities, BM_BLOCK_SIZE)
        self.rbm = cv2.ximgproc.createRightMatcher(self.bm)
        self.wls = cv2.ximgproc.createDisparityWLSFilter(self.bm)
        self.wls.setLambda(WLS_LAMBDA)
        self.wls.setSigmaColor(WLS_SIGMA)
        self.sift = cv2.SIFT.create(SIFT_FEATURES)
        self.bf = cv2.BFMatcher(cv2.NORM_L2)
        self.prev = None
        self.pose = np.eye(4)

    def process(self, frame):
        t = {}
        t0 = time.perf_counter()
        disp = (
            self.wls.filter(
                self.bm.compute(frame.left, frame.right),
                frame.left,
                disparity_map_right=self.rbm.compute(frame.right, frame.left),
            ).astype(np.float32)
            / 16
        )
        depth = np.where(disp > 0, self.cam.fx * self.cam.baseline_m / np.maximum(disp, 1e-6), 0)
        depth[depth > self.cfg.max_depth_m] = 0
        t1 = time.perf_counter()
        kps, desc = self.sift.detectAndCompute(frame.left, None)
        uv = np.array([k.pt for k in kps], np.float64)
        t2 = time.perf_counter()
        ok = True
        if self.prev is not None:
            puv, pdesc, pdepth = self.prev
            good = [
                m[0] for m in self.bf.knnMatch(pdesc, desc, k=2) if len(m) == 2 and m[0].distance < RATIO_TEST * m[1].distance
            ]
            t3 = time.perf_counter()
            a = np.array([m.queryIdx for m in good])
            b = np.array([m.trainIdx for m in good])
            z = pdepth[np.rint(puv[a, 1]).astype(int), np.rint(puv[a, 0]).astype(int)]
            v = z > 0
            pts = self.cam.backproject(puv[a[v], 0], puv[a[v], 1], z[v])
            res = cv2.solvePnPRansac(
                pts,
                uv[b[v]],
                self.cam.K,
                None,
                iterationsCount=PNP_ITERATIONS,
                reprojectionError=PNP_REPROJECTION_PX,
                confidence=PNP_CONFIDENCE,
            )
            ok = bool(res[0])
            if ok:
                T = np.eye(4)
                T[:3, :3] = cv2.Rodrigues(res[1])[0]
                T[:3, 3] = res[2].ravel()
                self.pose = self.pose @ inv(T)
            t4 = time.perf_counter()
            t.update(match=(t3 - t2) * 1e3, pnp=(t4 - t3) * 1e3)
        self.prev = (uv, desc, depth)
        t.update(depth=(t1 - t0) * 1e3, features=(t2 - t1) * 1e3, total=(time.perf_counter() - t0) * 1e3)
        return self.pose.copy(), ok, t
