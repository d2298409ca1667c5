"""Typed configuration, one section per stage, loadable from and dumped to TOML.

Every setting a user may change lives here with its one-line help and range as field metadata
(``snaps-graph config`` prints them; constants nobody needs to change stay in their modules); the
SNAPS section keeps the paper's Table I names. A run dumps what it used to ``config.toml``, and
``Config.load`` reads it back (an unknown key is a one-line error, so a typo never passes).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from .config_retired import FIXED, MOVED, RENAMED_VALUES, RETIRED
from .config_schema import (
    Range,
    Section,
    check_value,
    coerce,
    did_you_mean,
    dumps_section,
    hints_of,
    is_section,
    settings,
    toml_value,
)
from .drift_model import DriftModel
from .errors import SnapsGraphError
from .io_utils import atomic_write_text, read_toml

# The one vocabulary of modes (the CLI's --mode/--loops/--refine use the same lists).
FrontendMode = Literal["sift", "orb", "klt"]
DisparityMethod = Literal["bm_wls", "sgbm", "sparse"]
LoopMode = Literal["snaps", "none"]
RefineMode = Literal["none", "isam2", "batch", "both"]  # both = iSAM2 online + batch at the end


# ---- ranges ----
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


def _f(default: Any, help: str, range: Range | None = None) -> Any:
    """A config field: its default, one-line help (meaning, unit) and, for a number, its range.
    ``snaps-graph config`` prints the help and range beside the value."""
    meta: dict[str, Any] = {"help": help}
    if range is not None:
        meta["range"] = range
    return field(default=default, metadata=meta)


@dataclass
class KltConfig(Section):
    """KLT corners and their tracking from the reference frame (``mode = "klt"``)."""

    _name = "frontend.klt"

    features: int = _f(1500, "KLT corners detected when re-detecting", _in(1, MAX_POINTS))
    window_px: int = _f(11, "KLT window, px", _in(3, MAX_WINDOW_PX))
    quality: float = _f(0.01, "goodFeaturesToTrack quality, relative to the best corner", FRACTION)
    min_distance_px: int = _f(10, "minimum spacing between KLT corners, px", _in(1, 1000))
    border_px: int = _f(16, "no KLT corner this close to the image border, px", _nn(1000))
    bias_window_px: int = _f(7, "KLT window-bias removal: re-fit window, px (0 = off)", _nn(MAX_WINDOW_PX))
    weak_points: int = _f(
        300, "weak texture: fewer points with depth than this re-detect at a lower corner quality (0 = off)", _nn(MAX_POINTS)
    )

    def _cross_checks(self, source: str) -> None:
        if self.bias_window_px and not 3 <= self.bias_window_px < self.window_px:
            raise SnapsGraphError(
                f"{source}: frontend.klt.bias_window_px must be 0 or in [3, window_px), got {self.bias_window_px}"
            )


@dataclass
class StereoBAConfig(Section):
    """The two-view stereo bundle adjustment after PnP RANSAC (``motion = "stereo_ba"``)."""

    _name = "frontend.stereo_ba"

    huber_px: float = _f(0.3, "Huber width on a stereo-BA / local-BA residual, px", _pos(100))
    outlier_px: float = _f(0.6, "after the stereo BA's first round, points beyond this are dropped, px", _pos(100))
    keep_px: float = _f(2.0, "a small image keeps tracks within this of the stereo-BA pose too, px", _pos(100))
    iterations: int = _f(3, "stereo-BA Gauss-Newton iterations per round (two rounds)", _in(1, MAX_ITERATIONS))


@dataclass
class LocalBAConfig(Section):
    """The sliding-window stereo BA over the last keyframes (klt)."""

    _name = "frontend.local_ba"

    enabled: bool = _f(True, "klt: sliding-window stereo BA over the last keyframes")
    window: int = _f(6, "keyframes in the local-BA window", _in(2, 100))
    iterations: int = _f(5, "local-BA iterations per solve", _in(1, MAX_ITERATIONS))
    max_landmarks: int = _f(300, "landmarks in the local-BA window (longest tracks first)", _in(10, MAX_POINTS))
    every: int = _f(3, "a reference becomes a keyframe this many frames after the last", _in(1, MAX_FRAMES))
    keyframe_m: float = _f(2.5, "...or once driven this far from the last keyframe (0 = never), m", _nn(1000))
    chain: Literal["off", "yaw", "yaw_roll", "rotation", "full"] = _f(
        "yaw_roll", "which part of the VO chain's step between keyframes constrains the local-BA window"
    )


@dataclass
class OffsetConfig(Section):
    """The rig's disparity offset, configured and estimated online by the local BA."""

    _name = "frontend.offset"

    px: float = _f(0.0, "rig disparity offset (measured - true) at the centre column, px", Range(-10, 10))
    estimate: bool = _f(True, "klt + local BA: estimate the disparity offset online")
    prior_px: float = _f(0.5, "prior sigma of the offset in each local-BA solve, px", _pos(10))
    max_px: float = _f(2.0, "the estimate is clamped to +- this, px", Range(0, 10))
    min_solves: int = _f(3, "solves before an estimate may be applied", _in(1, MAX_FRAMES))
    min_px: float = _f(0.05, "an estimate is applied when it differs by at least this, px", _nn(10))
    max_sd_px: float = _f(0.05, "...and its standard error is at most this, px", _pos(10))
    min_z: float = _f(4.0, "...and it differs by at least this many standard errors", _nn(1e4))
    memory_solves: int = _f(20, "once applied, older solves fade with weight 1 - 1/this (0 = never)", _nn(MAX_FRAMES))


