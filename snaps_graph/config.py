"""Typed configuration, one section per stage, loadable from and dumped to TOML.

A setting here is a choice a user makes for their data or purpose, with its one-line help and
range as field metadata (``snaps-graph config`` prints them); tuning nobody needs to change is a
named constant beside the code that reads it. Presets by name (``PRESETS``: ``default``,
``paper``) compose with a config file and ``--set`` items in that order (``Config.compose``). A
run dumps what it used to ``config.toml``, and ``Config.load`` reads it back (an unknown key is a
one-line error, so a typo never passes; a key an older version had is a one-line note).
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

from .config_retired import OLD_KEYS, Moved
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
class FrontendConfig(Section):
    """Stereo visual odometry (SPEC "Front end"): what runs and what the camera sees; the tuning
    of each part is a constant beside its code (the KLT in ``frontend/features.py``, the stereo
    BA in ``stereo_ba.py``, the local BA in ``local_ba.py``, the offset rule in ``offset.py``)."""

    _name = "frontend"

    mode: FrontendMode = _f("klt", "features: sift (the paper's, slower), orb or klt (fast)")
    disparity: DisparityMethod = _f("sparse", "depth: bm_wls (the paper's StereoBM + WLS), sgbm, or sparse (at keypoints only)")
    motion: Literal["pnp", "stereo_ba"] = _f(
        "stereo_ba", "after PnP RANSAC: stereo_ba = two-view stereo bundle adjustment, pnp = PnP + LM (the paper's)"
    )
    local_ba: bool = _f(True, "klt: sliding-window stereo BA over the last keyframes")
    sift_first_octave: Literal[-1, 0] = _f(
        0, "SIFT scale space: -1 = image doubled first (OpenCV, the paper), 0 = own resolution (3x faster)"
    )
    num_disparities: int = _f(
        128, "BM/SGBM disparity search range (wider for a long baseline or near scenes), px", Range(16, 1024, multiple=16)
    )
    min_depth_m: float = _f(0.5, "nearer depth is invalid, m", _pos(1000))
    max_depth_m: float = _f(80.0, "farther depth is invalid (eq. 1 is noisy far away), m", _pos(1e4))
    offset_px: float = _f(0.0, "the rig's disparity offset (measured - true) at the centre column, px", Range(-10, 10))
    estimate_offset: bool = _f(True, "klt + local BA: estimate the disparity offset online")
    threads: int = _f(2, "worker threads (OpenCV releases the GIL)", Range(1, 256))

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
    """GTSAM factor graph (SPEC "Factor graph"); the rest of its noise: ``backend/noise.py``."""

    _name = "graph"

    refine: RefineMode = _f("none", "none, isam2, batch, or both (iSAM2 online + batch at the end)")
    robust_kernel: Literal["huber", "cauchy", "none"] = _f("cauchy", "robust kernel on loop factors")
    odom_sigma_rot_rad: float = _f(0.005, "VO step rotation sigma at 200 inliers (scaled by sqrt(200 / inliers)), rad", SIGMA_ROT)
    odom_sigma_trans_m: float = _f(
        0.05, "VO step translation sigma at 200 inliers (scaled by sqrt(200 / inliers)), m", SIGMA_TRANS
    )
    loop_sigma_rot_rad: float = _f(0.01, "verified loop rotation sigma at Q = 1, rad", SIGMA_ROT)
    loop_sigma_trans_m: float = _f(0.1, "verified loop translation sigma at Q = 1, m", SIGMA_TRANS)


@dataclass
class MapConfig(Section):
    """Fused surface map (SPEC "Map"); its stereo matcher's and fusion's tuning: constants in
    ``frontend/depth.py`` and ``mapping/tsdf.py``."""

    _name = "map"

    enabled: bool = _f(False, "build the TSDF map")
    trajectory: Literal["vo", "snaps", "isam2", "batch", "best"] = _f(
        "best", "trajectory the map is built on (best = the most refined)"
    )
    per_trajectory: bool = _f(False, "also write map_<trajectory>.ply for every trajectory")
    keyframe_every: int = _f(5, "one map keyframe every this many frames", _in(1, MAX_FRAMES))
    max_range_m: float = _f(15.0, "map depth beyond this is dropped, m", _pos(1000))
    depth_scale: float = _f(0.5, "map stereo runs on images resized by this (1 = full detail, slower)", Range(0.1, 1))
    tsdf_voxel_m: float = _f(0.15, "TSDF voxel edge (finer = more detail, more memory), m", _pos(10))


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


# Named presets: overrides of the defaults, checked as a config file is (``Config.preset``).
# paper: the paper's front end (OpenCV SIFT with the doubled first octave, StereoBM + WLS depth,
# PnP + LM, no local BA) and its loop closure rule.
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {
        "frontend": {"mode": "sift", "sift_first_octave": -1, "disparity": "bm_wls", "motion": "pnp", "local_ba": False},
        "loop": {"policy": "paper", "min_similarity": 0.75, "window": 8},  # Table I's threshold and UIQI window
    },
}


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
        return out

    @classmethod
    def preset(cls, name: str) -> "Config":
        """The named preset (``PRESETS``): the defaults with its overrides, validated."""
        if name not in PRESETS:
            raise SnapsGraphError(f"unknown preset '{name}' (one of {', '.join(PRESETS)})")
        return cls().merged(PRESETS[name], f"preset {name}")

    @classmethod
    def compose(
        cls, preset: str = "default", path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()
    ) -> "Config":
        """A preset, then a config file over it, then ``section.key=value`` items over both: the
        order ``run --preset P --config F --set K=V`` applies them in (the run's ``--mode``,
        ``--loops``, ``--refine`` and ``--map`` come last)."""
        cfg = cls.preset(preset)
        if path is not None:
            data = read_toml(Path(path), "config")
            cfg.source = str(path)  # the file is what a later error names
            cfg = cfg.merged(data, str(path))
        return cfg.with_overrides(overrides)

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
        _apply_table(self, _old_keys(data, source), source, "")
        self.validate()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def dumps(self, comments: bool = False) -> str:
        """The configuration as TOML, a nested section as its own table (``[section.part]``);
        ``comments`` adds each key's help and range as a comment."""
        return "\n".join(dumps_section(self, "", comments)) + "\n"

    def dump(self, path: str | Path) -> None:
        atomic_write_text(path, self.dumps())


