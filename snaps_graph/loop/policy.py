"""The two loop-closure rules by name: ``"drift"`` (ours, the default) and ``"paper"`` (SNAPS as
printed). ``loop.policy`` picks one; the choices and their measurements: docs/loop-closure.md and
docs/decisions.md, "Loop closure (SNAPS)".

A policy holds what differs between the rules and the constants of each rule; the user's keys
(radius, M, K, the Q threshold, the pause, the thumbnail) stay in ``[loop]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class LoopPolicy:
    """One loop-closure rule. Each flag's first value is the paper's, the other ours."""

    name: str
    # Candidate gate: the paper's fixed radius_m, or search_sigmas of the drift model's position
    # error since the candidate (never under radius_m, at most search_max_radius_m).
    search: Literal["radius", "drift"]
    # Eq. 6's window: fixed = discount_length frames (the paper), span = span_factor x (N - j).
    discount_window: Literal["fixed", "span"]
    # Gamma over the window: eq. 6's exponential (paper), or each frame's expected share of the
    # drift under the [odometry] drift model.
    discount_shape: Literal["paper", "drift"]
    # Weight of eq. 6's move: Q (the paper), or 1 for a verified loop (it measured where N stands).
    correction_weight: Literal["q", "verified"]
    # What eq. 6 moves: all three axes (the paper), or the ground plane (the reference's height
    # error stays out).
    correction_axes: Literal["xyz", "ground"]
    # A verified loop also turns the window's heading toward the verified one (yaw) or not.
    correction_rotation: Literal["none", "yaw"]
    # Eq. 6 aims at the reference's position (the paper's same place) or where verification puts N.
    use_verified_offset: bool
    # A loop must pass geometric verification (ours) or the best Q is taken unverified (the paper).
    require_verification: bool
    # In the pause and along a verified revisit, verified loops still go to the factor graph
    # without correcting (ours); the paper's pause compares nothing.
    pause_graph_loops: bool

    # Constants of the rules (not user keys; the docs name where each was measured).
    attempts: int = 5  # Table I: at most this many candidates compared per frame, nearest first
    max_yaw_deg: float = 10.0  # Table I: candidate heading limit |yaw_j - yaw_N|
    discount_offset: float = 3.0  # the 3 in eq. 6's gamma = 1 - exp(-(3 - alpha*0.01*s'))
    discount_rate: float = 0.01  # the 0.01 in the same formula
    search_sigmas: float = 3.0  # drift gate width in standard deviations: 3 keeps 99 % of true revisits
    search_max_radius_m: float = 40.0  # the drift gate's cap: wider gates only met aliased places
    verify_attempts: int = 3  # candidates at or above min_similarity verified, best Q first (more found none)
    verified_heading_sigma_deg: float = 0.1  # sigma of a verified heading in the turn's gain (PnP's, measured)
    span_factor: float = 1.0  # the span window is this x (N - j) frames: the whole loop drifted
    span_max: int = 1000  # the longest span window, frames: bounds eq. 6's cost per loop


DRIFT = LoopPolicy(
    name="drift",
    search="drift",
    discount_window="span",
    discount_shape="drift",
    correction_weight="verified",
    correction_axes="ground",
    correction_rotation="yaw",
    use_verified_offset=True,
    require_verification=True,
    pause_graph_loops=True,
)

PAPER = LoopPolicy(
    name="paper",
    search="radius",
    discount_window="fixed",
    discount_shape="paper",
    correction_weight="q",
    correction_axes="xyz",
    correction_rotation="none",
    use_verified_offset=False,
    require_verification=False,
    pause_graph_loops=False,
)

POLICIES: dict[str, LoopPolicy] = {p.name: p for p in (DRIFT, PAPER)}