@dataclass
class FrontendConfig(Section):
    """Stereo visual odometry (SPEC "Front end"): the general settings, then one table per part."""

    _name = "frontend"

    mode: FrontendMode = _f("klt", "features: sift (the paper's, slower), orb or klt (fast)")
    disparity: DisparityMethod = _f("sparse", "depth: bm_wls (the paper's StereoBM + WLS), sgbm, or sparse (at keypoints only)")
    num_disparities: int = _f(128, "BM/SGBM disparity search range, px", Range(16, 1024, multiple=16))
    block_size: int = _f(15, "StereoBM block size, px", Range(5, 255, odd=True))
    min_depth_m: float = _f(0.5, "nearer depth is invalid, m", _pos(1000))
    max_depth_m: float = _f(80.0, "farther depth is invalid (eq. 1 is noisy far away), m", _pos(1e4))
    sift_features: int = _f(2000, "SIFT keypoints per image", _in(1, MAX_POINTS))
    sift_first_octave: Literal[-1, 0] = _f(
        0, "SIFT scale space: -1 = image doubled first (OpenCV, the paper), 0 = own resolution (3x faster)"
    )
    orb_features: int = _f(2000, "ORB keypoints per image", _in(1, MAX_POINTS))
    ratio_test: float = _f(0.75, "Lowe's ratio for descriptor matching", FRACTION)
    pnp_reprojection_px: float = _f(1.5, "PnP RANSAC inlier threshold, px", _pos(100))
    min_inliers: int = _f(20, "fewer PnP inliers flag the frame", _in(6, MAX_POINTS))
    max_step_m: float = _f(4.0, "a larger step between frames is implausible (flagged), m", _pos(1000))
    max_step_deg: float = _f(20.0, "a larger turn between frames is implausible (flagged), deg", ANGLE)
    threads: int = _f(2, "worker threads (OpenCV releases the GIL)", Range(1, 256))
    stereo_guess_levels: int = _f(4, "sparse stereo LK pyramid levels for points with a predicted disparity", _nn(MAX_LEVELS))
    frame_features: int = _f(
        500, "keypoints with depth kept per frame in the VO result (the viewer's points)", _in(1, MAX_POINTS)
    )
    motion: Literal["pnp", "stereo_ba"] = _f(
        "stereo_ba", "after PnP RANSAC: stereo_ba = two-view stereo bundle adjustment, pnp = PnP + LM (the paper's)"
    )
    klt: KltConfig = field(default_factory=KltConfig)
    stereo_ba: StereoBAConfig = field(default_factory=StereoBAConfig)
    local_ba: LocalBAConfig = field(default_factory=LocalBAConfig)
    offset: OffsetConfig = field(default_factory=OffsetConfig)

    def _cross_checks(self, source: str) -> None:
        if not self.min_depth_m < self.max_depth_m:
            raise SnapsGraphError(
                f"{source}: frontend.min_depth_m must be < frontend.max_depth_m, got {self.min_depth_m} and {self.max_depth_m}"
            )


