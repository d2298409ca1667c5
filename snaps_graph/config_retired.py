"""Config keys of older versions, read back from an old config.toml: keys that are gone with
their option and settings that are constants in the code now (read with a note, ignored), and
keys that moved to a section of their own (read with a note, applied at their new place)."""

from __future__ import annotations

from typing import Any

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
    "an LK call spreads over OpenCV's own threads, never split in two": ("frontend.lk_split_min",),
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
    "the drift model's random walks per sqrt(m) replace one translation and one heading rate "
    "(snaps-graph drift-fit measures them)": ("odometry.trans_drift_pct", "odometry.rot_drift_deg_per_100m"),
    "every odometry step's noise holds the [odometry] drift model's error for its distance": (
        "graph.odom_cov_floor_rot_rad",
        "graph.odom_cov_floor_trans_m",
    ),
    "a verified turn's gain takes the heading's prior from the [odometry] drift model": ("loop.heading_drift_deg",),
}
RETIRED = {key: why for why, keys in _RETIRED_GROUPS.items() for key in keys}
RETIRED |= {
    "loop.correction_model": 'a verified heading turn always bends eq. 6\'s window ("shift" measured worse)',
    "loop.heading_prior": 'the heading prior is the drift since the reference ("tracked" measured no better)',
    "loop.ramp": "eq. 6's ramp follows the distance driven (by frame count measured worse)",
    "loop.pause_closer_ratio": "loop.pause_graph_loops gives the graph the verified loops inside the pause (closer ones only measured worse)",
}

# Settings that are constants in the code now (the module's name in upper case): an older
# config.toml that holds one is read with a note. tests/test_config.py checks the values agree.
FIXED: dict[str, Any] = {
    "frontend.wls_lambda": 8000.0,
    "frontend.wls_sigma": 1.5,
    "frontend.sgbm_block_size": 5,
    "frontend.stereo_window_px": 11,
    "frontend.stereo_levels": 4,
    "frontend.stereo_max_dy_px": 1.0,
    "frontend.stereo_lr_check_px": 0.5,
    "frontend.klt_min_tracks": 600,
    "frontend.klt_retry_features": 4000,
    "frontend.klt_levels": 3,
    "frontend.klt_bias_max_px": 0.5,
    "frontend.min_frame_std": 3.0,
    "frontend.min_sharpness_ratio": 0.35,
    "frontend.pnp_iterations": 200,
    "frontend.pnp_confidence": 0.999,
    "frontend.sba_keep_below": 100,
    "frontend.lba_chain_scale": 1.0,
    "frontend.loop_orb_levels": 8,
    "frontend.loop_orb_scale": 1.2,
    "frontend.loop_orb_fast_threshold": 20,
    "frontend.loop_orb_upright": True,
    "frontend.loop_ratio_test": 0.8,
    "frontend.loop_depth_min_ratio": 0.5,
    "frontend.loop_min_sigma_px": 0.5,
    "frontend.verify_max_translation_m": 30.0,
    "frontend.verify_max_rotation_deg": 90.0,
    "graph.prior_sigma_rot_rad": 1e-4,
    "graph.prior_sigma_trans_m": 1e-3,
    "graph.odom_min_inliers": 20,
    "graph.unverified_sigma_rot_rad": 0.5,
    "graph.robust_param": 3.0,
    "graph.isam2_relinearize_threshold": 0.01,
    "graph.isam2_relinearize_skip": 1,
    "graph.isam2_loop_iterations": 0,
    "graph.isam2_final_iterations": 10,
    "frontend.ransac_seed": 0,
    "frontend.loop_orb_features": 1000,
    "frontend.loop_query_features": 1500,
    "frontend.min_stereo_points": 40,
    "frontend.klt_weak_quality": 0.001,
    "graph.batch_max_iterations": 100,
    "graph.odom_sigma_scale_min": 0.5,
    "graph.odom_sigma_scale_max": 4.0,
    "graph.odom_ref_inliers": 200,
    "graph.flagged_sigma_scale": 100.0,
    "graph.loop_sigma_scale_max": 10.0,
    "map.depth_texture_threshold": 10,
    "map.depth_speckle_range_px": 1.0,
}

# Keys older versions wrote flat in [frontend], at their place now: read back, the value applied
# there, with a note.
MOVED: dict[str, str] = {
    "frontend.klt_features": "frontend.klt.features",
    "frontend.klt_window_px": "frontend.klt.window_px",
    "frontend.klt_quality": "frontend.klt.quality",
    "frontend.klt_min_distance_px": "frontend.klt.min_distance_px",
    "frontend.klt_border_px": "frontend.klt.border_px",
    "frontend.klt_bias_window_px": "frontend.klt.bias_window_px",
    "frontend.klt_weak_points": "frontend.klt.weak_points",
    "frontend.sba_huber_px": "frontend.stereo_ba.huber_px",
    "frontend.sba_outlier_px": "frontend.stereo_ba.outlier_px",
    "frontend.sba_keep_px": "frontend.stereo_ba.keep_px",
    "frontend.sba_iterations": "frontend.stereo_ba.iterations",
    "frontend.local_ba": "frontend.local_ba.enabled",
    "frontend.lba_window": "frontend.local_ba.window",
    "frontend.lba_iterations": "frontend.local_ba.iterations",
    "frontend.lba_max_landmarks": "frontend.local_ba.max_landmarks",
    "frontend.lba_every": "frontend.local_ba.every",
    "frontend.lba_keyframe_m": "frontend.local_ba.keyframe_m",
    "frontend.lba_chain": "frontend.local_ba.chain",
    "frontend.disparity_offset_px": "frontend.offset.px",
    "frontend.estimate_disparity_offset": "frontend.offset.estimate",
    "frontend.disparity_offset_prior_px": "frontend.offset.prior_px",
    "frontend.disparity_offset_max_px": "frontend.offset.max_px",
    "frontend.disparity_offset_min_solves": "frontend.offset.min_solves",
    "frontend.disparity_offset_min_px": "frontend.offset.min_px",
    "frontend.disparity_offset_max_sd_px": "frontend.offset.max_sd_px",
    "frontend.disparity_offset_min_z": "frontend.offset.min_z",
    "frontend.disparity_offset_memory_solves": "frontend.offset.memory_solves",
    "frontend.loop_features": "frontend.frame_features",
    "frontend.loop_detector": "verification.detector",
    "frontend.loop_reference_every": "verification.reference_every",
    "frontend.loop_depth_check_px": "verification.depth_check_px",
    "frontend.loop_max_distance_m": "verification.max_distance_m",
    "frontend.loop_subpixel_px": "verification.subpixel_px",
}

# Values older versions wrote that mean another value now: read with a note, applied as the new one.
RENAMED_VALUES: dict[tuple[str, Any], tuple[Any, str]] = {
    ("loop.discount_shape", "linear"): (
        "drift",
        "the ramp follows the [odometry] drift model; a translation walk gives the linear ramp",
    ),
}
