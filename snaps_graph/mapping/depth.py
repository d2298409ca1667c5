"""Depth for the map: a stricter dense stereo than the front end's (nothing filled in, a pixel
kept only where all the evidence agrees), at the map's working size (docs/decisions.md, "Map")."""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig, MapConfig
from ..frontend.depth import check_stereo_pair, correct_disparity

DEPTH_TEXTURE_THRESHOLD = 10  # map StereoBM: minimum local texture (prefiltered sum)
DEPTH_SPECKLE_RANGE_PX = 1.0  # map speckle filter: neighbours within this disparity form one region
# The map's matcher (docs/decisions.md, "Map"): a pixel is kept only where all the evidence agrees.
MAP_DEPTH_METHOD = "sgbm"  # SGBM, not the paper's BM: BM keeps far fewer valid pixels (docs/decisions.md, "Map")
MAP_BLOCK_SIZE = 5  # matcher block at the working size, px (odd; BM needs >= 5)
MAP_UNIQUENESS = 15  # the best match must beat the second by this, percent
MAP_LR_CHECK_PX = 1.0  # left-right consistency limit, px (0 = off)
MAP_MIN_CONFIDENCE = 0.0  # WLS confidence (0-255) below this is invalid; 0 = no WLS pass (it fills across edges)
MAP_EDGE_RATIO = 0.1  # invalid where the 3x3 disparity spread exceeds this x d: a blend of two depths
MAP_SPECKLE_PX = 50  # disparity regions smaller than this are dropped, working px


def map_camera(camera: StereoCamera, scale: float, width: int, height: int) -> StereoCamera:
    """The camera of images resized by ``scale`` from ``width`` x ``height`` (pixel centres kept:
    c' = (c + 0.5) s - 0.5), sized to the resized image."""
    w, h = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
    sx, sy = w / width, h / height
    return StereoCamera(
        camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5, (camera.cy + 0.5) * sy - 0.5, camera.baseline_m, w, h
    )