@dataclass
class VerificationConfig(Section):
    """Geometric verification of a loop candidate: its own keypoints on reference frames, matched
    and solved by PnP against the current frame (stereo, or triangulated from two views)."""

    _name = "verification"

    detector: Literal["orb", "sift"] = _f("orb", "loop verification keypoints: orb (pyramid) or sift (octave 0)")


@dataclass
class LoopConfig(Section):
    """SNAPS loop closure (paper §III, Table I; SPEC "SNAPS loop closure")."""

    _name = "loop"

    policy: Literal["drift", "paper"] = _f(
        "drift", "the rule: drift (ours: drift-model gate and correction, verified loops) or paper (SNAPS as printed)"
    )
    radius_m: float = _f(
        10.0, "candidates lie within this distance of the current position (the drift gate's least), m", _pos(1e4)
    )
    frame_distance: int = _f(100, "M: candidate j must satisfy N - j >= M, frames", _in(1, MAX_FRAMES))
    discount_length: int = _f(100, "K: eq. 6 moves poses N-K..N (the paper policy's fixed window), frames", _nn(MAX_FRAMES))
    min_similarity: float = _f(0.15, "Q threshold for a loop (UIQI)", FRACTION)
    inter_frame_pause: int = _f(50, "frames after the last pinned frame before another loop", _nn(MAX_FRAMES))
    thumbnail_scale: float = _f(1.0 / 6.0, "thumbnail = left image rescaled by this", FRACTION)
    window: int = _f(16, "UIQI sliding window B, thumbnail px", _in(2, 256))


@dataclass
class GraphConfig(Section):
    """GTSAM factor graph (SPEC "Factor graph")."""

    _name = "graph"

    refine: RefineMode = _f("none", "none, isam2, batch, or both (iSAM2 online + batch at the end)")
    odom_sigma_rot_rad: float = _f(0.005, "VO step rotation sigma at 200 inliers (scaled by sqrt(200 / inliers)), rad", SIGMA_ROT)
    odom_sigma_trans_m: float = _f(
        0.05, "VO step translation sigma at 200 inliers (scaled by sqrt(200 / inliers)), m", SIGMA_TRANS
    )
    loop_sigma_rot_rad: float = _f(0.01, "verified loop rotation sigma at Q = 1, rad", SIGMA_ROT)
    loop_sigma_trans_m: float = _f(0.1, "verified loop translation sigma at Q = 1, m", SIGMA_TRANS)
    unverified_sigma_trans_m: float = _f(2.0, "unverified loop translation sigma (same-place assumption), m", SIGMA_TRANS)
    loop_q_floor: float = _f(0.0, "Q at which a loop's sigmas would be infinite", Range(0, 1, hi_open=True))
    robust_kernel: Literal["huber", "cauchy", "none"] = _f("cauchy", "robust kernel on loop factors")
    odom_cov_scale: float = _f(1.0, "a stereo-BA step covariance is multiplied by this squared", _pos(MAX_SCALE))
    loop_cov_scale: float = _f(4.0, "a verified loop's PnP covariance multiplier", _pos(MAX_SCALE))
    loop_sigma_floor_rot_rad: float = _f(0.002, "rotation sigma added in quadrature to a verified loop's, rad", _nn(math.pi))
    loop_sigma_floor_trans_m: float = _f(0.02, "translation sigma added in quadrature to a verified loop's, m", _nn(1e4))


