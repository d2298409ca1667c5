"""Data passed between stages (images -> front end -> SNAPS -> graph -> map/evaluation).

Plain dataclasses with numpy fields (and the Protocols of the front end and of a stereo
source); no stage imports another stage's internals, only these.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from .camera import StereoCamera


@dataclass
class StereoFrame:
    """One rectified stereo pair, as every dataset yields it and the pipeline consumes it."""

    index: int  # the dataset's frame number (the image file's number)
    timestamp: float  # seconds
    left: np.ndarray  # uint8 grey, H x W
    right: np.ndarray  # uint8 grey, H x W


class StereoSource(Protocol):
    """What a run reads from: every reader of ``datasets.open.open_dataset`` and the renderer.

    The first six members are each reader's own; the rest have defaults in ``SequenceBase``,
    which every reader subclasses, so callers read them without probing."""

    camera: StereoCamera

    @property
    def indices(self) -> np.ndarray:
        """The dataset frame number of each frame, in stream order."""
        ...

    @property
    def timestamps(self) -> np.ndarray:
        """Seconds from the first frame, one per frame."""
        ...

    @property
    def gt_poses(self) -> np.ndarray | None:
        """Ground truth of the frames (4x4 each, the first re-based to the identity), or None."""
        ...

    @property
    def gt_origin(self) -> np.ndarray | None:
        """The ground truth's own pose of the first frame (what ``gt_poses`` re-bases), or None."""
        ...

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[StereoFrame]: ...

    @property
    def gt_path(self) -> Path | None: ...

    @property
    def stereo(self) -> bool: ...

    @property
    def t0_ns(self) -> int | None: ...

    @property
    def notes(self) -> Sequence[str]: ...

    @property
    def source_info(self) -> Mapping[str, str]: ...

    def frame_source(self, number: int) -> str | None: ...

    def close(self) -> None: ...


class SequenceBase:
    """The optional members of ``StereoSource`` with their defaults (a reader overrides what it knows)."""

    gt_path: Path | None = None  # the ground-truth file read (an input a run must never write)
    stereo: bool = True  # False: left images only (the VO needs odometry from elsewhere)
    t0_ns: int | None = None  # absolute time of timestamp 0 (pose files with absolute stamps)
    notes: Sequence[str] = ()  # what the reader dropped or assumed, one line each
    # What names the input beyond its path, for metrics.json (a bag's image topics); the
    # readers' own details stay on their classes.
    source_info: Mapping[str, str] = MappingProxyType({})

    def frame_source(self, number: int) -> str | None:
        """The file frame ``number`` was read from (for error messages); None when unknown."""
        return None

    def close(self) -> None:
        """Release what the reader holds open (bag files, devices)."""


@dataclass
class FrameFeatures:
    """A compact description of one frame, kept per frame for loop verification.

    ``uv`` are pixel positions in the left image, ``pts3d`` the matching 3D points in that
    frame's camera frame (metres, KITTI axes), ``desc`` their descriptors (uint8 rows for binary
    descriptors, float32 rows for SIFT). All three have the same length.
    """

    uv: np.ndarray  # (N, 2) float32
    pts3d: np.ndarray  # (N, 3) float32
    desc: np.ndarray  # (N, D) uint8 or float32


@dataclass
class VOResult:
    """What the front end returns for one frame."""

    index: int
    T_rel: np.ndarray  # 4x4, T_prev_cur: pose of this frame in the previous frame's camera frame
    pose: np.ndarray  # 4x4, T_world_cam of the pure VO chain (frame 0 = identity)
    ok: bool  # False: flagged frame, T_rel is the constant-velocity guess
    reason: str = ""  # why the frame was flagged ("" when ok)
    inliers: int = 0  # PnP inliers (0 when flagged)
    matches: int = 0
    features: FrameFeatures | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)  # per stage
    disparity_offset_px: float = 0.0  # disparity offset (measured - true, px) this frame was measured with
    # 6x6 covariance of T_rel from the stereo BA (rotation rad, translation m: GTSAM's Pose3
    # tangent at T_rel); None when not estimated (flagged, PnP only, not measured from the previous frame)
    cov: np.ndarray | None = None
    # The drift model's covariance of this step along the path it drove, from a front end that
    # knows the path (a pose file's step across frames left out); None: the graph takes the chord.
    drift_cov: np.ndarray | None = None


