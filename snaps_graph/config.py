"""Typed configuration, one section per stage, loadable from and dumped to TOML.

Every number a user may want to change lives here with its unit in the field name or comment.
The SNAPS section uses the paper's Table I names (radius, frame distance, discount length,
minimum similarity, inter-frame pause, attempts). A run dumps the full configuration it used to
``config.toml`` in its results folder, and ``Config.load`` reads such a file back (unknown keys
are a one-line error, so a typo never passes silently).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

from .errors import SnapsGraphError
from .io_utils import atomic_write_text, read_toml

# The one vocabulary of modes (the CLI's --mode/--loops/--refine use the same lists).
FrontendMode = Literal["sift", "orb", "klt"]
DisparityMethod = Literal["bm_wls", "sgbm", "sparse"]
LoopMode = Literal["snaps", "none"]
RefineMode = Literal["none", "isam2", "batch", "both"]  # both = iSAM2 online + batch at the end


class _Section:
    """Validation shared by the config sections: every field is checked against its type (a
    ``Literal`` is an enumeration) and its range in ``RULES``, at construction and on demand."""

    _name = "config"

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, source: str = "config") -> None:
        """A one-line SnapsGraphError naming ``source`` and the key for the first bad value."""
        hints = _hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            key = f"{self._name}.{f.name}"
            _check_value(getattr(self, f.name), hints[f.name], RULES.get(key), f"{source}: {key}")
        self._cross_checks(source)

    def _cross_checks(self, source: str) -> None:
        pass


@dataclass
class FrontendConfig(_Section):
    """Stereo visual odometry (SPEC "Front end")."""

    _name = "frontend"

    # Feature mode: "sift" is the paper's (faithful, slower); "orb" and "klt" are fast modes.
    mode: FrontendMode = "klt"
    # Dense disparity: "bm_wls" (paper: StereoBM + WLS filter), "sgbm", or "sparse" (depth only
    # at keypoints, found by matching along the epipolar line; the fast default).
    disparity: DisparityMethod = "sparse"
    num_disparities: int = 128  # BM/SGBM disparity search range, pixels (multiple of 16)
    block_size: int = 15  # BM block size, pixels (odd)
    wls_lambda: float = 8000.0  # WLS smoothness
    wls_sigma: float = 1.5  # WLS colour sensitivity
    min_depth_m: float = 0.5
    max_depth_m: float = 80.0  # depth beyond this is invalid (eq. 1 is noisy far away)
    sift_features: int = 2000
    # SIFT scale space: -1 = OpenCV's (image doubled first, as the paper ran it), 0 = from the
    # image's own resolution (Lowe without doubling, VLFeat's default; about 3x faster).
    sift_first_octave: Literal[-1, 0] = 0
    orb_features: int = 2000
    klt_features: int = 1500  # corners detected when re-detecting in KLT mode
    klt_min_tracks: int = 600  # re-detect when fewer tracks than this survive
    ratio_test: float = 0.75  # Lowe's ratio for descriptor matching
    pnp_reprojection_px: float = 1.5  # RANSAC inlier threshold
    pnp_iterations: int = 200
    pnp_confidence: float = 0.999
    min_inliers: int = 20  # fewer PnP inliers flags the frame
    max_step_m: float = 4.0  # a larger translation between frames is implausible (flagged)
    max_step_deg: float = 20.0  # a larger rotation between frames is implausible (flagged)
    min_frame_std: float = 3.0  # a frame whose grey std is below this is treated as black/flat
    threads: int = 2  # worker threads (OpenCV releases the GIL)
    sgbm_block_size: int = 5  # SGBM block size, pixels (odd)
    # Sparse stereo (disparity = "sparse"): LK from left to right along the row.
    stereo_window_px: int = 11  # LK window, pixels
    stereo_levels: int = 4  # LK pyramid levels (disparities up to ~100 px near the car)
    # LK pyramid levels for points with a disparity guess (klt: tracked points, the guess
    # predicted from the point's 3D position and the constant-velocity motion)
    stereo_guess_levels: int = 4
    stereo_max_dy_px: float = 1.0  # a match may leave its row by at most this (rectified pair)
    stereo_lr_check_px: float = 0.5  # right-to-left re-track must land this close; 0 disables
    # KLT mode: frame-to-frame tracking of corners.
    klt_window_px: int = 11  # LK window, pixels
    klt_levels: int = 3  # LK pyramid levels
    klt_quality: float = 0.01  # goodFeaturesToTrack quality level (relative to the best corner)
    klt_min_distance_px: int = 10  # minimum spacing between corners, pixels
    klt_border_px: int = 16  # corners are not detected this close to the image border
    loop_features: int = 500  # keypoints with depth kept per frame (VOResult.features)
    min_stereo_points: int = 40  # a frame with fewer keypoints with depth cannot be a reference
    min_sharpness_ratio: float = 0.35  # mean |Laplacian| below this x the reference's: blurred
    ransac_seed: int = 0  # cv2.setRNGSeed before every RANSAC (same input -> same output)
    verify_max_translation_m: float = 30.0  # loop verification: a larger relative pose is implausible
    verify_max_rotation_deg: float = 90.0
    # Motion estimate after PnP RANSAC (the seed and the outlier rejection): "stereo_ba" refines
    # it by a two-view stereo bundle adjustment over (u_left, v, u_right) in both frames
    # (frontend/stereo_ba.py); "pnp" keeps PnP + LM on the inliers (the paper's).
    motion: Literal["pnp", "stereo_ba"] = "stereo_ba"
    # Huber kernel width on a (point, view) residual, pixels (stereo BA and local BA); after the
    # stereo BA's first round, points beyond sba_outlier_px in either view are dropped. Tight,
    # because the tails of the KLT errors carry the pitch bias (docs/layout.md).
    sba_huber_px: float = 0.3
    sba_outlier_px: float = 0.6
    # When the stereo BA's estimate keeps fewer than sba_keep_below tracks, the tracks within
    # sba_keep_px of its pose in both views are kept too (and count as its inliers): a tight
    # kernel must not thin out a small image's tracks. Full-size KITTI frames keep 200 or more.
    sba_keep_px: float = 2.0
    sba_keep_below: int = 100
    sba_iterations: int = 3  # Gauss-Newton iterations per round (two rounds)
    # klt mode: sliding-window stereo BA over the last lba_window keyframes (frontend/local_ba.py);
    # a reference frame becomes a keyframe lba_every frames after the last one.
    local_ba: bool = True
    lba_window: int = 6
    lba_iterations: int = 5
    lba_max_landmarks: int = 300
    lba_every: int = 3
    # ... or sooner, once the drive has gone lba_keyframe_m from the last keyframe (0 = never): a
    # fast drive keeps the keyframe spacing of a normal one (3 frames at 0.7-1.2 m per frame,
    # which 2.5 m leaves as they are).
    lba_keyframe_m: float = 2.5
    # klt: when PnP on the KLT tracks fails or has fewer than min_inliers inliers (large motion:
    # a fast drive, or frames skipped), retry once by matching ORB keypoints detected afresh in
    # the reference and the current frame.
    klt_retry_features: int = 4000  # ORB keypoints detected per image by the retry
    # Disparity offset, measured - true, px, at the centre column (a rig's rectification residual:
    # a rig whose disparities read 0.3 px small has -0.3). It is modelled as a small turn of the
    # right camera about its y axis, offset * (1 + ((u_r - cx) / fx)^2) at right-image column u_r;
    # every disparity the front end uses is corrected.
    disparity_offset_px: float = 0.0
    # klt + local BA: estimate the offset online (one more unknown in each local-BA solve, Gaussian
    # prior of disparity_offset_prior_px around the running estimate); the information-weighted
    # mean of the solves, clamped to +-disparity_offset_max_px, replaces disparity_offset_px once
    # disparity_offset_min_solves solves contributed, its standard error is at most
    # disparity_offset_max_sd_px (a drive with too little depth change -- a MAV hovering, a car
    # standing -- leaves the offset unobservable) and it differs by disparity_offset_min_px and by
    # disparity_offset_min_z standard errors or more (frontend/offset.py): the significance test
    # keeps an offset-free rig's early noise out.
    estimate_disparity_offset: bool = True
    disparity_offset_prior_px: float = 0.5
    disparity_offset_max_px: float = 2.0
    disparity_offset_min_solves: int = 3
    disparity_offset_min_px: float = 0.05
    disparity_offset_max_sd_px: float = 0.05
    disparity_offset_min_z: float = 4.0
    # Once applied, the running estimate forgets older solves (weight 1 - 1/memory per new solve;
    # 0 = never): they saw a worse offset applied, whose track selection leans toward it.
    disparity_offset_memory_solves: int = 20
    loop_detector: Literal["orb", "sift"] = "orb"  # "orb": ORB pyramid; "sift": SIFT from octave 0
    loop_orb_features: int = 1000  # keypoints per reference frame (before the stereo check)
    loop_query_features: int = 1500  # keypoints of the current frame when verifying
    loop_orb_levels: int = 8
    loop_orb_scale: float = 1.2  # pyramid ratio between levels
    loop_orb_fast_threshold: int = 20
    loop_orb_upright: bool = True  # descriptors at angle 0 (cameras do not roll)
    loop_reference_every: int = 5  # reference features every this many frames (nearest one is used)
    loop_ratio_test: float = 0.8  # Lowe's ratio for loop matches
    # After PnP, an inlier's current-frame stereo disparity must agree with its predicted one
    # within this many pixels (0 disables), and at least loop_depth_min_ratio of the inliers with
    # a current disparity must agree: a look-alike place at another distance fails.
    loop_depth_check_px: float = 1.0
    loop_depth_min_ratio: float = 0.5
    loop_min_sigma_px: float = 0.5  # floor of the reprojection sigma in the loop covariance
    # A verified loop farther apart than this is refused: a loop is a revisit of the same place,
    # and views 10-30 m apart along one street verify too; 8 m keeps a margin below the
    # evaluation's 10 m "false" line.
    loop_max_distance_m: float = 8.0
    # KLT window bias (the pitch bias at its source): where the flow curves within the LK
    # window (the road under forward motion) the translation-only fit is biased by the window's
    # second moment, (w^2 - 1) / 12. Each track is re-fitted at the finest level with a
    # klt_bias_window_px window and extrapolated to a zero-size window (0 disables); a re-fit that
    # fails or moves more than klt_bias_max_px keeps the plain position.
    klt_bias_window_px: int = 7
    klt_bias_max_px: float = 0.5
    # The chain's step between consecutive local-BA keyframes (the composed stereo-BA steps, their
    # covariance carried along and multiplied by lba_chain_scale) as a relative-pose factor in
    # the window: "yaw_roll" = its rotation about the camera's y and z axes
    # (the window's far landmarks leave yaw and the sideways step ambiguous, and a yaw held alone
    # is paid for in the window's roll, which they couple; the chain's pitch carries the tracking
    # bias the window removes), "yaw", "rotation", "full", or "off".
    lba_chain: Literal["off", "yaw", "yaw_roll", "rotation", "full"] = "yaw_roll"
    lba_chain_scale: float = 1.0
    # klt, weak texture: goodFeaturesToTrack's quality is relative to the image's strongest corner,
    # so a high-contrast far field (a tree line against the sky, beyond max_depth_m) can suppress
    # every corner of the weakly textured ground that stereo can range. When tracked plus newly
    # detected points with depth are fewer than klt_weak_points and most new corners lie beyond
    # max_depth_m, corners are detected once more at klt_weak_quality (klt_weak_points = 0: off).
    klt_weak_points: int = 300
    klt_weak_quality: float = 0.001
    # threads > 1: an LK call (KLT tracking, sparse stereo) on at least this many points is split
    # in two halves run in two threads; LK tracks each point alone, so the result is the same
    # (0: never split).
    lk_split_min: int = 200
    # ORB loop keypoints refined at full resolution (cv2.cornerSubPix, half-window this many
    # pixels x the pyramid scale of the keypoint's level; 0 = the level's pixel grid): a FAST
    # corner from pyramid level o sits on that level's grid, up to 1.2^o px off.
    loop_subpixel_px: float = 2.0

    def _cross_checks(self, source: str) -> None:
        if self.klt_bias_window_px and not 3 <= self.klt_bias_window_px < self.klt_window_px:
            raise SnapsGraphError(
                f"{source}: frontend.klt_bias_window_px must be 0 or in [3, klt_window_px), got {self.klt_bias_window_px}"
            )
        if not self.min_depth_m < self.max_depth_m:
            raise SnapsGraphError(
                f"{source}: frontend.min_depth_m must be < frontend.max_depth_m, got {self.min_depth_m} and {self.max_depth_m}"
            )


@dataclass
class LoopConfig(_Section):
    """SNAPS loop closure (paper §III, Table I; SPEC "SNAPS loop closure")."""

    _name = "loop"

    radius_m: float = 10.0  # candidates lie within this distance of the current position
    # Candidate gate: "drift" = within search_sigmas standard deviations of the [odometry] drift
    # accrued between the candidate and now (through the last verified loop if shorter), never
    # less than radius_m nor more than search_max_radius_m, nearest in sigmas first; "radius" =
    # the paper's fixed radius_m around an estimate taken as exact.
    search: Literal["drift", "radius"] = "drift"
    search_sigmas: float = 3.0
    search_max_radius_m: float = 40.0
    frame_distance: int = 100  # M: candidate j must satisfy N - j >= M
    discount_length: int = 100  # K of discount_window = "fixed": poses N-K..N move (the paper's Table I)
    # Q threshold for a loop: the paper's 0.75 is unreachable with the exact Wang-Bovik index on a
    # moving camera (docs/loop-closure.md).
    min_similarity: float = 0.15
    inter_frame_pause: int = 50  # frames after the last pinned frame before another loop
    attempts: int = 5  # at most this many candidates (nearest first) are compared
    max_yaw_deg: float = 10.0  # |yaw_j - yaw_N| limit
    thumbnail_scale: float = 1.0 / 6.0  # thumbnails: left image rescaled by this (INTER_AREA)
    window: int = 16  # UIQI sliding window B (Wang & Bovik use 8; 16 separates revisits better)
    # Compare thumbnails also at horizontal shifts up to this (heading differences between
    # passes); 0 = the paper (unshifted), 3x cheaper for about the same loops.
    shift_px: int = 0
    shift_step_px: int = 2  # ...in steps of this many thumbnail pixels
    discount_offset: float = 3.0  # the 3 in gamma = 1 - exp(-(3 - alpha*0.01*s'))
    discount_rate: float = 0.01  # the 0.01 in the same formula
    # Where geometric verification gives T_ref_cur, eq. 6's delta aims at p_ref + R_ref t_ref_cur
    # (where frame N really stands) instead of p_ref (the paper's same-place assumption).
    # false = the paper exactly.
    use_verified_offset: bool = True
    # Weight of eq. 6's move: "q" = the paper (Q); "verified" = 1 for a verified loop (its target
    # is measured, not assumed), Q otherwise.
    correction_weight: Literal["q", "verified"] = "verified"
    # With a verifier (the pipeline always has one): a loop must pass geometric verification;
    # candidates at or above min_similarity are tried in order of Q, at most verify_attempts.
    # false = the paper: the highest Q is a loop even when unverified (same-place assumption).
    require_verification: bool = True
    verify_attempts: int = 3
    # UIQI window sums kept per thumbnail (LRU) so a comparison only computes the cross term;
    # ~180 KB per 207x63 thumbnail, so 512 frames ~ 92 MB. 0 disables the cache.
    stats_cache_frames: int = 512
    # Verify every compared candidate (not only those at or above min_similarity, at most
    # verify_attempts) and record each outcome in candidates.csv, so the precision-recall curve
    # with verification (snaps-graph loops) covers every threshold. The loop chosen is the same;
    # only verification time (t_verify_ms, never SNAPS's t_loop_ms) grows.
    verify_all_candidates: bool = False
    # What eq. 6 moves: "xyz" = the three position components (the paper); "ground" = the
    # ground-plane components only (world x, z), so the reference's own height error is not
    # copied into the current frame.
    correction_axes: Literal["xyz", "ground"] = "ground"
    # Orientation correction of a verified loop: "none" = orientations keep their VO values (the
    # paper); "yaw" = the window turns about the world vertical toward the verified heading
    # R_ref R_ref_cur (bent progressively over eq. 6's window), so later frames continue on the
    # corrected heading.
    correction_rotation: Literal["none", "yaw"] = "yaw"
    # The turn applied is the gain g = n*d^2 / (n*d^2 + s^2) of a loop n frames after its
    # reference: d the VO's heading random walk per sqrt(frame), s the verified heading's sigma.
    heading_drift_deg: float = 0.003
    verified_heading_sigma_deg: float = 0.1
    # Eq. 6's window for a loop from frame N to its reference j: "fixed" = discount_length frames
    # (the paper); "span" = min(discount_length_max, round(discount_span_factor * (N - j))), so a
    # long loop (more drift to spread) corrects more frames than a short one.
    discount_window: Literal["fixed", "span"] = "span"
    discount_span_factor: float = 1.0
    discount_length_max: int = 1000
    # Shape of gamma over the window: "paper" = 1 - exp(-(3 - alpha*0.01*s')) (eq. 6); "linear" = a
    # ramp from 0.95 at N to 0 just past the window's oldest frame, so the correction never steps.
    # discount_window = "fixed" + "paper" is eq. 6 exactly.
    discount_shape: Literal["paper", "linear"] = "linear"
    # During the inter-frame pause, keep searching candidates estimated closer than this fraction
    # of the last loop's distance (verified |t_ref_cur|, else the estimated distance); one that
    # verifies at a measured distance below the same limit is a loop for the factor graph only
    # (correcting the heuristic again re-bends what the last loop explained). 0 = the paper's pause.
    pause_closer_ratio: float = 0.5

    def _cross_checks(self, source: str) -> None:
        if self.search_max_radius_m < self.radius_m:
            raise SnapsGraphError(
                f"{source}: loop.search_max_radius_m must be >= loop.radius_m, got {self.search_max_radius_m} and {self.radius_m}"
            )


@dataclass
class GraphConfig(_Section):
    """GTSAM factor graph (SPEC "Factor graph")."""

    _name = "graph"

    refine: RefineMode = "none"  # none | isam2 | batch | both (iSAM2 online + batch at the end)
    prior_sigma_rot_rad: float = 1e-4
    prior_sigma_trans_m: float = 1e-3
    odom_sigma_rot_rad: float = 0.005  # VO step noise at the reference inlier count
    odom_sigma_trans_m: float = 0.05
    odom_ref_inliers: int = 200  # sigmas scale with sqrt(odom_ref_inliers / inliers)
    odom_min_inliers: int = 20  # inlier counts below this floor count as this many
    odom_sigma_scale_min: float = 0.5  # clamp of the inlier scale sqrt(ref / inliers)
    odom_sigma_scale_max: float = 4.0
    flagged_sigma_scale: float = 100.0  # a flagged VO step's sigmas are this much looser
    loop_sigma_rot_rad: float = 0.01  # verified loop at Q = 1 (a PnP like a VO step, ~2x looser)
    loop_sigma_trans_m: float = 0.1
    unverified_sigma_rot_rad: float = 0.5  # same-place assumption: loose rotation
    unverified_sigma_trans_m: float = 2.0
    # Q at which a loop's sigmas would be infinite: sigma = base * clip((1 - q0)/(Q - q0), 1, max).
    # 0 for the exact UIQI (true revisits score 0.15-0.6): sigma = base / Q, at most 10x.
    loop_q_floor: float = 0.0
    loop_sigma_scale_max: float = 10.0  # clip of (1 - loop_q_floor) / (Q - loop_q_floor)
    robust_kernel: Literal["huber", "cauchy", "none"] = "cauchy"  # loop factors only
    robust_param: float = 3.0  # kernel width on the whitened 6-vector norm (an inlier's is ~2.4)
    isam2_relinearize_threshold: float = 0.01
    isam2_relinearize_skip: int = 1
    # Extra iSAM2 steps right after an update that carried a loop (the robust weight converges
    # by IRLS). Each costs about a loop update (20-100 ms on KITTI 00) and later frames' updates
    # converge it anyway, so 0 online; PoseGraph.converge() finishes the job at the end.
    isam2_loop_iterations: int = 0
    isam2_final_iterations: int = 10  # PoseGraph.converge(): at most this many extra steps
    batch_max_iterations: int = 100
    # A step that carries the front end's stereo-BA covariance (VOResult.cov) takes it times
    # odom_cov_scale^2, plus odom_cov_floor_* squared on the diagonal so it is never
    # over-confident; a step without one takes odom_sigma_* scaled by its inlier count.
    odom_cov_scale: float = 1.0
    odom_cov_floor_rot_rad: float = 1e-4
    odom_cov_floor_trans_m: float = 1e-3
    # A verified loop with a covariance (the PnP covariance of its own inliers,
    # frontend/loop_features.py) takes it times loop_cov_scale plus the floors below in
    # quadrature; other loops take loop_sigma_* scaled by Q.
    loop_cov_scale: float = 4.0  # covariance multiplier (sigma x2): unmodelled errors of the points
    # Rotation floor, added in quadrature to the verification's rotation sigma: without it the
    # graph would take a loop's rotation as exact against the realistic VO rotation noise.
    loop_sigma_floor_rot_rad: float = 0.002
    loop_sigma_floor_trans_m: float = 0.02

    def _cross_checks(self, source: str) -> None:
        if not self.odom_sigma_scale_min <= self.odom_sigma_scale_max:
            raise SnapsGraphError(
                f"{source}: graph.odom_sigma_scale_min must be <= graph.odom_sigma_scale_max, "
                f"got {self.odom_sigma_scale_min} and {self.odom_sigma_scale_max}"
            )


@dataclass
class MapConfig(_Section):
    """Point-cloud map (SPEC "Map")."""

    _name = "map"

    enabled: bool = False
    keyframe_every: int = 5  # one keyframe cloud every this many frames
    max_range_m: float = 15.0  # depth beyond this is dropped (stereo depth error grows with z^2)
    trajectory: Literal["vo", "snaps", "isam2", "batch", "best"] = "best"  # best: the most refined available
    per_trajectory: bool = False  # also write map_<trajectory>.ply for every trajectory of the run
    # Map depth (frontend.depth.map_depth): stereo on images scaled by depth_scale, then every
    # pixel with weak evidence is invalid; nothing is filled in. max_range_m above is its range.
    depth_method: Literal["sgbm", "bm"] = "sgbm"  # StereoSGBM 3-way; StereoBM: 1.5x faster, 6x fewer valid pixels on real KITTI
    depth_scale: float = 0.5  # stereo runs on images resized by this (1 = full size)
    depth_block_size: int = 5  # matcher block size at the working size, pixels (odd)
    depth_texture_threshold: int = 10  # StereoBM: minimum local texture (prefiltered sum)
    depth_uniqueness: int = 15  # best match must beat the second best by this percentage
    depth_lr_check_px: float = 1.0  # left-right consistency: |d_left - d_right| <= this; 0 disables
    depth_min_confidence: float = 0.0  # WLS confidence map (0-255) below this is invalid; 0 skips WLS
    depth_edge_ratio: float = 0.1  # invalid where the 3x3 disparity spread exceeds this x d (depth edges)
    depth_speckle_px: int = 50  # connected regions smaller than this (working pixels) are dropped
    depth_speckle_range_px: float = 1.0  # ...where neighbours differ by at most this disparity
    # TSDF fusion (mapping.tsdf.FusedMap): keyframe depth kept as PNG-encoded uint16 mm.
    tsdf_voxel_m: float = 0.15  # TSDF voxel edge
    tsdf_trunc_voxels: float = 6.0  # truncation distance, in voxels
    tsdf_max_blocks: int = 40000  # fuse in chunks: a chunk's surface is extracted when it holds this many blocks (6 KB each)
    tsdf_min_weight: float = 1.0  # mesh/points only where at least this many keyframes saw the surface
    tsdf_min_component: int = 0  # mesh pieces of fewer triangles are dropped (floating blobs of wrong depth); 0 keeps all
    world_mesh: str = ""  # the true world as a triangle mesh (synth --world-mesh): map accuracy
    accuracy_range_m: float = 20.0  # completeness counts true surface within this of the path
    accuracy_tolerance_m: float = 0.2  # ...and within this of the map
    accuracy_samples: int = 200_000  # true-surface samples within range used for completeness

    def _cross_checks(self, source: str) -> None:
        if self.depth_method == "bm" and self.depth_block_size < 5:
            raise SnapsGraphError(
                f"{source}: map.depth_block_size must be >= 5 for depth_method 'bm', got {self.depth_block_size}"
            )


@dataclass
class OdometryConfig(_Section):
    """Odometry drift model: how fast a trajectory's error grows with the distance driven (1 sigma).

    A pose file (``run --odometry``) carries no covariance, so its factors take their noise from
    here; the drift-aware loop search and the ``drift`` tool use the same model."""

    _name = "odometry"

    trans_drift_pct: float = 1.0  # translation error per distance driven, percent
    # Heading (and attitude) error per 100 m driven, degrees: 1 % of lateral drift over 1 km of
    # driving needs about 0.1 (lateral error b D^2 / 2; docs/loop-closure.md).
    rot_drift_deg_per_100m: float = 0.1


@dataclass
class Config:
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    map: MapConfig = field(default_factory=MapConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    loops: LoopMode = "snaps"

    def __post_init__(self) -> None:
        self.source = "config"  # the file it was loaded from, named in validation errors
        self.validate()

    def validate(self, source: str | None = None) -> None:
        """Every field (types, enumerations, ranges) and the rules across fields; a one-line
        SnapsGraphError naming the config file and the key. ``snaps-graph config FILE`` and
        ``run`` (before the first frame) both call this on the configuration that would run."""
        source = source or self.source
        for section in (self.frontend, self.loop, self.graph, self.map, self.odometry):
            section.validate(source)
        hints = _hints(type(self))
        _check_value(self.loops, hints["loops"], None, f"{source}: loops")
        if self.map.enabled and self.map.trajectory != "best":
            need = {
                "vo": True,
                "snaps": self.loops == "snaps",
                "isam2": self.graph.refine in ("isam2", "both"),
                "batch": self.graph.refine in ("batch", "both"),
            }[self.map.trajectory]
            if not need:
                what = (
                    "loops = 'snaps'" if self.map.trajectory == "snaps" else f"graph.refine = '{self.map.trajectory}' or 'both'"
                )
                raise SnapsGraphError(
                    f"{source}: map.trajectory = '{self.map.trajectory}' needs {what} "
                    f"(this run has loops = '{self.loops}', graph.refine = '{self.graph.refine}')"
                )

    def resolved(self, *, loops: str | None = None, refine: str | None = None, build_map: bool | None = None) -> "Config":
        """A validated copy with a run's overrides (``--loops``, ``--refine``, ``--map``) applied:
        what runs. The pipeline uses it (it never changes the caller's config), and so does the
        CLI's check before the first frame."""
        out = copy.deepcopy(self)
        if loops is not None:
            out.loops = loops  # type: ignore[assignment]
        if refine is not None:
            out.graph.refine = refine  # type: ignore[assignment]
        if build_map is not None:
            out.map.enabled = bool(build_map)
        out.validate()
        return out

    # ---- TOML ----
    @classmethod
    def load(cls, path: str | Path) -> "Config":
        path = Path(path)
        data = read_toml(path, "config")
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "config") -> "Config":
        cfg = cls()
        cfg.source = source
        for key, value in data.items():
            if not hasattr(cfg, key):
                raise SnapsGraphError(f"{source}: unknown key '{key}'{_did_you_mean(key, cfg)}")
            current = getattr(cfg, key)
            if dataclasses.is_dataclass(current):
                if not isinstance(value, dict):
                    raise SnapsGraphError(f"{source}: [{key}] must be a table")
                for sub, subval in value.items():
                    if f"{key}.{sub}" in RETIRED:  # an older version wrote it into config.toml
                        print(
                            f"note: {source}: {key}.{sub} is no longer used ({RETIRED[f'{key}.{sub}']}); ignored", file=sys.stderr
                        )
                        continue
                    if not hasattr(current, sub):
                        raise SnapsGraphError(f"{source}: unknown key '{key}.{sub}'{_did_you_mean(sub, current, key + '.')}")
                    setattr(current, sub, _coerce(getattr(current, sub), subval, f"{source}: {key}.{sub}"))
            else:
                if isinstance(value, dict):  # a table where a value belongs: a misspelled section
                    close = difflib.get_close_matches(
                        key, [f.name for f in dataclasses.fields(cfg) if dataclasses.is_dataclass(getattr(cfg, f.name))], n=1
                    )
                    hint = f" (did you mean [{close[0]}]?)" if close else ""
                    raise SnapsGraphError(f"{source}: [{key}] is not a section{hint}")
                setattr(cfg, key, _coerce(current, value, f"{source}: {key}"))
        cfg.validate()
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def dumps(self) -> str:
        lines: list[str] = []
        sections = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if dataclasses.is_dataclass(value):
                sections.append((f.name, value))
            else:
                lines.append(f"{f.name} = {_toml_value(value)}")
        for name, section in sections:
            lines.append("")
            lines.append(f"[{name}]")
            for f in dataclasses.fields(section):
                lines.append(f"{f.name} = {_toml_value(getattr(section, f.name))}")
        return "\n".join(lines) + "\n"

    def dump(self, path: str | Path) -> None:
        atomic_write_text(path, self.dumps())


