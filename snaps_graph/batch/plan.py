"""Plans: a TOML of sequences and variants, checked on the driver and expanded into cells."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import re
import subprocess
from pathlib import Path
from typing import Any

from .. import __version__
from ..config import Config, FrontendMode, LoopMode, RefineMode
from ..config_schema import choices
from ..datasets.open import open_dataset
from ..errors import SnapsGraphError
from ..io_utils import (
    parse_frame_range,
    read_toml,
)
from ..types import StereoSource

# Run options a plan (top level or a variant) may give: key -> (config key it sets, type).
RUN_OPTIONS: dict[str, tuple[str | None, Any]] = {
    "frames": (None, str),
    "refine": ("graph.refine", RefineMode),
    "loops": ("loops", LoopMode),
    "map": ("map.enabled", bool),
    "mode": ("frontend.mode", FrontendMode),
    "map_all": ("map.per_trajectory", bool),
}
TOP_ONLY = ("sequences", "variants", "preset", "config", "cpus_per_task")
CONFIG_SECTIONS = ("frontend", "verification", "loop", "graph", "map")
READER_KEYS = ("left_topic", "right_topic", "calib")  # a sequence table's reader options, as `run` takes them
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+=,-]*$")


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (sequence, variant) run of a plan: everything its task needs."""

    sequence: str  # folder name under DIR
    variant: str  # folder name under DIR/<sequence>
    seq_path: str  # absolute
    gt: str | None  # absolute ground-truth file, None when the sequence has none
    frames: str | None
    cfg: Config
    config_hash: str
    reader: tuple[tuple[str, str], ...] = ()  # reader options: left_topic, right_topic, calib

    def open(self) -> StereoSource:
        """The dataset, read as ``run`` reads it."""
        return open_dataset(self.seq_path, frames=self.frames, gt=self.gt, **dict(self.reader))

    def folder(self, out_dir: str | Path) -> Path:
        return Path(out_dir) / self.sequence / self.variant


@dataclasses.dataclass
class Plan:
    source: str
    cells: list[Cell]
    cpus_per_task: float = 1.0