@dataclass
class MapConfig(Section):
    """Point-cloud map (SPEC "Map")."""

    _name = "map"

    enabled: bool = _f(False, "build the TSDF map")
    keyframe_every: int = _f(5, "one map keyframe every this many frames", _in(1, MAX_FRAMES))
    max_range_m: float = _f(15.0, "map depth beyond this is dropped, m", _pos(1000))
    trajectory: Literal["vo", "snaps", "isam2", "batch", "best"] = _f(
        "best", "trajectory the map is built on (best = the most refined)"
    )
    per_trajectory: bool = _f(False, "also write map_<trajectory>.ply for every trajectory")
    depth_method: Literal["sgbm", "bm"] = _f("sgbm", "map stereo matcher: StereoSGBM or StereoBM")
    depth_scale: float = _f(0.5, "map stereo runs on images resized by this", Range(0.1, 1))
    depth_block_size: int = _f(5, "map matcher block size at the working size, px", Range(1, 255, odd=True))
    depth_uniqueness: int = _f(15, "best match must beat the second by this, percent", Range(0, 100))
    depth_lr_check_px: float = _f(1.0, "left-right consistency limit (0 = off), px", _nn(100))
    depth_min_confidence: float = _f(0.0, "WLS confidence (0-255) below this is invalid (0 = no WLS)", Range(0, 255))
    depth_edge_ratio: float = _f(0.1, "invalid where the 3x3 disparity spread exceeds this x d", _nn(100))
    depth_speckle_px: int = _f(50, "disparity regions smaller than this are dropped, working px", _nn(10**6))
    tsdf_voxel_m: float = _f(0.15, "TSDF voxel edge, m", _pos(10))
    tsdf_trunc_voxels: float = _f(6.0, "TSDF truncation distance, voxels", _in(1, 100))
    tsdf_max_blocks: int = _f(40000, "a fused chunk is extracted at this many blocks (6 KB each)", _in(1000, 10**7))
    tsdf_min_weight: float = _f(1.0, "surface kept where at least this many keyframes saw it", _nn(10**6))
    tsdf_min_component: int = _f(0, "mesh pieces of fewer triangles are dropped (0 = keep all)", _nn(10**8))
    world_mesh: str = _f("", "the true world as a triangle mesh, for map accuracy (empty = none)")
    accuracy_range_m: float = _f(20.0, "completeness counts true surface within this of the path, m", _pos(1e4))
    accuracy_tolerance_m: float = _f(0.2, "...and within this of the map, m", _pos(100))
    accuracy_samples: int = _f(200_000, "true-surface samples for completeness", _in(1000, 10**8))

    def _cross_checks(self, source: str) -> None:
        if self.depth_method == "bm" and self.depth_block_size < 5:
            raise SnapsGraphError(
                f"{source}: map.depth_block_size must be >= 5 for depth_method 'bm', got {self.depth_block_size}"
            )


@dataclass
class OdometryConfig(Section):
    """The odometry's drift model (1 sigma, per metre driven; snaps_graph.drift_model): the pose
    graph's odometry noise, the drift-aware loop search's gate and the heuristic correction's shape
    all follow it; ``snaps-graph drift-fit EST GT`` measures it for an odometry with ground truth."""

    _name = "odometry"

    heading_deg_per_sqrt_m: float = _f(0.07, "heading random walk, deg per sqrt(m)", Range(0, 90, lo_open=True))
    pitch_deg_per_sqrt_m: float = _f(0.017, "pitch random walk, deg per sqrt(m)", _nn(90))
    roll_deg_per_sqrt_m: float = _f(0.017, "roll random walk, deg per sqrt(m)", _nn(90))
    scale_pct: float = _f(0.02, "translation scale error, percent", _nn(50))
    trans_m_per_sqrt_m: float = _f(
        0.002, "translation random walk of a step, every axis, m per sqrt(m)", Range(0, 10, lo_open=True)
    )

    def model(self) -> DriftModel:
        return DriftModel(
            heading_deg_per_sqrt_m=self.heading_deg_per_sqrt_m,
            pitch_deg_per_sqrt_m=self.pitch_deg_per_sqrt_m,
            roll_deg_per_sqrt_m=self.roll_deg_per_sqrt_m,
            scale_pct=self.scale_pct,
            trans_m_per_sqrt_m=self.trans_m_per_sqrt_m,
        )