def parse_set(items: list[str] | tuple[str, ...], source: str = "--set") -> dict[str, Any]:
    """``section.key=value`` items, a nested section's key with its full path
    (``section.part.key=1``; the value in TOML: 3, 0.5, true, "yaw"; a bare word is a
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


def _old_keys(data: dict[str, Any], source: str) -> dict[str, Any]:
    """``data`` without the keys an older version had (``OLD_KEYS``), a one-line note for each: a
    key that moved has its value applied at its place now (both places given is an error), one
    that became a constant is ignored, and a table left empty by them goes too."""
    moves: list[tuple[str, str, Any]] = []

    def walk(src: dict[str, Any], prefix: str) -> dict[str, Any]:
        dst: dict[str, Any] = {}
        for key, value in src.items():
            path = prefix + key
            old = OLD_KEYS.get(path)
            if old is not None and not isinstance(value, dict):  # an old key held a value, never a table
                if isinstance(old, Moved):
                    moves.append((path, old.to, value))
                else:
                    print(f"note: {source}: {path} = {_shown(value)} is no longer a setting ({old}); ignored", file=sys.stderr)
            elif isinstance(value, dict):
                sub = walk(value, path + ".")
                if sub or not any(k.startswith(path + ".") for k in OLD_KEYS) or _is_section_path(path):
                    dst[key] = sub
            else:
                dst[key] = value
        return dst

    out = walk(data, "")
    for old, new, value in moves:
        print(f"note: {source}: {old} moved to {new}", file=sys.stderr)
        *parents, name = new.split(".")
        table, bad = _table_at(out, parents)
        if table is None:
            raise SnapsGraphError(f"{source}: [{bad}] must be a table")
        if name in table:
            raise SnapsGraphError(f"{source}: {old} and {new} are the same setting; give {new} only")
        table[name] = value
    return out


def _is_section_path(path: str) -> bool:
    """``path`` ("frontend") names a section of the configuration now."""
    obj: Any = Config
    for part in path.split("."):
        fields = {f.name: f for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else {}
        if part not in fields:
            return False
        obj = hints_of(obj if isinstance(obj, type) else type(obj))[part]
    return isinstance(obj, type) and dataclasses.is_dataclass(obj)


def _shown(value: Any) -> str:
    try:
        return toml_value(value)
    except TypeError:
        return repr(value)


def _apply_table(obj: Any, data: dict[str, Any], source: str, prefix: str) -> None:
    """Set ``obj``'s fields from ``data``, a nested section from its own table, in turn."""
    names = {f.name for f in dataclasses.fields(obj)}
    for key, value in data.items():
        path = prefix + key
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
            setattr(obj, key, coerce(current, value, f"{source}: {path}"))


# The range of every numeric field, "section.field" -> Range, from the fields' metadata.
RULES: dict[str, Range] = {key: f.metadata["range"] for key, f, _ in settings(Config()) if "range" in f.metadata}