# ---------------------------------------------------------------- plan parsing
def load_plan(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Plan:
    """Read and check a plan file (its format: docs/usage.md, "batch"); a one-line error names it.
    ``overrides``: ``section.key=value`` items applied to every variant's config last."""
    path = Path(path)
    data = read_toml(path, "plan")
    return plan_from_dict(data, source=str(path), base_dir=path.parent, overrides=overrides)


def plan_from_dict(
    data: dict[str, Any], source: str = "plan", base_dir: str | Path = ".", overrides: list[str] | tuple[str, ...] = ()
) -> Plan:
    """Check a plan given as a dict (what a plan file holds) and expand it into cells.

    Experiments build plans this way in memory. ``base_dir``: where relative paths start;
    ``overrides`` (``--set`` items) beat the plan, as a command-line option beats a file."""
    base = Path(base_dir)
    allowed = (*TOP_ONLY, *RUN_OPTIONS)
    for key in data:
        if key not in allowed:
            hint = " (config overrides go under [variants.NAME])" if key in CONFIG_SECTIONS else ""
            raise SnapsGraphError(f"{source}: unknown key '{key}'{hint}; a plan has {', '.join(allowed)}")
    cpus = data.get("cpus_per_task", 1)
    if isinstance(cpus, bool) or not isinstance(cpus, (int, float)) or not (0 < cpus <= 1024) or not math.isfinite(cpus):
        raise SnapsGraphError(f"{source}: cpus_per_task must be a number in (0, 1024], got {cpus!r}")

    config = data.get("config")
    if config is not None and not isinstance(config, str):
        raise SnapsGraphError(f"{source}: config must be a path (string), got {config!r}")
    if not isinstance(data.get("preset", ""), str):
        raise SnapsGraphError(f"{source}: preset must be a name (string), got {data['preset']!r}")
    try:  # the named preset, the config file over it
        base_cfg = Config.compose(data.get("preset", "default"), _resolve(base, config) if config is not None else None)
    except SnapsGraphError as exc:
        raise SnapsGraphError(f"{source}: {'config' if config is not None else 'preset'}: {exc}") from None
    top = _run_options(data, source, "")

    variants = data.get("variants", {})
    if not isinstance(variants, dict):
        raise SnapsGraphError(f"{source}: variants must be tables [variants.NAME]")
    if not variants:
        variants = {"default": {}}
    resolved: dict[str, tuple[Config, str | None]] = {}
    for name, body in variants.items():
        where = f"variants.{name}"
        _check_name(name, source, where)
        if not isinstance(body, dict):
            raise SnapsGraphError(f"{source}: [{where}] must be a table")
        cfg, frames = _variant_config(base_cfg, top, body, source, where)
        resolved[name] = (cfg.with_overrides(overrides), frames)

    seqs = _sequences(data, source, base)
    cells: list[Cell] = []
    checked: dict[tuple[str, str | None], str | None] = {}  # (sequence, frames) -> its ground-truth file
    digests: dict[str, str] = {}
    for s_name, s_path, s_gt, reader in seqs:
        for v_name, (cfg, frames) in resolved.items():
            seq_key = (s_name, frames)
            if seq_key not in checked:
                checked[seq_key] = _check_sequence(s_name, s_path, s_gt, frames, reader, source)
            gt = checked[seq_key]
            extra = "".join(f";{k}={v}" for k, v in reader)
            if s_name not in digests:
                digests[s_name] = inputs_digest([s_path, gt, *(v for k, v in reader if k == "calib")])
            key = config_hash(cfg, s_path + extra, frames, gt, digests[s_name])
            cells.append(Cell(s_name, v_name, s_path, gt, frames, cfg, key, reader))
    return Plan(source, cells, float(cpus))


def _check_sequence(name: str, path: str, gt: str | None, frames: str | None, reader: tuple, source: str) -> str | None:
    """Open a sequence as its cells will (calibration, images, frame range, ground truth); returns
    its ground-truth file (absolute) or None."""
    try:
        seq = open_dataset(path, frames=frames, gt=gt, **dict(reader))
    except SnapsGraphError as exc:
        raise SnapsGraphError(f"{source}: sequence '{name}': {exc}") from None
    try:
        found = seq.gt_path or (gt if seq.gt_poses is not None else None)
        return str(Path(found).absolute()) if found is not None else None
    finally:
        seq.close()


def _resolve(base: Path, path: str) -> Path:
    p = Path(path).expanduser()
    return (p if p.is_absolute() else base / p).absolute()


def _check_name(name: Any, source: str, where: str) -> None:
    if not isinstance(name, str) or not _NAME.match(name):
        raise SnapsGraphError(
            f"{source}: {where}: name {name!r} must start with a letter or digit and hold only letters, digits and . _ + = , -"
        )


def _run_options(table: dict[str, Any], source: str, prefix: str) -> dict[str, Any]:
    """The run options of a plan table, each checked (``prefix``: "variants.NAME." or "")."""
    out: dict[str, Any] = {}
    for key, (_, typ) in RUN_OPTIONS.items():
        if key not in table:
            continue
        value, where = table[key], f"{source}: {prefix}{key}"
        if key == "map" and prefix and isinstance(value, dict):
            continue  # in a variant, map = { ... } is the [map] config section
        allowed = choices(typ)
        if allowed is not None:
            if not isinstance(value, str) or value not in allowed:
                raise SnapsGraphError(f"{where} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
        elif typ is bool:
            if not isinstance(value, bool):
                raise SnapsGraphError(f"{where}: expected true/false, got {value!r}")
        elif key == "frames":
            if not isinstance(value, str):
                raise SnapsGraphError(f'{where}: expected a frame range "A:B" (a string), got {value!r}')
            try:
                parse_frame_range(value)
            except SnapsGraphError as exc:
                raise SnapsGraphError(f"{where}: {exc}") from None
        out[key] = value
    return out


def _variant_config(
    base: Config, top: dict[str, Any], body: dict[str, Any], source: str, where: str
) -> tuple[Config, str | None]:
    """The checked configuration of one variant and its frame range.

    Precedence, lowest first: the plan's ``preset``, its ``config`` file, the plan's run options, the variant's
    config sections, the variant's run options (as on the command line, an option beats the
    config file)."""
    for key in body:
        if key not in (*CONFIG_SECTIONS, *RUN_OPTIONS):
            raise SnapsGraphError(
                f"{source}: {where}: unknown key '{key}'; a variant has the config sections "
                f"{', '.join(CONFIG_SECTIONS)} and the run options {', '.join(RUN_OPTIONS)}"
            )
    own = _run_options(body, source, f"{where}.")
    merged = base.to_dict()
    _apply_options(merged, top)
    sections: dict[str, Any] = {}
    for section in CONFIG_SECTIONS:
        if section in body and not (section == "map" and isinstance(body[section], bool)):  # map = true: the run option
            if not isinstance(body[section], dict):
                raise SnapsGraphError(f"{source}: {where}.{section} must be a table, e.g. {section} = {{ key = value }}")
            sections[section] = body[section]
    options: dict[str, Any] = {}
    _apply_options(options, own)
    src = f"{source}: {where}"  # a variant's keys are read as a config file's (an older key: moved, with a note)
    cfg = Config.from_dict(merged, source=src).merged(sections, src).merged(options, src)
    return cfg, own.get("frames", top.get("frames"))


def _apply_options(merged: dict[str, Any], options: dict[str, Any]) -> None:
    for key, value in options.items():
        target = RUN_OPTIONS[key][0]
        if target is None:
            continue
        section, _, field = target.rpartition(".")
        (merged.setdefault(section, {}) if section else merged)[field] = value


def _sequences(data: dict[str, Any], source: str, base: Path) -> list[tuple[str, str, str | None, tuple]]:
    """(name, absolute path, ground-truth file or None, reader options) per plan sequence; names unique."""
    seqs = data.get("sequences")
    if not isinstance(seqs, list) or not seqs:
        raise SnapsGraphError(f"{source}: sequences must be a non-empty list of sequence folders")
    out: list[tuple[str, str, str | None, tuple]] = []
    for i, entry in enumerate(seqs):
        where = f"sequences[{i}]"
        path: Any
        name: Any
        gt: Any = None
        reader: list[tuple[str, str]] = []
        if isinstance(entry, str):
            path, name = entry, None
        elif isinstance(entry, dict):
            unknown = set(entry) - {"path", "name", "gt", *READER_KEYS}
            if unknown:
                raise SnapsGraphError(
                    f"{source}: {where}: unknown key '{sorted(unknown)[0]}' (a sequence has path, name, gt, {', '.join(READER_KEYS)})"
                )
            path, name, gt = entry.get("path"), entry.get("name"), entry.get("gt")
            for key in ("path", "gt", *READER_KEYS):
                if entry.get(key) is not None and not isinstance(entry[key], str):
                    raise SnapsGraphError(f"{source}: {where}.{key}: expected a string, got {entry[key]!r}")
            if path is None:
                raise SnapsGraphError(f'{source}: {where}: a sequence table needs path = "..."')
            for key in READER_KEYS:
                if entry.get(key) is not None:
                    reader.append((key, str(_resolve(base, entry[key])) if key == "calib" else entry[key]))
        else:
            raise SnapsGraphError(f"{source}: {where}: expected a folder or a table {{ path = ..., name = ... }}, got {entry!r}")
        if path.startswith("live:"):
            raise SnapsGraphError(
                f"{source}: {where}: a live device cannot be a batch cell (it can be neither repeated nor resumed)"
            )
        full = _resolve(base, path)
        if name is None:  # the folder's name (a EuRoC mav0/ folder: its parent's; a bag file: its stem)
            name = full.parent.name if full.name == "mav0" else (full.stem if full.is_file() else full.name)
        _check_name(name, source, where)
        if any(name == o[0] for o in out):
            raise SnapsGraphError(
                f'{source}: {where}: two sequences are named \'{name}\' (their folder); give one a name: {{ path = "{path}", name = "..." }}'
            )
        out.append((name, str(full), str(_resolve(base, gt)) if gt is not None else None, tuple(reader)))
    return out


def config_hash(cfg: Config, seq_path: str, frames: str | None, gt: str | None, inputs: str = "") -> str:
    """What decides a run's output: the full configuration, the sequence, the frames, the ground
    truth, the inputs' content (``inputs_digest``) and the code (version and commit)."""
    text = json.dumps(
        {
            "config": cfg.dumps(),
            "sequence": seq_path,
            "frames": frames or "",
            "gt": gt or "",
            "inputs": inputs,
            "code": f"{__version__} {git_commit()}",
        },
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


DIGEST_CONTENT_BYTES = 16 * 2**20  # files up to this size are hashed whole (calibration, times, ground truth)


def inputs_digest(paths) -> str:
    """A digest of every file under ``paths`` (files or folders; None skipped): each file's
    relative name, size and modification time, and the content of the small ones. A changed
    calibration, ground truth, time or image gives another digest, so a resumed batch re-runs."""
    h = hashlib.sha256()
    for given in paths:
        if given is None:
            continue
        root = Path(given)
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for f in files:
            st = f.stat()
            h.update(f"{f.relative_to(root) if f != root else f.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
            if st.st_size <= DIGEST_CONTENT_BYTES and f.suffix.lower() not in (".png", ".jpg", ".jpeg", ".pgm"):
                h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """The commit of the package source this process runs ("" outside a git checkout), with
    ``-dirty`` when tracked files differ from it."""
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            # --match of no tag: always the commit hash, never a tag name
            ["git", "-C", str(here), "describe", "--always", "--dirty", "--abbrev=12", "--match=NO-TAGS"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""