def map_depth(
    left: np.ndarray, right: np.ndarray, camera: StereoCamera, cfg: FrontendConfig, mcfg: MapConfig, offset_px: float = 0.0
) -> np.ndarray:
    """Depth for the map: float32 metres at the working size (``map_camera(camera,
    mcfg.depth_scale, W, H)``), 0 = invalid. Unlike ``dense_depth`` nothing is filled in: a pixel
    is kept only when all the evidence agrees --

    - the matcher found it (StereoBM's texture threshold and uniqueness ratio; SGBM's uniqueness),
    - left-right consistency: the right image's own disparity map (``createRightMatcher``) at the
      matched pixel agrees within ``MAP_LR_CHECK_PX`` (SGBM: also its built-in
      ``disp12MaxDiff``, which alone does the check when no confidence map is wanted),
    - optionally the WLS filter's confidence map (``getConfidenceMap``) is at least
      ``MAP_MIN_CONFIDENCE`` (the filtered disparity itself is never used: WLS fills across
      depth edges and into the sky),
    - it is not on a depth edge: the 3x3 spread of disparity is at most ``MAP_EDGE_RATIO`` x d
      (pixels straddling an edge get a blend of both depths),
    - it is not in a speckle: a connected region of similar disparity of at least
      ``MAP_SPECKLE_PX`` pixels (``cv2.filterSpeckles``),
    - eq. 1, on the disparity corrected for the front end's offset ``offset_px`` (full-size
      pixels, ``true_disparity``), puts it within [``cfg.min_depth_m``, ``mcfg.max_range_m``].
    """
    check_stereo_pair(left, right)
    h0, w0 = left.shape
    cam = map_camera(camera, mcfg.depth_scale, w0, h0)
    if (cam.width, cam.height) != (w0, h0):
        left = cv2.resize(left, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    # frontend.num_disparities at full size, scaled; at most the image width
    ndisp = max(16, min(16 * int(np.ceil(cfg.num_disparities * mcfg.depth_scale / 16)), 16 * (cam.width // 16)))
    matcher = _matcher(ndisp)
    disp_l = matcher.compute(left, right)  # int16, x16; < 0 = no match
    d = disp_l.astype(np.float32) / 16.0
    valid = d > 0
    if (MAP_LR_CHECK_PX > 0 and MAP_DEPTH_METHOD == "bm") or MAP_MIN_CONFIDENCE > 0:
        _right_checks(matcher, left, right, disp_l, d, valid)
    if MAP_EDGE_RATIO > 0:
        kernel = np.ones((3, 3), np.uint8)
        hi = cv2.dilate(np.where(valid, d, 0.0).astype(np.float32), kernel)
        lo = cv2.erode(np.where(valid, d, np.float32(1e6)).astype(np.float32), kernel)
        valid &= (hi - lo) <= MAP_EDGE_RATIO * d
    if MAP_SPECKLE_PX > 0:
        d16 = np.where(valid, disp_l, np.int16(-16)).astype(np.int16)
        cv2.filterSpeckles(d16, -16, int(MAP_SPECKLE_PX), int(round(16 * DEPTH_SPECKLE_RANGE_PX)))
        valid &= d16 > 0
    if offset_px != 0.0:  # the offset at the working size, each pixel's gain at its right column
        vv, uu = np.nonzero(valid)
        d[vv, uu] = correct_disparity(d[vv, uu], uu, offset_px * cam.fx / camera.fx, cam)
        valid &= d > 0
    z = np.zeros_like(d)
    z[valid] = (cam.fx * cam.baseline_m) / d[valid]  # eq. 1
    z[(z < cfg.min_depth_m) | (z > mcfg.max_range_m)] = 0.0
    return z


def _matcher(ndisp: int):
    """The map's stereo matcher: StereoBM or StereoSGBM over ``ndisp`` disparities."""
    b = MAP_BLOCK_SIZE
    if MAP_DEPTH_METHOD == "bm":
        matcher = cv2.StereoBM.create(ndisp, b)
        matcher.setTextureThreshold(int(DEPTH_TEXTURE_THRESHOLD))
        matcher.setUniquenessRatio(int(MAP_UNIQUENESS))
    else:
        # SGBM's own left-right check (disp12MaxDiff) reuses its cost volume: no second match
        lr = int(max(1, round(MAP_LR_CHECK_PX))) if MAP_LR_CHECK_PX > 0 else -1
        matcher = cv2.StereoSGBM.create(
            minDisparity=0,
            numDisparities=ndisp,
            blockSize=b,
            P1=8 * b * b,
            P2=32 * b * b,
            disp12MaxDiff=lr,
            uniquenessRatio=int(MAP_UNIQUENESS),
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
    return matcher


def _right_checks(matcher, left, right, disp_l, d, valid) -> None:
    """Clear in ``valid`` the pixels the right image's own disparity map contradicts, or where
    the WLS filter's confidence is low (only the confidence map is used)."""
    disp_r = cv2.ximgproc.createRightMatcher(matcher).compute(right, left)  # <= 0, -16 ndisp = none
    if MAP_LR_CHECK_PX > 0:
        vv, uu = np.nonzero(valid)
        ur = np.rint(uu - d[vv, uu]).astype(np.intp)
        inside = ur >= 0
        dr = np.full(len(uu), -np.inf, np.float32)
        dr[inside] = disp_r[vv[inside], ur[inside]].astype(np.float32) / 16.0
        bad = ~(np.abs(d[vv, uu] + dr) <= MAP_LR_CHECK_PX)
        valid[vv[bad], uu[bad]] = False
    if MAP_MIN_CONFIDENCE > 0:
        wls = cv2.ximgproc.createDisparityWLSFilter(matcher)
        wls.filter(disp_l, left, disparity_map_right=disp_r)
        valid &= wls.getConfidenceMap() >= MAP_MIN_CONFIDENCE