def _coerce(current: Any, value: Any, where: str) -> Any:
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise SnapsGraphError(f"{where}: expected true/false, got {value!r}")
        return value
    if isinstance(current, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise SnapsGraphError(f"{where}: expected an integer, got {value!r}")
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SnapsGraphError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise SnapsGraphError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    raise TypeError(f"cannot write {value!r} to TOML")


# ---- validation ----
@dataclass(frozen=True)
class Range:
    """Allowed values of a number: bounds (open or closed), odd, a multiple of ``multiple``."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    odd: bool = False
    multiple: int | None = None

    def describe(self) -> str:
        if self.lo is not None and self.hi is not None:
            text = f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            text = f"{'>' if self.lo_open else '>='} {self.lo:g}"
        elif self.hi is not None:
            text = f"{'<' if self.hi_open else '<='} {self.hi:g}"
        else:
            text = "a number"
        if self.odd:
            text = "odd and " + text
        if self.multiple:
            text = f"a multiple of {self.multiple} and " + text
        return text

    def ok(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        if self.odd and int(v) % 2 == 0:
            return False
        return not (self.multiple and int(v) % self.multiple)


def _gt(lo: float) -> Range:
    return Range(lo=lo, lo_open=True)


def _ge(lo: float) -> Range:
    return Range(lo=lo)


def _in(lo: float, hi: float) -> Range:
    return Range(lo, hi)


def _pos(hi: float) -> Range:
    return Range(0, hi, lo_open=True)


def _nn(hi: float) -> Range:
    return Range(0, hi)


POSITIVE = _gt(0)
NON_NEGATIVE = _ge(0)
AT_LEAST_1 = _ge(1)
# Upper bounds: far beyond any useful setting, and below what would exhaust memory, time or a
# C int (an OpenCV or gtsam argument) and crash instead of an error line.
MAX_POINTS = 100_000  # features, tracks, landmarks, inliers per frame
MAX_FRAMES = 10_000_000  # frame counts and gaps (about two weeks at 10 Hz)
MAX_ITERATIONS = 100_000  # solver iterations
MAX_WINDOW_PX = 101  # matching windows (an image pyramid level is rarely smaller)
MAX_LEVELS = 10  # pyramid levels
MAX_SCALE = 1e6  # dimensionless sigma and covariance factors
SIGMA_ROT = Range(0, math.pi, lo_open=True)  # a rotation sigma, rad
SIGMA_TRANS = Range(0, 1e4, lo_open=True)  # a translation sigma, m
FRACTION = Range(0, 1, lo_open=True)  # (0, 1]
PROBABILITY = Range(0, 1, lo_open=True, hi_open=True)  # (0, 1)
ANGLE = Range(0, 180, lo_open=True)  # (0, 180] degrees

# The range of every numeric field, keyed "section.field" (booleans and Literal fields are checked
# by their type). A new numeric field needs a line here (tests/test_contract.py checks it).
# Keys older versions had (and wrote into every run's config.toml): read back with a note.
_RETIRED_GROUPS = {
    "the map is a TSDF fusion now, not a union of point clouds": (
        "map.pixel_step",
        "map.voxel_size_m",
        "map.keyframe_voxel_size_m",
        "map.build_chunk_points",
        "map.build_tile_m",
    ),
    "KLT tracks from the last frame": (
        "frontend.klt_reference",
        "frontend.kf_max_gap",
        "frontend.kf_min_ratio",
        "frontend.klt_anchor_gap",
        "frontend.klt_anchor_max_px",
    ),
    "the road prewarp is gone; the KLT window bias is removed per track": (
        "frontend.klt_road_prewarp",
        "frontend.klt_road_max_depth_m",
        "frontend.klt_road_tol_m",
        "frontend.klt_road_min_points",
        "frontend.klt_road_max_tilt_deg",
    ),
    "the local BA runs inline, numpy solver, longest tracks first": (
        "frontend.lba_async",
        "frontend.lba_solver",
        "frontend.lba_select",
    ),
    "far points are not used": ("frontend.sba_far_points", "frontend.far_min_disparity_px"),
    "KLT always retries a failed frame on ORB matches": ("frontend.klt_retry",),
    "the disparity offset is modelled as a turned right camera": ("frontend.disparity_offset_model",),
    "loops verify with their own features against the nearest stored reference, PnP pose": (
        "frontend.loop_verify_features",
        "frontend.loop_verify_neighbours",
        "frontend.loop_pose_refine",
    ),
    "the batch solve is Levenberg-Marquardt without a gravity prior": (
        "graph.batch_solver",
        "graph.gnc_inlier_probability",
        "graph.gravity_prior",
        "graph.gravity_sigma_deg",
        "graph.gravity_rounds",
    ),
    "iSAM2 factorises by QR": ("graph.isam2_factorization",),
    "a step with a stereo-BA covariance uses it, others their inlier count": ("graph.odom_noise",),
    "a verified loop with a covariance uses it, others their Q": ("graph.loop_sigma_source",),
    "the top-down PNG is coloured by height at a fixed resolution": ("map.topdown_colour_by", "map.topdown_dpi"),
}
RETIRED = {key: why for why, keys in _RETIRED_GROUPS.items() for key in keys}
RETIRED |= {
    "loop.correction_model": 'a verified heading turn always bends eq. 6\'s window ("shift" measured worse)',
    "loop.heading_prior": 'the heading prior is the drift since the reference ("tracked" measured no better)',
    "loop.ramp": "eq. 6's ramp follows the distance driven (by frame count measured worse)",
}

RULES: dict[str, Range] = {
    "frontend.num_disparities": Range(16, 1024, multiple=16),
    "frontend.block_size": Range(5, 255, odd=True),
    "frontend.wls_lambda": _nn(1e6),
    "frontend.wls_sigma": _pos(100),
    "frontend.min_depth_m": _pos(1000),
    "frontend.max_depth_m": _pos(1e4),
    "frontend.sift_features": _in(1, MAX_POINTS),
    "frontend.orb_features": _in(1, MAX_POINTS),
    "frontend.klt_features": _in(1, MAX_POINTS),
    "frontend.klt_min_tracks": _nn(MAX_POINTS),
    "frontend.ratio_test": FRACTION,
    "frontend.pnp_reprojection_px": _pos(100),
    "frontend.pnp_iterations": _in(1, 100_000),
    "frontend.pnp_confidence": PROBABILITY,
    "frontend.min_inliers": _in(6, MAX_POINTS),  # PnP needs at least 6
    "frontend.max_step_m": _pos(1000),
    "frontend.max_step_deg": ANGLE,
    "frontend.min_frame_std": _nn(255),
    "frontend.threads": Range(1, 256),
    "frontend.sgbm_block_size": Range(1, 255, odd=True),
    "frontend.stereo_window_px": _in(3, MAX_WINDOW_PX),
    "frontend.stereo_levels": _nn(MAX_LEVELS),
    "frontend.stereo_guess_levels": _nn(MAX_LEVELS),
    "frontend.stereo_max_dy_px": _nn(100),
    "frontend.stereo_lr_check_px": _nn(100),
    "frontend.klt_window_px": _in(3, MAX_WINDOW_PX),
    "frontend.klt_levels": _nn(MAX_LEVELS),
    "frontend.klt_quality": FRACTION,
    "frontend.klt_min_distance_px": _in(1, 1000),
    "frontend.klt_border_px": _nn(1000),
    "frontend.loop_features": _in(1, MAX_POINTS),
    "frontend.min_stereo_points": _in(6, MAX_POINTS),
    "frontend.min_sharpness_ratio": _nn(100),
    "frontend.ransac_seed": _nn(2**31 - 1),
    "frontend.verify_max_translation_m": _pos(1e4),
    "frontend.verify_max_rotation_deg": ANGLE,
    "frontend.sba_huber_px": _pos(100),
    "frontend.sba_outlier_px": _pos(100),
    "frontend.sba_keep_px": _pos(100),
    "frontend.sba_keep_below": _nn(MAX_POINTS),
    "frontend.sba_iterations": _in(1, MAX_ITERATIONS),
    "frontend.lba_window": _in(2, 100),
    "frontend.lba_iterations": _in(1, MAX_ITERATIONS),
    "frontend.lba_max_landmarks": _in(10, MAX_POINTS),
    "frontend.lba_every": _in(1, MAX_FRAMES),
    "frontend.lba_keyframe_m": _nn(1000),
    "frontend.klt_retry_features": _in(1, MAX_POINTS),
    "frontend.disparity_offset_px": Range(-10, 10),
    "frontend.disparity_offset_prior_px": _pos(10),
    "frontend.disparity_offset_max_px": Range(0, 10),
    "frontend.disparity_offset_min_solves": _in(1, MAX_FRAMES),
    "frontend.disparity_offset_min_px": _nn(10),
    "frontend.disparity_offset_max_sd_px": _pos(10),
    "frontend.disparity_offset_min_z": _nn(1e4),
    "frontend.disparity_offset_memory_solves": _nn(MAX_FRAMES),
    "frontend.klt_bias_window_px": _nn(MAX_WINDOW_PX),
    "frontend.klt_bias_max_px": _pos(100),
    "frontend.lba_chain_scale": _pos(1000),
    "frontend.klt_weak_points": _nn(MAX_POINTS),
    "frontend.klt_weak_quality": FRACTION,
    "frontend.lk_split_min": _nn(MAX_POINTS),
    "frontend.loop_orb_features": _in(1, MAX_POINTS),
    "frontend.loop_query_features": _in(1, MAX_POINTS),
    "frontend.loop_orb_levels": Range(1, 16),
    "frontend.loop_orb_scale": Range(1, 2, lo_open=True),
    "frontend.loop_orb_fast_threshold": Range(1, 255),
    "frontend.loop_reference_every": _in(1, MAX_FRAMES),
    "frontend.loop_ratio_test": FRACTION,
    "frontend.loop_depth_check_px": _nn(100),
    "frontend.loop_depth_min_ratio": Range(0, 1),
    "frontend.loop_min_sigma_px": _pos(100),
    "frontend.loop_max_distance_m": _pos(1e4),
    "frontend.loop_subpixel_px": _nn(100),
    "loop.radius_m": _pos(1e4),
    "loop.search_sigmas": _pos(100),
    "loop.search_max_radius_m": _pos(1e4),
    "odometry.trans_drift_pct": Range(0, 50, lo_open=True),
    "odometry.rot_drift_deg_per_100m": Range(0, 90, lo_open=True),
    "loop.frame_distance": _in(1, MAX_FRAMES),
    "loop.discount_length": _nn(MAX_FRAMES),
    "loop.min_similarity": FRACTION,
    "loop.inter_frame_pause": _nn(MAX_FRAMES),
    "loop.attempts": _nn(1000),
    "loop.max_yaw_deg": Range(0, 180),
    "loop.thumbnail_scale": FRACTION,
    "loop.window": _in(2, 256),  # eq. 5 divides by N - 1
    "loop.shift_px": _nn(256),
    "loop.shift_step_px": _in(1, 256),
    "loop.discount_offset": _pos(1e6),
    "loop.discount_rate": _nn(1000),
    "loop.verify_attempts": _in(1, 1000),
    "loop.stats_cache_frames": _nn(MAX_FRAMES),
    "loop.heading_drift_deg": _nn(180),
    "loop.verified_heading_sigma_deg": _nn(180),
    "loop.discount_span_factor": _pos(1000),
    "loop.discount_length_max": _nn(MAX_FRAMES),
    "loop.pause_closer_ratio": Range(0, 1, hi_open=True),
    "graph.prior_sigma_rot_rad": SIGMA_ROT,
    "graph.prior_sigma_trans_m": SIGMA_TRANS,
    "graph.odom_sigma_rot_rad": SIGMA_ROT,
    "graph.odom_sigma_trans_m": SIGMA_TRANS,
    "graph.odom_ref_inliers": _in(1, MAX_POINTS),
    "graph.odom_min_inliers": _in(1, MAX_POINTS),
    "graph.odom_sigma_scale_min": _pos(MAX_SCALE),
    "graph.odom_sigma_scale_max": _pos(MAX_SCALE),
    "graph.flagged_sigma_scale": _in(1, MAX_SCALE),
    "graph.loop_sigma_rot_rad": SIGMA_ROT,
    "graph.loop_sigma_trans_m": SIGMA_TRANS,
    "graph.unverified_sigma_rot_rad": SIGMA_ROT,
    "graph.unverified_sigma_trans_m": SIGMA_TRANS,
    "graph.loop_q_floor": Range(0, 1, hi_open=True),
    "graph.loop_sigma_scale_max": _in(1, MAX_SCALE),
    "graph.robust_param": _pos(1000),
    "graph.isam2_relinearize_threshold": _nn(10),
    "graph.isam2_relinearize_skip": _in(1, 1000),
    "graph.isam2_loop_iterations": _nn(MAX_ITERATIONS),
    "graph.isam2_final_iterations": _nn(MAX_ITERATIONS),
    "graph.batch_max_iterations": _in(1, MAX_ITERATIONS),
    "graph.odom_cov_scale": _pos(MAX_SCALE),
    "graph.odom_cov_floor_rot_rad": SIGMA_ROT,
    "graph.odom_cov_floor_trans_m": SIGMA_TRANS,
    "graph.loop_cov_scale": _pos(MAX_SCALE),
    "graph.loop_sigma_floor_rot_rad": _nn(math.pi),
    "graph.loop_sigma_floor_trans_m": _nn(1e4),
    "map.keyframe_every": _in(1, MAX_FRAMES),
    "map.max_range_m": _pos(1000),
    "map.depth_scale": Range(0.1, 1),
    "map.depth_block_size": Range(1, 255, odd=True),
    "map.depth_texture_threshold": _nn(100_000),
    "map.depth_uniqueness": Range(0, 100),
    "map.depth_lr_check_px": _nn(100),
    "map.depth_min_confidence": Range(0, 255),
    "map.depth_edge_ratio": _nn(100),
    "map.depth_speckle_px": _nn(10**6),
    "map.depth_speckle_range_px": _pos(1000),
    "map.tsdf_voxel_m": _pos(10),
    "map.tsdf_trunc_voxels": _in(1, 100),
    "map.tsdf_max_blocks": _in(1000, 10**7),
    "map.tsdf_min_weight": _nn(10**6),
    "map.tsdf_min_component": _nn(10**8),
    "map.accuracy_range_m": _pos(1e4),
    "map.accuracy_tolerance_m": _pos(100),
    "map.accuracy_samples": _in(1000, 10**8),
}


def _did_you_mean(name: str, obj: Any, prefix: str = "") -> str:
    """ " (did you mean 'loop.min_similarity'?)" for a misspelled key, else ""."""
    close = difflib.get_close_matches(name, [f.name for f in dataclasses.fields(obj)], n=1, cutoff=0.7)
    return f" (did you mean '{prefix}{close[0]}'?)" if close else ""


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = get_type_hints(cls)
    return _HINTS[cls]


def choices(hint: Any) -> tuple | None:
    """The allowed values of a ``Literal`` type, else None."""
    return get_args(hint) if get_origin(hint) is Literal else None


def _check_value(value: Any, hint: Any, rule: Range | None, where: str) -> None:
    allowed = choices(hint)
    if allowed is not None:
        if isinstance(value, bool) or value not in allowed:
            raise SnapsGraphError(f"{where} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
        return
    if hint is bool:
        if not isinstance(value, bool):
            raise SnapsGraphError(f"{where}: expected true/false, got {value!r}")
        return
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SnapsGraphError(f"{where}: expected an integer, got {value!r}")
    elif hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SnapsGraphError(f"{where}: expected a finite number, got {value!r}")
    else:
        return  # a section or a string
    if rule is not None and not rule.ok(value):
        shown = f"{value:.10g}" if isinstance(value, float) else repr(value)
        raise SnapsGraphError(f"{where} must be {rule.describe()}, got {shown}")