class FrontEnd(Protocol):
    """What the pipeline needs of a front end: ``StereoOdometry``, or any substitute (the paper:
    "it is possible to substitute the visual odometry part with any desired model")."""

    @property
    def disparity_offset_px(self) -> float:
        """The disparity offset (measured - true, px) the front end applies now; 0 without one."""
        ...

    def process(self, frame: StereoFrame) -> VOResult: ...

    def close(self) -> None: ...


@dataclass
class LoopEvent:
    """A loop closed by SNAPS at frame ``frame`` against earlier frame ``reference``."""

    frame: int
    reference: int
    distance_m: float  # |p_ref - p_N| before the correction (heuristic positions)
    yaw_diff_deg: float
    q: float  # UIQI (eq. 4)
    correlation: float
    luminance: float
    contrast: float
    delta: np.ndarray  # (3,) p_ref - p_N
    n_corrected: int  # poses moved by eq. 6
    alpha: int  # loops closed so far, this one included
    candidates: int  # similarities computed on this frame
    t_ms: float  # detection + correction time
    # Geometric verification (PnP from the reference's 3D points to this frame's keypoints):
    verified: bool = False  # measurement from geometric verification (else same-place assumption)
    verify_inliers: int = 0
    T_ref_cur: np.ndarray | None = None  # measured relative pose when verified
    t_verify_ms: float = 0.0  # geometric verification time (not part of t_ms)
    shift_px: int = 0  # horizontal thumbnail shift at which Q was highest
    weight: float = 0.0  # the weight eq. 6 applied (Q, or 1 for a verified loop)
    # A loop to a prior session: its name (the folder it came from; "" for this run's own frames),
    # its index among the run's priors, and whether this loop relocalised the run against it.
    session: str = ""
    prior: int = -1
    relocalised: bool = False

    def to_json(self) -> dict:
        d = {
            "frame": self.frame,
            "reference": self.reference,
            "distance_m": self.distance_m,
            "yaw_diff_deg": self.yaw_diff_deg,
            "q": self.q,
            "correlation": self.correlation,
            "luminance": self.luminance,
            "contrast": self.contrast,
            "delta": [float(v) for v in self.delta],
            "n_corrected": self.n_corrected,
            "alpha": self.alpha,
            "candidates": self.candidates,
            "t_ms": self.t_ms,
            "verified": self.verified,
            "verify_inliers": self.verify_inliers,
            "t_verify_ms": self.t_verify_ms,
            "shift_px": self.shift_px,
            "weight": self.weight,
        }
        if self.T_ref_cur is not None:
            d["T_ref_cur"] = [float(v) for v in np.asarray(self.T_ref_cur)[:3, :4].reshape(-1)]
        if self.session:  # a loop to a prior session: its reference is that session's frame
            d["session"], d["relocalised"] = self.session, self.relocalised
        return d


@dataclass
class FrameRecord:
    """One processed frame: what ``frames.csv`` holds, one row per frame, columns in field order."""

    frame: int  # the dataset's frame number
    timestamp: float  # seconds
    t_total_ms: float
    t_vo_ms: float
    vo_ok: int  # 1, or 0 for a flagged frame
    vo_inliers: int
    vo_reason: str  # why the frame was flagged ("" when ok)
    t_loop_ms: float
    loop_candidates: int
    loop_closed: int
    t_verify_ms: float
    t_graph_ms: float
    graph_ok: int
    t_map_ms: float
    vo_disparity_offset_px: float = 0.0  # VOResult.disparity_offset_px (the running estimate, if on)


FRAME_COLUMNS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(FrameRecord))


@dataclass(frozen=True)
class CandidateRecord:
    """One similarity SNAPS computed: a row of ``candidates.csv`` (columns in field order; the
    writer and reader are in evaluation/results_io.py)."""

    frame: int  # dataset frame index of the current frame
    reference: int  # ... of the earlier candidate
    distance_m: float  # |p_ref - p_N| on the heuristic trajectory when compared
    yaw_diff_deg: float  # wrap(yaw_ref - yaw_N), heuristic orientations
    q: float  # the Q SNAPS compared with min_similarity (at the best shift)
    correlation: float  # Q's factors at that shift (window means)
    luminance: float
    contrast: float
    shift_px: int  # horizontal thumbnail shift of the best Q (0 without shift search)
    above_threshold: bool  # Q >= min_similarity
    verify_tried: bool  # geometric verification was run on this pair
    verify_passed: bool  # ... and returned a relative pose
    inliers: int  # PnP inliers of a passed verification (0 otherwise)
    accepted: bool  # this pair closed the loop at this frame


CANDIDATE_COLUMNS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(CandidateRecord))
