"""Typed configuration, one section per stage, loadable from and dumped to TOML.

Every number a user may want to change lives here with its unit in the field name or comment.
The SNAPS section uses the paper's Table I names (radius, frame distance, discount length,
minimum similarity, inter-frame pause, attempts). A run dumps the full configuration it used to
``config.toml`` in its results folder, and ``Config.load`` reads such a file back (unknown keys
are a one-line error, so a typo never passes silently).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import SnapsGraphError


@dataclass
class FrontendConfig:
    """Stereo visual odometry (SPEC "Front end")."""

    # Feature mode: "sift" is the paper's (faithful, slower); "orb" and "klt" are fast modes.
    mode: str = "klt"
    # Dense disparity: "bm_wls" (paper: StereoBM + WLS filter), "sgbm", or "sparse" (depth only
    # at keypoints, found by matching along the epipolar line; the fast default).
    disparity: str = "sparse"
    num_disparities: int = 128  # BM/SGBM disparity search range, pixels (multiple of 16)
    block_size: int = 15  # BM block size, pixels (odd)
    wls_lambda: float = 8000.0  # WLS smoothness
    wls_sigma: float = 1.5  # WLS colour sensitivity
    min_depth_m: float = 0.5
    max_depth_m: float = 80.0  # depth beyond this is invalid (eq. 1 is noisy far away)
    sift_features: int = 2000
    # SIFT scale space: -1 = OpenCV's (image doubled first, as the paper ran it), 0 = from the
    # image's own resolution (Lowe without doubling, VLFeat's default; about 3x faster).
    sift_first_octave: int = 0
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
    stereo_max_dy_px: float = 1.0  # a match may leave its row by at most this (rectified pair)
    stereo_lr_check_px: float = 0.5  # right-to-left re-track must land this close; 0 disables
    # KLT mode: frame-to-frame tracking of corners.
    klt_window_px: int = 11  # LK window, pixels
    klt_levels: int = 3  # LK pyramid levels
    klt_quality: float = 0.01  # goodFeaturesToTrack quality level (relative to the best corner)
    klt_min_distance_px: int = 10  # minimum spacing between corners, pixels
    klt_border_px: int = 16  # corners are not detected this close to the image border
    loop_features: int = 500  # keypoints (with depth and descriptor) kept per frame for loops
    min_stereo_points: int = 40  # a frame with fewer keypoints with depth cannot be a reference
    min_sharpness_ratio: float = 0.35  # mean |Laplacian| below this x the reference's: blurred
    ransac_seed: int = 0  # cv2.setRNGSeed before every RANSAC (same input -> same output)
    verify_max_translation_m: float = 30.0  # verify_loop: a larger relative pose is implausible
    verify_max_rotation_deg: float = 90.0


@dataclass
class LoopConfig:
    """SNAPS loop closure (paper §III, Table I; SPEC "SNAPS loop closure")."""

    radius_m: float = 10.0  # candidates lie within this distance of the current position
    frame_distance: int = 100  # M: candidate j must satisfy N - j >= M
    discount_length: int = 100  # K: poses N-K..N are corrected
    # Q threshold for a loop. The paper's 0.75 is unreachable with the exact Wang-Bovik index on
    # a moving camera (real KITTI 06: Q = 0.33-0.44 between frames 1.2 m apart); tuned on the
    # synthetic KITTI 00 rendering: true revisits median 0.14 unshifted (0.26 with shift_px = 8),
    # no place farther than 20 m above 0.11 in our sample (README).
    min_similarity: float = 0.15
    inter_frame_pause: int = 50  # frames after the last pinned frame before another loop
    attempts: int = 5  # at most this many candidates (nearest first) are compared
    max_yaw_deg: float = 10.0  # |yaw_j - yaw_N| limit
    thumbnail_scale: float = 1.0 / 6.0  # thumbnails: left image rescaled by this (INTER_AREA)
    window: int = 16  # UIQI sliding window B (Wang & Bovik use 8; 16 separates revisits better)
    # Compare thumbnails also at horizontal shifts up to this (heading differences between
    # passes); 0 = the paper (unshifted). Measured on synthetic KITTI 00 with verification on:
    # 0 -> 15 loops, 1.0 ms on candidate frames; 8 -> 16 loops, 3.3 ms; no false loop either way.
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
    correction_weight: str = "verified"
    # With a verifier (the pipeline always has one): a loop must pass geometric verification;
    # candidates at or above min_similarity are tried in order of Q, at most verify_attempts.
    # false = the paper: the highest Q is a loop even when unverified (same-place assumption).
    require_verification: bool = True
    verify_attempts: int = 3
    # UIQI window sums kept per thumbnail (LRU) so a comparison only computes the cross term;
    # ~180 KB per 207x63 thumbnail, so 512 frames ~ 92 MB. 0 disables the cache.
    stats_cache_frames: int = 512


@dataclass
class GraphConfig:
    """GTSAM factor graph (SPEC "Factor graph")."""

    refine: str = "none"  # none | isam2 | batch
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
    robust_kernel: str = "cauchy"  # huber | cauchy | none (loop factors only)
    robust_param: float = 3.0  # kernel width on the whitened 6-vector norm (an inlier's is ~2.4)
    isam2_factorization: str = "QR"  # QR | CHOLESKY (SPEC: Cholesky threw on long chains)
    isam2_relinearize_threshold: float = 0.01
    isam2_relinearize_skip: int = 1
    # Extra iSAM2 steps right after an update that carried a loop (the robust weight converges
    # by IRLS). Each costs about a loop update (20-100 ms on KITTI 00) and later frames' updates
    # converge it anyway, so 0 online; PoseGraph.converge() finishes the job at the end.
    isam2_loop_iterations: int = 0
    isam2_final_iterations: int = 10  # PoseGraph.converge(): at most this many extra steps
    batch_solver: str = "lm"  # lm | gnc
    batch_max_iterations: int = 100
    gnc_inlier_probability: float = 0.99  # GNC: chi-square inlier threshold at this probability
    # Level-vehicle (gravity) prior, experimental, batch only, off by default. On KITTI 00 it cut the
    # batch ATE about 4x but made t_rel / r_rel 2-4x worse (README "gravity prior"). Each
    # frame's camera down axis, through a camera-frame gravity direction shared by all frames
    # (the mounting), points along a world gravity direction shared by all frames, within
    # gravity_sigma_deg (the spread of road grade and camber). Both directions are re-estimated
    # from the poses before each of gravity_rounds Levenberg-Marquardt solves.
    gravity_prior: bool = False
    gravity_sigma_deg: float = 2.0
    gravity_rounds: int = 3


@dataclass
class MapConfig:
    """Point-cloud map (SPEC "Map")."""

    enabled: bool = False
    keyframe_every: int = 5  # one keyframe cloud every this many frames
    pixel_step: int = 4  # subsample depth pixels on this grid
    max_range_m: float = 40.0  # depth beyond this is dropped (stereo depth error grows with z^2)
    voxel_size_m: float = 0.3  # voxel of the global map (open3d voxel_down_sample)
    # Voxel each keyframe cloud is pre-downsampled with in its own camera frame, to bound memory;
    # half the map voxel so the global downsample decides the final spacing. 0 disables.
    keyframe_voxel_size_m: float = 0.15
    # build() voxelises consecutive keyframes in chunks of about this many points, then the
    # union of the chunks once more: bounds peak memory on long runs (KITTI 00: ~10 M points).
    build_chunk_points: int = 2_000_000
    build_tile_m: float = 100.0  # ...and the union is voxelised again in x-z tiles of this size
    topdown_colour_by: str = "height"  # top-down PNG: "height" (-y, metres) or "intensity"
    topdown_dpi: int = 150  # top-down PNG resolution (a 8x8 inch figure)
    trajectory: str = "best"  # vo | snaps | isam2 | batch | best (the most refined available)
    per_trajectory: bool = False  # also write map_<trajectory>.ply for every trajectory of the run


@dataclass
class Config:
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    map: MapConfig = field(default_factory=MapConfig)
    loops: str = "snaps"  # snaps | none

    # ---- TOML ----
    @classmethod
    def load(cls, path: str | Path) -> "Config":
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise SnapsGraphError(f"{path}: config file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise SnapsGraphError(f"{path}: malformed TOML ({exc})") from None
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "config") -> "Config":
        cfg = cls()
        for key, value in data.items():
            if not hasattr(cfg, key):
                raise SnapsGraphError(f"{source}: unknown key '{key}'")
            current = getattr(cfg, key)
            if dataclasses.is_dataclass(current):
                if not isinstance(value, dict):
                    raise SnapsGraphError(f"{source}: [{key}] must be a table")
                for sub, subval in value.items():
                    if not hasattr(current, sub):
                        raise SnapsGraphError(f"{source}: unknown key '{key}.{sub}'")
                    setattr(current, sub, _coerce(getattr(current, sub), subval, f"{source}: {key}.{sub}"))
            else:
                setattr(cfg, key, _coerce(current, value, f"{source}: {key}"))
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
        from .io_utils import atomic_write_text

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