@dataclass
class Config:
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    map: MapConfig = field(default_factory=MapConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    loops: LoopMode = _f("snaps", "loop closure: snaps or none")

    def __post_init__(self) -> None:
        self.source = "config"  # the file it was loaded from, named in validation errors
        self.validate()

    def validate(self, source: str | None = None) -> None:
        """Every field (types, enumerations, ranges) and the rules across fields; a one-line
        SnapsGraphError naming the config file and the key. ``snaps-graph config FILE`` and
        ``run`` (before the first frame) both call this on the configuration that would run."""
        source = source or self.source
        for f in dataclasses.fields(self):
            if is_section(section := getattr(self, f.name)):
                section.validate(source)
        check_value(self.loops, hints_of(type(self))["loops"], None, f"{source}: loops")
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
        mesh = out.map.world_mesh
        if out.map.enabled and mesh and not Path(mesh).is_file():  # else the map stage fails after every frame
            what = "is a folder, not a world mesh" if Path(mesh).is_dir() else "world mesh not found"
            where = f" in {out.source}" if out.source and out.source != "config" else ""
            raise SnapsGraphError(f"{mesh}: {what} (map.world_mesh{where})")
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
        cfg._apply(data, source)
        return cfg

    def with_overrides(self, items: list[str] | tuple[str, ...], source: str = "--set") -> "Config":
        """A copy with ``section.key=value`` overrides (:func:`parse_set`) applied, validated."""
        return self.merged(parse_set(items, source), source) if items else copy.deepcopy(self)

    def merged(self, data: dict[str, Any], source: str) -> "Config":
        """A copy with ``data`` (nested tables, as a config file gives them) applied, validated."""
        out = copy.deepcopy(self)
        out._apply(data, source)
        return out

    def _apply(self, data: dict[str, Any], source: str) -> None:
        _apply_table(self, _moved(data, source), source, "")
        self.validate()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def dumps(self, comments: bool = False) -> str:
        """The configuration as TOML, a nested section as its own table (``[frontend.klt]``);
        ``comments`` adds each key's help and range as a comment."""
        return "\n".join(dumps_section(self, "", comments)) + "\n"

    def dump(self, path: str | Path) -> None:
        atomic_write_text(path, self.dumps())


def parse_set(items: list[str] | tuple[str, ...], source: str = "--set") -> dict[str, Any]:
    """``section.key=value`` items, a nested section's key with its full path
    (``frontend.klt.window_px=11``; the value in TOML: 3, 0.5, true, "yaw"; a bare word is a
    string) as the nested dict a config file would give; a malformed item is a one-line error."""
    data: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        parts = [p.strip() for p in key.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise SnapsGraphError(f"{source} {item!r}: expected section.key=value")
        if "\n" in value or "\r" in value:  # a second line could carry tables the key would not show
            raise SnapsGraphError(f"{source} {item!r}: the value must be one TOML value on one line")
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            parsed = value.strip()
        table, bad = _table_at(data, parts[:-1])
        if table is None:
            raise SnapsGraphError(f"{source} {item!r}: {bad} is a value, not a section")
        if isinstance(table.get(parts[-1]), dict):
            raise SnapsGraphError(f"{source} {item!r}: {key.strip()} is a section, not a value")
        table[parts[-1]] = parsed
    return data


def _table_at(root: dict[str, Any], parts: list[str]) -> tuple[dict[str, Any] | None, str]:
    """The nested table at the path ``parts`` in ``root`` (created where missing), or (None, the
    path up to the first part that holds a value, not a table)."""
    table = root
    for i, part in enumerate(parts):
        table = table.setdefault(part, {})
        if not isinstance(table, dict):
            return None, ".".join(parts[: i + 1])
    return table, ""


def _moved(data: dict[str, Any], source: str) -> dict[str, Any]:
    """``data`` with each key an older version wrote flat (``frontend.klt_window_px``) at its place
    now (``frontend.klt.window_px``), a one-line note for each; both places given is an error."""
    out: dict[str, Any] = {}
    moves: list[tuple[str, Any]] = []

    def walk(src: dict[str, Any], dst: dict[str, Any], prefix: str) -> None:
        for key, value in src.items():
            path = prefix + key
            if path in MOVED and not isinstance(value, dict):  # an old key held a value, never a table
                moves.append((path, value))
            elif isinstance(value, dict):
                walk(value, dst.setdefault(key, {}), path + ".")
            else:
                dst[key] = value

    walk(data, out, "")
    for old, value in moves:
        new = MOVED[old]
        print(f"note: {source}: {old} moved to {new}", file=sys.stderr)
        *parents, name = new.split(".")
        table, bad = _table_at(out, parents)
        if table is None:
            raise SnapsGraphError(f"{source}: [{bad}] must be a table")
        if name in table:
            raise SnapsGraphError(f"{source}: {old} and {new} are the same setting; give {new} only")
        table[name] = value
    return out


def _apply_table(obj: Any, data: dict[str, Any], source: str, prefix: str) -> None:
    """Set ``obj``'s fields from ``data``, a nested section from its own table, in turn."""
    names = {f.name for f in dataclasses.fields(obj)}
    for key, value in data.items():
        path = prefix + key
        if path in RETIRED or path in FIXED:  # an older version wrote it
            print(f"note: {source}: {_retired_note(path, value)}; ignored", file=sys.stderr)
            continue
        if key not in names:
            raise SnapsGraphError(f"{source}: unknown key '{path}'{did_you_mean(key, obj, prefix)}")
        current = getattr(obj, key)
        if is_section(current):
            if not isinstance(value, dict):
                raise SnapsGraphError(f"{source}: [{path}] must be a table")
            _apply_table(current, value, source, path + ".")
        elif isinstance(value, dict):  # a table where a value belongs: a misspelled section
            tables = [n for n in sorted(names) if is_section(getattr(obj, n))]
            close = difflib.get_close_matches(key, tables, n=1)
            hint = f" (did you mean [{prefix}{close[0]}]?)" if close else ""
            raise SnapsGraphError(f"{source}: [{path}] is not a section{hint}")
        else:
            renamed = RENAMED_VALUES.get((path, value)) if isinstance(value, str) else None
            if renamed is not None:
                print(
                    f"note: {source}: {path} = {toml_value(value)} is {toml_value(renamed[0])} now ({renamed[1]})",
                    file=sys.stderr,
                )
                value = renamed[0]
            setattr(obj, key, coerce(current, value, f"{source}: {path}"))


def _retired_note(key: str, value: Any) -> str:
    if key in FIXED:
        fixed = FIXED[key]
        if value == fixed and type(value) is type(fixed):
            return f"{key} is no longer a setting (fixed at {toml_value(fixed)})"
        return f"{key} is no longer a setting: it is fixed at {toml_value(fixed)} now, this file's {toml_value(value)} is ignored"
    return f"{key} is no longer used ({RETIRED[key]})"


# The range of every numeric field, "section.field" -> Range, from the fields' metadata.
RULES: dict[str, Range] = {key: f.metadata["range"] for key, f, _ in settings(Config()) if "range" in f.metadata}
