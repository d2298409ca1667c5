"""Keys the previous version's config had, read back from its config.toml with a one-line note:
a key that moved is applied at its place now; a setting that became a constant (or an
evaluation option) is ignored, the note naming where it lives. Keys of earlier development
states are not kept: such a file is an error naming the key."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Moved:
    to: str  # the key's place now: the old value is applied there


def _constants(module: str, names: dict[str, str]) -> dict[str, str]:
    """old key -> "NAME in snaps_graph/MODULE.py" for settings that are constants there now."""
    return {key: f"{name} in snaps_graph/{module.replace('.', '/')}.py" for key, name in names.items()}


# key -> its place now (Moved) or a note saying where it went.
OLD_KEYS: dict[str, str | Moved] = {
    "frontend.local_ba.enabled": Moved("frontend.local_ba"),
    "frontend.offset.px": Moved("frontend.offset_px"),
    "frontend.offset.estimate": Moved("frontend.estimate_offset"),
    "map.world_mesh": "an evaluation option: run --world-mesh, compare --world-mesh",
    **_constants(
        "frontend.features",
        {"frontend.sift_features": "SIFT_FEATURES", "frontend.orb_features": "ORB_FEATURES", "frontend.ratio_test": "RATIO_TEST"}
        | {f"frontend.klt.{k}": f"KLT.{k}" for k in ("features", "window_px", "quality", "min_distance_px", "border_px")}
        | {f"frontend.klt.{k}": f"KLT.{k}" for k in ("bias_window_px", "weak_points")},
    ),
    **_constants(
        "frontend.motion",
        {
            "frontend.pnp_reprojection_px": "PNP_REPROJECTION_PX",
            "frontend.min_inliers": "MIN_INLIERS",
            "frontend.max_step_m": "MAX_STEP_M",
            "frontend.max_step_deg": "MAX_STEP_DEG",
        },
    ),
    **_constants("frontend.keyframe", {"frontend.frame_features": "FRAME_FEATURES"}),
    **_constants(
        "frontend.stereo_ba",
        {f"frontend.stereo_ba.{k}": f"STEREO_BA.{k}" for k in ("huber_px", "outlier_px", "keep_px", "iterations")},
    ),
    **_constants(
        "frontend.local_ba",
        {"frontend.local_ba.window": "LBA_WINDOW", "frontend.local_ba.iterations": "LBA_ITERATIONS"}
        | {"frontend.local_ba.max_landmarks": "LBA_MAX_LANDMARKS"},
    ),
    **_constants(
        "frontend.lba_schedule",
        {
            "frontend.local_ba.every": "LBA_EVERY",
            "frontend.local_ba.keyframe_m": "LBA_KEYFRAME_M",
            "frontend.local_ba.chain": "LBA_CHAIN",
        },
    ),
    **_constants(
        "frontend.offset",
        {f"frontend.offset.{k}": f"OFFSET_RULE.{k}" for k in ("prior_px", "max_px", "min_solves", "min_px", "max_sd_px", "min_z")}
        | {"frontend.offset.memory_solves": "OFFSET_RULE.memory_solves"},
    ),
    **_constants(
        "frontend.depth",
        {"frontend.block_size": "BM_BLOCK_SIZE", "frontend.stereo_guess_levels": "STEREO_GUESS_LEVELS"},
    ),
    **_constants(
        "mapping.depth",
        {
            "map.depth_method": "MAP_DEPTH_METHOD",
            "map.depth_block_size": "MAP_BLOCK_SIZE",
            "map.depth_uniqueness": "MAP_UNIQUENESS",
        }
        | {"map.depth_lr_check_px": "MAP_LR_CHECK_PX", "map.depth_min_confidence": "MAP_MIN_CONFIDENCE"}
        | {"map.depth_edge_ratio": "MAP_EDGE_RATIO", "map.depth_speckle_px": "MAP_SPECKLE_PX"},
    ),
    **_constants(
        "mapping.tsdf",
        {f"map.tsdf_{k}": f"TSDF_{k.upper()}" for k in ("trunc_voxels", "max_blocks", "min_weight", "min_component")},
    ),
    **_constants(
        "mapping.accuracy",
        {"map.accuracy_range_m": "RANGE_M", "map.accuracy_tolerance_m": "TOLERANCE_M", "map.accuracy_samples": "MIN_SAMPLES"},
    ),
    **_constants(
        "backend.noise",
        {f"graph.{k}": k.upper() for k in ("unverified_sigma_trans_m", "loop_q_floor", "odom_cov_scale", "loop_cov_scale")}
        | {f"graph.{k}": k.upper() for k in ("loop_sigma_floor_rot_rad", "loop_sigma_floor_trans_m")},
    ),
}

# [loop] and [verification]: the rule's flags are the two policies now, the rest constants.
OLD_KEYS |= {
    "loop.search": 'loop.policy: "drift" = drift, "paper" = radius',
    "loop.discount_window": 'loop.policy: "drift" = span, "paper" = fixed (discount_length)',
    "loop.discount_shape": 'loop.policy: "drift" = drift, "paper" = paper',
    "loop.correction_weight": 'loop.policy: "drift" = verified, "paper" = q',
    "loop.correction_axes": 'loop.policy: "drift" = ground, "paper" = xyz',
    "loop.correction_rotation": 'loop.policy: "drift" = yaw, "paper" = none',
    "loop.use_verified_offset": 'loop.policy: "drift" = true, "paper" = false',
    "loop.require_verification": 'loop.policy: "drift" = true, "paper" = false',
    "loop.pause_graph_loops": 'loop.policy: "drift" = true, "paper" = false',
    "loop.shift_px": "removed: shifted thumbnails measured worse (docs/decisions.md); comparisons are unshifted",
    "loop.shift_step_px": "removed with loop.shift_px",
    "loop.verify_all_candidates": "removed: an experiment's switch (benchmarks/ verifies every candidate itself)",
    **_constants(
        "loop.policy",
        {f"loop.{k}": f"LoopPolicy.{k}" for k in ("attempts", "max_yaw_deg", "discount_offset", "discount_rate")}
        | {f"loop.{k}": f"LoopPolicy.{k}" for k in ("search_sigmas", "search_max_radius_m", "verify_attempts")}
        | {"loop.verified_heading_sigma_deg": "LoopPolicy.verified_heading_sigma_deg"}
        | {"loop.discount_span_factor": "LoopPolicy.span_factor", "loop.discount_length_max": "LoopPolicy.span_max"},
    ),
    **_constants("loop.uiqi", {"loop.stats_cache_frames": "STATS_CACHE_FRAMES"}),
    **_constants(
        "verification.features",
        {f"verification.{k}": k.upper() for k in ("reference_every", "depth_check_px", "max_distance_m", "subpixel_px")},
    ),
}
