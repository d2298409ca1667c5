"""SNAPS loop closer: candidate rules, eq. 6 correction, persistence, spatial index.

Fake images are random textures (one per place, identical at a revisit); ``A // 2`` against ``A``
(even-valued A) has Q = (2·0.5/1.25)² = 0.64 exactly, which gives hand-checkable corrections.
Thumbnails are taken at scale 1 so the textures are compared as they are.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from snaps_graph.config import LoopConfig, OdometryConfig
from snaps_graph.errors import SnapsGraphError
from snaps_graph.geometry import inv, wrap_deg, yaw_deg
from snaps_graph.loop import SnapsLoopCloser
from snaps_graph.loop.policy import DRIFT, PAPER, LoopPolicy
from snaps_graph.loop.search import _NEIGHBOUR_OFFSETS

SHAPE = (16, 20)


def cfg(**kw) -> tuple[LoopConfig, LoopPolicy]:
    """The tests' [loop] keys and rule: the drift policy with the paper's gate, window, weight and
    pause (each test changes what it is about); ``kw`` may set either."""
    base: dict[str, Any] = dict(
        radius_m=5.5,
        frame_distance=3,
        discount_length=4,
        min_similarity=0.6,
        inter_frame_pause=2,
        thumbnail_scale=1.0,
        window=4,
        attempts=5,
        max_yaw_deg=10.0,
        correction_weight="q",  # eq. 6 exactly as the paper weighs it (verified weight: own test)
        discount_window="fixed",  # the paper's window K and gamma (span/shapes: test_loop_features)
        discount_shape="paper",
        search="radius",  # the paper's fixed radius (the drift gate: own tests)
        pause_graph_loops=False,  # the paper's pause (graph-only loops inside it: own tests)
    )
    base.update(kw)
    rule = {f.name for f in dataclasses.fields(LoopPolicy)}
    policy = dataclasses.replace(DRIFT, **{k: v for k, v in base.items() if k in rule})
    return LoopConfig(**{k: v for k, v in base.items() if k not in rule}), policy


def make(setup: tuple[LoopConfig, LoopPolicy], odometry: OdometryConfig | None = None, pause_every: int = 1) -> SnapsLoopCloser:
    return SnapsLoopCloser(setup[0], odometry, pause_every, policy=setup[1])


class Answers:
    """A verifier answering by a function of the reference's frame number (the tests' measurements)."""

    def __init__(self, fn: Callable[[int], "tuple[np.ndarray, int] | None"]):
        self.fn = fn

    def verify(self, reference: int) -> "tuple[np.ndarray, int] | None":
        return self.fn(reference)


def step_v(closer: SnapsLoopCloser, index: int, T_rel: np.ndarray, image: np.ndarray, verify) -> Any:
    """One step with ``verify`` answering this frame's verifications."""
    closer.verifier = Answers(verify)
    return closer.step(index, T_rel, image)


def tex(seed: int) -> np.ndarray:
    """A random texture with even pixel values (so tex // 2 is exact)."""
    return (2 * np.random.default_rng(1000 + seed).integers(1, 128, SHAPE)).astype(np.uint8)


def pose(z: float = 0.0, x: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """T_world_cam at (x, 0, z) with heading ``yaw`` degrees about the camera's y axis."""
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    T = np.eye(4)
    T[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    T[0, 3], T[2, 3] = x, z
    return T


def drive(closer: SnapsLoopCloser, poses: list[np.ndarray], images: list[np.ndarray], index0: int = 0, start: int = 0):
    """Feed frames start.. of a true path (frame 0 = identity) as VO increments; return the steps."""
    steps = []
    for k in range(start, len(poses)):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        steps.append(closer.step(index0 + k, T_rel, images[k]))
    return steps


def gamma(alpha: int, s_prime: float) -> float:
    """Eq. 6's discount with the paper's constants 3 and 0.01, clamped at 0."""
    return max(0.0, 1.0 - math.exp(-(3.0 - alpha * 0.01 * s_prime)))


# ---------------------------------------------------------------- eq. 6
def test_eq6_known_corrections_alpha_1_and_2_and_persistence():
    closer = make(cfg())
    poses = [pose(z=k) for k in range(9)]  # straight ahead, 1 m per frame
    images = [tex(k) for k in range(9)]
    images[5] = tex(0) // 2  # frame 5 revisits frame 0 with Q = 0.64
    images[8] = tex(3) // 2  # frame 8 revisits frame 3 with Q = 0.64
    steps = drive(closer, poses[:6], images[:6], index0=100)

    ev = steps[5].loop
    assert ev is not None and (ev.frame, ev.reference) == (105, 100)
    assert ev.q == pytest.approx(0.64, abs=1e-12) and ev.alpha == 1
    assert ev.distance_m == pytest.approx(5.0) and ev.n_corrected == 5
    np.testing.assert_allclose(ev.delta, [0, 0, -5.0], atol=1e-12)
    # s in [N-K, N] = [1, 5]; p_s.z = s + Q·γ(s')·δz. At s' = 0: 5 - 3.2·(1 - e^-3) = 1.959318618...
    z = closer.positions[:, 2]
    assert z[5] == pytest.approx(1.9593186187772, abs=1e-9)
    for s in range(1, 6):
        assert z[s] == pytest.approx(s - 0.64 * 5.0 * gamma(1, 5 - s), abs=1e-12)
    assert z[0] == 0.0  # outside the discount length
    np.testing.assert_allclose(steps[5].pose[:3, 3], [0, 0, z[5]], atol=1e-12)
    assert closer.last_pinned == 5

    # Frames 6, 7 compose onto the corrected pose; the pause (2) blocks any search on them.
    steps += drive(closer, poses[:8], images[:8], index0=100, start=6)
    assert steps[6].pose[2, 3] == pytest.approx(z[5] + 1.0) and steps[7].pose[2, 3] == pytest.approx(z[5] + 2.0)
    assert steps[6].candidates == 0 and steps[7].candidates == 0
    before = closer.positions
    p8 = before[7] + [0, 0, 1.0]

    # Frame 8: second loop (alpha = 2) against frame 3, found among candidates 5, 4, 0, 3 (nearest first).
    steps += drive(closer, poses, images, index0=100, start=8)
    ev2 = steps[8].loop
    assert ev2 is not None and (ev2.frame, ev2.reference, ev2.alpha) == (108, 103, 2)
    assert ev2.candidates == 4
    delta = before[3] - p8
    np.testing.assert_allclose(ev2.delta, delta, atol=1e-12)
    after = closer.positions
    for s in range(4, 9):
        prev = p8 if s == 8 else before[s]
        np.testing.assert_allclose(after[s], prev + 0.64 * gamma(2, 8 - s) * delta, atol=1e-12)
    np.testing.assert_array_equal(after[:4], before[:4])
    assert [e.frame for e in closer.loops] == [105, 108]


def test_gamma_clamped_at_zero_and_orientations_kept():
    # rate 1.0: γ(s') = 1 - e^-(3 - s') is 0 at s' = 3 and would be negative at s' = 4.
    closer = make(cfg(discount_rate=1.0))
    poses = [pose(z=k, yaw=1.0 * k) for k in range(6)]  # yaw 5° apart at the loop
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2
    steps = drive(closer, poses, images)
    ev = steps[5].loop
    assert ev is not None and ev.n_corrected == 3
    assert ev.yaw_diff_deg == pytest.approx(-5.0)
    moved = closer.positions
    true = np.array([p[:3, 3] for p in poses])
    np.testing.assert_allclose(moved[:3], true[:3], atol=1e-12)  # s' = 5 (outside K), 4 (clamped), 3 (γ = 0)
    np.testing.assert_allclose(moved[5], true[5] + 0.64 * (1 - math.exp(-3)) * ev.delta, atol=1e-12)
    R_true = np.array([p[:3, :3] for p in poses])
    np.testing.assert_allclose(closer.poses[:, :3, :3], R_true, atol=1e-12)


# ---------------------------------------------------------------- candidate rules
def far_path(last: np.ndarray, n_before: int = 5) -> list[np.ndarray]:
    """Frames 0..n_before-1 40 m apart along x, then ``last``."""
    return [pose(x=40.0 * k) for k in range(n_before)] + [last]


@pytest.mark.parametrize("z, found", [(5.4, True), (5.6, False)])
def test_radius(z, found):
    closer = make(cfg())
    images = [tex(k) for k in range(5)] + [tex(0)]
    steps = drive(closer, far_path(pose(z=z)), images)
    assert (steps[5].loop is not None) == found
    assert steps[5].candidates == (1 if found else 0)


@pytest.mark.parametrize("revisit, found", [(2, True), (3, False)])
def test_frame_distance(revisit, found):
    closer = make(cfg())
    poses = [pose(z=0.1 * k) for k in range(6)]  # all frames within the radius
    images = [tex(k) for k in range(5)] + [tex(revisit)]
    steps = drive(closer, poses, images)
    assert steps[5].candidates == 3  # frames 0, 1, 2 (N - j >= 3)
    assert (steps[5].loop is not None) == found
    if found:
        assert steps[5].loop.reference == 2


@pytest.mark.parametrize(
    "yaw_ref, yaw_cur, found",
    [(0.0, 9.9, True), (0.0, 10.1, False), (0.0, -10.1, False), (179.0, -179.0, True), (175.0, -174.0, False)],
)
def test_yaw_difference_with_wraparound(yaw_ref, yaw_cur, found):
    closer = make(cfg())
    # Frame 1 is the reference place (heading yaw_ref); frame 6 comes back to it heading yaw_cur.
    poses = [pose(), pose(x=100.0, yaw=yaw_ref)] + [pose(x=40.0 * k + 200) for k in range(4)]
    poses.append(pose(x=101.0, yaw=yaw_cur))
    images = [tex(k) for k in range(6)] + [tex(1)]
    steps = drive(closer, poses, images)
    assert (steps[6].loop is not None) == found
    assert steps[6].candidates == (1 if found else 0)
    if found:
        assert steps[6].loop.yaw_diff_deg == pytest.approx(wrap_deg(yaw_ref - yaw_cur))
        assert abs(yaw_deg(closer.poses[6]) - yaw_cur) < 1e-9


def test_inter_frame_pause():
    closer = make(cfg())
    # 0..4 20 m apart; 5 back at frame 0; 6, 7, 8 stand at frame 1's place and look like it.
    poses = [pose(z=20.0 * k) for k in range(5)] + [pose(z=1.0)] + [pose(z=21.0)] * 3
    images = [tex(k) for k in range(5)] + [tex(0)] + [tex(1)] * 3
    steps = drive(closer, poses, images)
    assert steps[5].loop is not None and steps[5].loop.reference == 0
    assert steps[6].candidates == 0 and steps[7].candidates == 0  # N - 5 <= 2: no search
    assert steps[7].loop is None
    assert steps[8].loop is not None and steps[8].loop.reference == 1  # 8 - 5 > 2
    assert closer.last_pinned == 8


@pytest.mark.parametrize("attempts, found", [(2, False), (3, True)])
def test_attempts_limit_nearest_first(attempts, found):
    closer = make(cfg(attempts=attempts))
    # Frame 5 at z = 3 looks like frame 0 (3 m away), the third nearest after frames 2 (1 m) and 1 (2 m).
    poses = [pose(z=0.0), pose(z=1.0), pose(z=2.0), pose(z=50.0), pose(z=60.0), pose(z=3.0)]
    images = [tex(k) for k in range(5)] + [tex(0)]
    steps = drive(closer, poses, images)
    assert steps[5].candidates == attempts
    assert (steps[5].loop is not None) == found
    if found:
        assert steps[5].loop.reference == 0 and steps[5].loop.distance_m == pytest.approx(3.0)
    else:  # nothing corrected: the full candidate list is still the one step() saw
        ids, d = closer.index.search(5)
        np.testing.assert_array_equal(ids, [2, 1, 0])
        np.testing.assert_allclose(d, [1.0, 2.0, 3.0])


def test_highest_q_wins_over_nearest():
    closer = make(cfg())
    A = tex(0)
    poses = [pose(z=0.0), pose(z=2.0), pose(z=50.0), pose(z=60.0), pose(z=70.0), pose(z=3.0)]
    images = [A, A // 2, tex(2), tex(3), tex(4), A]  # frame 1 (nearer): Q = 0.64; frame 0: Q = 1
    ev = drive(closer, poses, images)[5].loop
    assert ev is not None and ev.reference == 0 and ev.q == pytest.approx(1.0)
    assert ev.candidates == 2


def test_below_min_similarity_no_loop():
    closer = make(cfg(min_similarity=0.7))
    poses = far_path(pose(z=1.0))
    images = [tex(k) for k in range(5)] + [tex(0) // 2]  # Q = 0.64 < 0.7
    steps = drive(closer, poses, images)
    assert steps[5].loop is None and steps[5].candidates == 1
    np.testing.assert_allclose(steps[5].pose[:3, 3], [0, 0, 1.0], atol=1e-12)
    assert closer.loops == [] and closer.last_pinned is None


# ---------------------------------------------------------------- spatial index
def brute_force(closer: SnapsLoopCloser, n: int) -> np.ndarray:
    c = closer.cfg
    P, yaw = closer.positions, np.asarray(yaw_deg(closer.poses))
    j = np.arange(n + 1 - c.frame_distance)
    d = np.linalg.norm(P[j] - P[n], axis=1)
    ok = (d <= c.radius_m) & (np.abs(wrap_deg(yaw[j] - yaw[n])) <= closer.policy.max_yaw_deg)
    j, d = j[ok], d[ok]
    return j[np.lexsort((j, d))]


def test_spatial_index_tracks_corrected_positions():
    # A drifting loop driven 4 times: images keyed by the true 4 m cell, so revisits close loops,
    # and K > M so corrections move frames that are already in the grid.
    c, rule = cfg(radius_m=3.0, frame_distance=5, discount_length=40, inter_frame_pause=3, max_yaw_deg=30.0, min_similarity=0.9)
    closer = make((c, rule))
    rng = np.random.default_rng(9)
    n = 160
    theta = np.linspace(0, 8 * np.pi, n)  # 4 laps of a 12 m radius circle
    poses = [pose(x=12 * math.sin(t) + 0.02 * k, z=12 * (1 - math.cos(t)), yaw=math.degrees(t)) for k, t in enumerate(theta)]
    poses[0] = np.eye(4)
    textures: dict[tuple[int, int], np.ndarray] = {}
    moved_cells = 0
    key: tuple[int, int] | int
    for k in range(n):
        P = poses[k][:3, 3]
        key = (int(np.floor(P[0] / 4)), int(np.floor(P[2] / 4)))
        if key not in textures:
            textures[key] = tex(len(textures) + 50)
        img = np.clip(textures[key].astype(int) + rng.integers(-3, 4, SHAPE), 0, 255).astype(np.uint8)
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        T_rel[:3, 3] *= 1.03  # VO scale drift
        before = closer.positions
        step = closer.step(k, T_rel, img)
        if step.loop is not None:
            j = np.arange(max(0, k - c.discount_length), k - c.frame_distance + 1)
            after = closer.positions
            moved_cells += int(np.any(np.floor(before[j] / 3.0) != np.floor(after[j] / 3.0), axis=1).sum())
        np.testing.assert_array_equal(closer.index.search(k)[0], brute_force(closer, k))
        # The neighbourhood counts that short-cut empty searches agree with the grid itself.
        expect: dict[int, int] = {}
        for key in closer.index._grid:
            for off in _NEIGHBOUR_OFFSETS:
                expect[key + off] = expect.get(key + off, 0) + 1
        assert closer.index._near == expect
    assert len(closer.loops) >= 3
    assert moved_cells > 0  # the index really had to re-file frames


# ---------------------------------------------------------------- bad input
def test_bad_input_errors():
    closer = make(cfg())
    closer.step(0, np.eye(4), tex(0))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(SnapsGraphError, match="finite 4x4"):
        closer.step(1, bad, tex(1))
    with pytest.raises(SnapsGraphError, match="finite 4x4"):
        closer.step(1, np.eye(3), tex(1))
    with pytest.raises(SnapsGraphError, match="differs"):
        closer.check_image(1, (16, 22))
    assert len(closer) == 1 and np.all(np.isfinite(closer.poses))
    with pytest.raises(SnapsGraphError, match="radius_m"):
        LoopConfig(radius_m=0.0)
    with pytest.raises(SnapsGraphError, match="min_similarity"):
        LoopConfig(min_similarity=0.0)


def test_default_thumbnail_scale_on_full_size_frames():
    closer = SnapsLoopCloser(LoopConfig())
    img = np.random.default_rng(0).integers(0, 256, (376, 1241), dtype=np.uint8)
    s = closer.step(7, np.eye(4), img)
    assert closer.thumbnail(0).shape == (63, 207) and closer.thumbnail(0).dtype == np.uint8
    np.testing.assert_array_equal(s.pose, np.eye(4))
    assert closer.indices.tolist() == [7]


# ---------------------------------------------------------------- verified offset
@pytest.mark.parametrize("use_offset", [True, False])
def test_verified_offset_aims_at_measured_position(use_offset):
    """With a verifier, delta aims at p_ref + R_ref t_ref_cur (use_verified_offset) or p_ref."""
    closer = make(cfg(use_verified_offset=use_offset))
    poses = [pose(z=k) for k in range(6)]
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2  # frame 5 revisits frame 0 with Q = 0.64
    T_meas = pose(z=1.5, x=-0.5)  # the current frame stands 1.5 m ahead, 0.5 m left of frame 0
    asked = []

    def verify(ref_index):
        asked.append(ref_index)
        return T_meas, 42

    for k in range(6):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        step = step_v(closer, 10 + k, T_rel, images[k], verify)
    ev = step.loop
    assert ev is not None
    assert asked == [10]  # only the winning reference is verified, once
    assert ev.verified and ev.verify_inliers == 42
    assert ev.T_ref_cur is not None
    np.testing.assert_allclose(ev.T_ref_cur, T_meas)
    target = np.array([-0.5, 0.0, 1.5]) if use_offset else np.zeros(3)
    np.testing.assert_allclose(ev.delta, target - [0, 0, 5.0], atol=1e-12)
    np.testing.assert_allclose(closer.positions[5], [0, 0, 5.0] + 0.64 * gamma(1, 0) * ev.delta, atol=1e-12)


def test_verified_loop_moves_with_weight_one():
    """correction_weight = "verified": a verified loop moves N by gamma_0 * delta (weight 1)."""
    closer = make(cfg(correction_weight="verified"))
    poses = [pose(z=k) for k in range(6)]
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2
    T_meas = pose(z=1.0)
    for k in range(6):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        step = step_v(closer, k, T_rel, images[k], lambda ref: (T_meas, 30))
    ev = step.loop
    assert ev is not None
    assert ev.weight == 1.0 and ev.q == pytest.approx(0.64)
    np.testing.assert_allclose(closer.positions[5], [0, 0, 5.0 + gamma(1, 0) * (1.0 - 5.0)], atol=1e-12)
    np.testing.assert_allclose(closer.positions[4], [0, 0, 4.0 + gamma(1, 1) * (1.0 - 5.0)], atol=1e-12)


def test_failed_verification_rejects_or_falls_back():
    """require_verification: no loop when no candidate verifies; the paper's rule otherwise."""
    poses = [pose(z=k) for k in range(6)]
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2
    closer = make(cfg(require_verification=True))
    for k in range(6):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        step = step_v(closer, k, T_rel, images[k], lambda ref: None)
    assert (
        step.loop is None
        and any(r.above_threshold and r.verify_tried and not r.accepted for r in closer.candidate_records())
        and step.candidates > 0
    )
    np.testing.assert_allclose(closer.positions[5], [0, 0, 5.0])  # nothing moved


def test_next_candidate_verified_when_best_fails():
    """Frame 6 resembles frames 0 (Q 1) and 1 (Q 0.64); 0 fails verification, 1 passes."""
    poses = [pose(z=0.5 * k) for k in range(7)]
    images = [tex(k) for k in range(7)]
    images[1] = tex(0) // 2
    images[6] = tex(0).copy()
    closer = make(cfg(frame_distance=3, min_similarity=0.5, require_verification=True))
    tried = []

    def verify(ref):
        tried.append(ref)
        return (np.eye(4), 25) if ref == 1 else None

    for k in range(7):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        step = step_v(closer, k, T_rel, images[k], verify)
    assert tried == [0, 1]  # highest Q first
    assert step.loop is not None and step.loop.reference == 1 and step.loop.verified


def test_failed_verification_falls_back_to_same_place():
    closer = make(cfg(require_verification=False))
    poses = [pose(z=k) for k in range(6)]
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2
    for k in range(6):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        step = step_v(closer, k, T_rel, images[k], lambda ref: None)
    assert step.loop is not None and not step.loop.verified
    np.testing.assert_allclose(step.loop.delta, [0, 0, -5.0], atol=1e-12)


# ---------------------------------------------------------------- eq. 6: what it corrects
def _height_error_case(axes: str, rotation: str = "none"):
    """Reference frame 2 carries a VO height error of 0.5 m (step 1->2 climbs, 2->3 descends
    again); from step 2->3 on the VO is 0.2 m off sideways. Frame 6 revisits frame 2 and
    verification measures the true relative pose. Returns (errors before, errors after, closer)."""
    true = [pose(z=0.0), pose(z=1.0), pose(z=2.0), pose(x=20.0), pose(x=40.0), pose(x=20.0, z=20.0), pose(x=0.5, z=3.0)]
    est = [T.copy() for T in true]
    est[2][1, 3] += 0.5  # height error of the reference (KITTI y points down; the sign is irrelevant)
    for k in range(3, 7):
        est[k][0, 3] += 0.2  # horizontal error of everything after it
    images = [tex(k) for k in range(7)]
    images[6] = tex(2) // 2  # Q = 0.64 against frame 2 only
    T_meas = inv(true[2]) @ true[6]
    closer = make(cfg(discount_length=3, correction_weight="verified", correction_axes=axes, correction_rotation=rotation))
    for k in range(7):
        T_rel = np.eye(4) if k == 0 else inv(est[k - 1]) @ est[k]
        step = step_v(closer, k, T_rel, images[k], lambda ref: (T_meas, 50))
    assert step.loop is not None and step.loop.reference == 2 and step.loop.verified
    p_true = np.array([T[:3, 3] for T in true])
    before = np.linalg.norm(np.array([T[:3, 3] for T in est]) - p_true, axis=1)
    after = np.linalg.norm(closer.positions - p_true, axis=1)
    return before, after, closer


def test_eq6_ground_rule_never_copies_the_reference_height_error():
    before, after, _ = _height_error_case("ground")
    assert np.all(after <= before + 1e-12)  # no frame got worse
    assert after[6] < 0.05 * before[6]  # the current frame's sideways error is gone (0.2 m -> 0.01 m)
    # The paper's three components copy the reference's 0.5 m height error into frame 6 (why eq. 6
    # raised the height error on a real path): its error grows from 0.2 m to about 0.48 m.
    before_xyz, after_xyz, _ = _height_error_case("xyz")
    assert after_xyz[6] > 2.0 * before_xyz[6]


@pytest.mark.parametrize("sigma, gain", [(0.0, 1.0), (math.sqrt(5.0), 0.5)])
def test_eq6_rotation_correction_turns_window_to_verified_heading(sigma, gain):
    """The VO turned 3 deg too far in its first step, so frames 1..5 head 3 deg off. The verified
    rotation at the loop (frame 5 vs frame 0) bends the window [1, 5] back from its anchor
    (frame 0): frame s turns by g*w*3*s/5 deg, and a frame composed afterwards keeps the
    corrected heading. The gain g weighs the drift over the 5 frames (5 * 1 deg^2) against the
    measurement's variance sigma^2: 1 with an exact measurement, 0.5 when sigma^2 = 5 (the drift
    model's heading walk, 1 deg per sqrt(m), over the 5 m driven)."""
    true = [pose(z=float(k)) for k in range(6)]
    est = [true[0]] + [pose(z=float(k), yaw=3.0) for k in range(1, 6)]
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2
    T_meas = inv(true[0]) @ true[5]
    closer = make(
        cfg(
            correction_weight="verified",
            correction_axes="ground",
            correction_rotation="yaw",
            verified_heading_sigma_deg=sigma,
        ),
        OdometryConfig(heading_deg_per_sqrt_m=1.0),  # 1 deg^2 of heading variance per metre
    )
    for k in range(6):
        T_rel = np.eye(4) if k == 0 else inv(est[k - 1]) @ est[k]
        step = step_v(closer, k, T_rel, images[k], lambda ref: (T_meas, 50))
    assert step.loop is not None
    yaw = np.asarray(yaw_deg(closer.poses))
    for s in range(1, 6):
        assert yaw[s] == pytest.approx(3.0 * (1.0 - gain * s / 5.0), abs=1e-9)
    nxt = closer.step(6, pose(z=1.0), tex(6))  # one more metre straight ahead in the camera frame
    assert yaw_deg(nxt.pose) == pytest.approx(yaw[5], abs=1e-9)


def test_loop_policy_validated():
    with pytest.raises(SnapsGraphError, match="policy"):
        LoopConfig(policy="ours")  # type: ignore[arg-type]


def test_eq6_never_moves_the_reference_or_older_frames():
    """K (10) larger than N - ref (4): the window starts after the reference, the loop's anchor."""
    closer = make(cfg(discount_length=10))
    poses = [pose(z=float(k)) for k in range(7)]
    images = [tex(k) for k in range(7)]
    images[6] = tex(2) // 2  # frame 6 revisits frame 2
    steps = drive(closer, poses, images)
    assert steps[6].loop is not None and steps[6].loop.reference == 2 and steps[6].loop.n_corrected == 4
    np.testing.assert_array_equal(closer.positions[:3], [[0, 0, 0], [0, 0, 1.0], [0, 0, 2.0]])
    assert closer.positions[3, 2] != 3.0


# ---------------------------------------------------------------- bend, pause
def _circle_case():
    """A 36-frame circle (10 deg and 1 m per frame) that the VO turns 0.2 deg too far per frame;
    frame 36 revisits frame 0 and verification measures the exact relative pose. Returns the
    position errors (true vs corrected) of frames 0..36 and the closer."""
    r = 0.5 / math.sin(math.radians(5.0))  # chord of 1 m per 10 deg

    def on_circle(k: int, extra: float = 0.0) -> np.ndarray:
        a = math.radians(10.0 * k)
        T = pose(x=r * (1.0 - math.cos(a)), z=r * math.sin(a), yaw=10.0 * k + extra)
        return T

    true = [on_circle(k) for k in range(37)]
    images = [tex(k) for k in range(36)] + [tex(0) // 2]
    closer = make(
        cfg(
            radius_m=5.5,
            frame_distance=30,
            correction_weight="verified",
            correction_axes="ground",
            correction_rotation="yaw",
            verified_heading_sigma_deg=0.0,  # exact measurement: the full turn
            discount_window="span",
            discount_shape="drift",
        )
    )
    turn = pose(yaw=0.2)  # the VO's extra 0.2 deg per frame
    for k in range(37):
        T_rel = np.eye(4) if k == 0 else inv(true[k - 1]) @ true[k] @ turn
        step = step_v(closer, k, T_rel, images[k], lambda ref: (inv(true[ref]) @ true[36], 50))
    assert step.loop is not None and step.loop.reference == 0 and step.loop.verified
    err = np.linalg.norm(closer.positions - np.array([T[:3, 3] for T in true]), axis=1)
    return err, closer


def test_bend_undoes_a_constant_heading_drift():
    """A heading error growing evenly along the loop is what the bend models: turning the
    window's headings progressively and re-composing its positions puts every frame back on the
    circle (the ramp has nothing left to spread)."""
    err, closer = _circle_case()
    assert np.max(err) < 1e-6
    assert yaw_deg(closer.poses[36]) == pytest.approx(0.0, abs=1e-6)


def _pause_case(
    graph_loops: bool, second_z: float, verifies: bool = True, require_verification: bool = True, pause_every: int = 1
):
    """Frames 0..4 lie 20 m apart; frame 5 (z = 4) revisits frame 0 and verifies at 4 m, which
    starts the pause (10 frames); frame 6 (z = second_z) looks like frame 0 as well and verifies
    at its true distance (or, ``verifies`` False, does not verify)."""
    closer = make(
        cfg(
            inter_frame_pause=10,
            pause_graph_loops=graph_loops,
            correction_weight="verified",
            require_verification=require_verification,
        ),
        pause_every=pause_every,
    )
    poses = [pose(z=20.0 * k) for k in range(5)] + [pose(z=4.0), pose(z=second_z)]
    images = [tex(k) for k in range(5)] + [tex(0) // 2, tex(0) // 2]
    meas = {5: pose(z=4.0), 6: pose(z=second_z) if verifies else None}
    steps = []
    for k in range(7):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        steps.append(step_v(closer, k, T_rel, images[k], lambda ref, k=k: None if meas[k] is None else (meas[k], 50)))
    assert steps[5].loop is not None and steps[5].loop.reference == 0
    return steps, closer


def test_pause_graph_loops():
    steps, closer = _pause_case(False, 3.0)  # the paper's pause: no search at all
    assert steps[6].candidates == 0 and steps[6].loop is None
    p6 = closer.positions[6].copy()
    steps, closer = _pause_case(True, 3.0)  # searched, verified: a graph-only loop
    ev = steps[6].loop
    assert ev is not None and ev.reference == 0 and ev.verified and ev.weight == 0.0 and ev.n_corrected == 0
    assert closer.last_pinned == 5 and ev.alpha == 1  # not pinned, not counted by eq. 6
    np.testing.assert_array_equal(closer.positions[6], p6)  # the trajectory is the paper pause's
    steps, closer = _pause_case(True, 3.0, verifies=False)  # compared, not verified: no loop
    assert steps[6].candidates == 1 and steps[6].loop is None and closer.last_pinned == 5
    steps, _ = _pause_case(True, 3.0, pause_every=2)  # one frame into the pause: not its turn
    assert steps[6].candidates == 0 and steps[6].loop is None
    with pytest.raises(SnapsGraphError, match="pause_every"):
        make(cfg(), pause_every=0)
    # even where the paper's rule takes an unverified loop, the pause does not
    steps, closer = _pause_case(True, 3.0, verifies=False, require_verification=False)
    assert steps[6].candidates == 1 and steps[6].loop is None


def test_closer_loop_keeps_the_pause_of_the_loop_that_started_it():
    """A closer (graph-only) loop inside the pause does not restart it: frame 16 (11 frames after
    the loop at 5, pause 10) searches normally although frame 6 closed a closer loop."""
    closer = make(cfg(inter_frame_pause=10, pause_graph_loops=True, correction_weight="verified"))
    poses = [pose(z=20.0 * k) for k in range(5)] + [pose(z=4.0), pose(z=1.0)] + [pose(z=200.0 + 20 * k) for k in range(9)]
    poses.append(pose(z=20.5))  # frame 16 revisits frame 1
    images = [tex(k) for k in range(5)] + [tex(0) // 2, tex(0) // 2] + [tex(10 + k) for k in range(9)] + [tex(1) // 2]
    for k in range(17):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        meas = inv(poses[1 if k == 16 else 0]) @ poses[k]
        step = step_v(closer, k, T_rel, images[k], lambda ref, m=meas: (m, 50))
    assert step.loop is not None and step.loop.reference == 1 and closer.last_pinned == 16


def _track_case(pause: int, offset_m: float, **kw) -> tuple[list, SnapsLoopCloser]:
    """Frames 0..4 lie 20 m apart; frame 5 (z = 4) revisits frame 0 and verifies; frames 6, 7 and
    8 (z = 3, 2, 1) pass frame 0 again showing textures unlike it (Q near 0, below
    ``min_similarity``) and verify at their true poses, frame 8 ``offset_m`` off its true pose."""
    closer = make(cfg(inter_frame_pause=pause, pause_graph_loops=True, correction_weight="verified", **kw))
    poses = [pose(z=20.0 * k) for k in range(5)] + [pose(z=4.0), pose(z=3.0), pose(z=2.0), pose(z=1.0)]
    images = [tex(k) for k in range(5)] + [tex(0) // 2, tex(77), tex(78), tex(79)]
    meas = {k: poses[k] for k in range(5, 9)}
    meas[8] = pose(z=1.0 + offset_m)
    steps = []
    for k in range(9):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        steps.append(step_v(closer, k, T_rel, images[k], lambda ref, k=k: (meas[k], 50)))
    return steps, closer


@pytest.mark.parametrize("pause", [10, 2])
def test_a_verified_revisit_is_followed_on_verification_alone(pause):
    """Along a verified revisit, frames whose Q has fallen below ``min_similarity`` still give the
    graph loops where verification agrees with the loop that started the track, inside the pause
    (pause 10) and after it (pause 2: frame 8 searches normally, 2 frames after frame 6's loop);
    a verified pose 5 m off the track's prediction (an aliased match) gives none."""
    steps, closer = _track_case(pause, 0.0)
    assert steps[5].loop is not None and steps[5].loop.weight == 1.0
    for k in (6, 7, 8):
        ev = steps[k].loop
        assert ev is not None and ev.reference == 0 and ev.verified and ev.q < 0.6
        assert ev.weight == 0.0 and ev.n_corrected == 0  # the graph's, the heuristic is not moved
    assert closer.last_pinned == 5
    steps_off, closer_off = _track_case(pause, 5.0)
    assert steps_off[7].loop is not None and steps_off[8].loop is None
    np.testing.assert_array_equal(closer_off.positions, closer.positions)


def test_no_track_without_a_verified_loop():
    """Without a verified loop to follow, a candidate below ``min_similarity`` is not verified."""
    closer = make(cfg(inter_frame_pause=10, pause_graph_loops=True))
    poses = [pose(z=20.0 * k) for k in range(5)] + [pose(z=3.0)]
    images = [tex(k) for k in range(5)] + [tex(77)]
    calls: list[int] = []

    def verify(ref: int) -> tuple[np.ndarray, int]:
        calls.append(ref)
        return poses[5], 50

    for k in range(6):
        T_rel = np.eye(4) if k == 0 else inv(poses[k - 1]) @ poses[k]
        step = step_v(closer, k, T_rel, images[k], verify)
    assert step.candidates == 1 and step.loop is None and calls == []


# ---------------------------------------------------------------- drift-aware search
def drifted_revisit(offset_x: float, n_out: int = 300) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A drive n_out metres along z (1 m per frame), then, as estimated, back beside frame 100
    shifted ``offset_x`` metres across (a drift the true path does not have); the last frame
    shows the place of frame 100."""
    poses = [pose(z=float(k)) for k in range(n_out)] + [pose(z=100.0, x=offset_x)]
    images = [tex(k % 997) for k in range(n_out)] + [tex(100)]
    return poses, images


@pytest.mark.parametrize("search, found", [("radius", False), ("drift", True)])
def test_drift_gate_reaches_a_revisit_beyond_the_radius(search, found):
    from snaps_graph.config import OdometryConfig

    # 20 m off after ~1400 m driven: outside radius 5.5, inside 3 sigma of the default drift model.
    closer = make(cfg(search=search, search_max_radius_m=60.0, attempts=100), OdometryConfig())
    poses, images = drifted_revisit(20.0, n_out=800)
    steps = drive(closer, poses, images)
    assert (steps[-1].loop is not None) == found
    if found:
        assert steps[-1].loop.reference == 100


def test_drift_gate_never_below_radius_and_grows_with_distance():
    from snaps_graph.config import OdometryConfig

    closer = make(cfg(search="drift", search_max_radius_m=60.0), OdometryConfig())
    _, g = closer.index.gates(np.array([0.0, 10.0, 200.0, 500.0, 1000.0, 1e5]))
    assert g[0] == g[1] == 5.5  # the paper's radius below
    assert np.all(np.diff(g[2:5]) > 0) and g[-1] == 60.0
    # faster than linear: a heading walk's sideways error grows as D^1.5
    s = closer.index.drift_sigma(np.array([500.0, 1000.0]))
    assert s[1] > 2.0 * s[0]
    assert s[1] == pytest.approx(math.radians(0.07) * math.sqrt(1000.0**3 / 3), rel=0.01)


@pytest.mark.parametrize("last_loop", [None, (150, 20)])
def test_drift_gate_scalar_and_vector_paths_agree(last_loop):
    """The short-list path (plain Python) and the long-list path (numpy) apply the same gates:
    on a winding drive that passes its own start twice, both return the same candidates in the
    same order, with the same distances."""
    from snaps_graph.config import OdometryConfig

    closer = make(cfg(search="drift", search_max_radius_m=40.0), OdometryConfig(heading_deg_per_sqrt_m=0.2))
    rng = np.random.default_rng(7)
    poses, yaw, x, z = [], 0.0, 0.0, 0.0
    for _ in range(240):  # circles of ~60 m, heading noise, sideways jitter
        yaw += 6.0 + rng.normal(0.0, 2.0)
        x += math.sin(math.radians(yaw)) + rng.normal(0.0, 0.3)
        z += math.cos(math.radians(yaw))
        poses.append(pose(z=z, x=x, yaw=yaw))
    drive(closer, poses, [tex(k) for k in range(len(poses))])
    closer.index.last_loop = last_loop
    compared = 0
    for n in range(60, 240, 7):
        found = list(range(n))
        small = closer.index._search_drift_small(n, found)
        vector = closer.index._search_drift_vector(n, found)
        np.testing.assert_array_equal(small[0], vector[0])
        np.testing.assert_allclose(small[1], vector[1], rtol=0, atol=1e-12)
        compared += len(small[0])
    assert compared > 50  # the drive does revisit: the gates had candidates to agree on


def test_verified_loop_restarts_the_uncertainty():
    from snaps_graph.config import OdometryConfig

    closer = make(cfg(search="drift"), OdometryConfig())
    poses, images = drifted_revisit(0.0, n_out=300)
    drive(closer, poses[:300], images[:300])
    ids = np.array([50])
    before = float(closer.index.driven_since(299, ids)[0])
    closer.index.last_loop = (299, 40)  # as if frame 299 had been verified against frame 40
    after = float(closer.index.driven_since(299, ids)[0])
    assert before == pytest.approx(249.0) and after == pytest.approx(10.0)


def test_wide_gate_samples_across_it_within_attempts():
    closer = make(cfg(search="drift", attempts=5))
    seen: set[int] = set()
    for _ in range(30):
        pick = closer.index.pick(60)
        assert len(pick) <= 5 and pick[0] == 0 and len(set(pick.tolist())) == len(pick)
        seen |= set(pick.tolist())
    assert seen == set(range(60))  # every candidate of a wide gate is compared within a few frames
    assert closer.index.pick(4).tolist() == [0, 1, 2, 3]


def test_correction_ramp_follows_the_distance_driven():
    """Drift grows with distance: frames standing still share one correction, and a jump in the
    frame numbers (frames left out, driven at the speed before it) carries its share of it."""
    # A drift model of translation noise alone: each frame's share is its share of the distance.
    walk = OdometryConfig(
        heading_deg_per_sqrt_m=1e-9, pitch_deg_per_sqrt_m=0, roll_deg_per_sqrt_m=0, scale_pct=0, trans_m_per_sqrt_m=0.1
    )
    closer = make(cfg(discount_window="span", discount_shape="drift", correction_rotation="none"), walk)
    zs = [0, 1, 2, 3, 3, 3, 3, 4, 5, 6]  # a stop at z = 3 (frames 3-6)
    index = list(range(10)) + [30]  # frame 30 after 20 frames left out, 20 m later
    zs.append(26)
    for k, (i, z) in enumerate(zip(index, zs)):
        T_rel = np.eye(4) if k == 0 else pose(z=float(z - zs[k - 1]))
        closer.step(i, T_rel, tex(k))
    before = closer.positions
    closer._correct(10, 0, 1.0, np.array([1.0, 0.0, 0.0]), 1, None)
    moved = (closer.positions - before)[:, 0]
    share = (1.0 - math.exp(-3.0)) * np.array([0, 1, 2, 3, 3, 3, 3, 4, 5, 6, 26], float) / 26.0
    np.testing.assert_allclose(moved, share, atol=1e-12)


def test_correction_spares_the_frames_a_heading_walk_did_not_drift():
    """Under a heading walk (the default model's main term) the first frames after the anchor hold a
    small share of the loop's offset: (3x^2 - x^3) / 2 of the distance share x, not x."""
    heading = OdometryConfig(pitch_deg_per_sqrt_m=0, roll_deg_per_sqrt_m=0, scale_pct=0, trans_m_per_sqrt_m=1e-9)
    closer = make(cfg(discount_window="span", discount_shape="drift", correction_rotation="none"), heading)
    for k in range(21):
        closer.step(k, np.eye(4) if k == 0 else pose(z=1.0), tex(k))
    before = closer.positions
    closer._correct(20, 0, 1.0, np.array([1.0, 0.0, 0.0]), 1, None)
    moved = (closer.positions - before)[:, 0]
    x = np.arange(21) / 20.0
    assert moved[0] == 0.0 and moved[20] == pytest.approx(1.0 - math.exp(-3.0))
    assert np.all(moved[1:10] < 0.6 * (1.0 - math.exp(-3.0)) * x[1:10])  # well under the linear ramp
    assert moved[2] == pytest.approx((1.0 - math.exp(-3.0)) * (3 * x[2] ** 2 - x[2] ** 3) / 2, rel=0.05)


# ---------------------------------------------------------------- the two rules
def test_paper_policy_is_every_paper_flag_and_drift_the_former_defaults():
    """``loop.policy`` names the rule: "paper" is the value each former flag's doc called the
    paper's, "drift" the former defaults."""
    paper = dict(
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
    drift = dict(
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
    assert {k: getattr(PAPER, k) for k in paper} == paper
    assert {k: getattr(DRIFT, k) for k in drift} == drift
    assert SnapsLoopCloser(LoopConfig(policy="paper")).policy is PAPER
    assert SnapsLoopCloser(LoopConfig()).policy is DRIFT


@pytest.mark.parametrize("policy", ["paper", "drift"])
def test_paper_policy_takes_an_unverified_loop_on_all_axes(policy):
    """Frame 5 revisits frame 0 one metre higher (Q = 0.64) and fails verification. The paper's
    rule takes it anyway and eq. 6 moves all three axes by Q·γ(s')·δ over [N - K, N]; ours
    refuses it."""
    c = LoopConfig(
        policy=policy,
        radius_m=5.5,
        frame_distance=3,
        discount_length=4,
        min_similarity=0.6,
        inter_frame_pause=2,
        thumbnail_scale=1.0,
        window=4,
    )
    closer = SnapsLoopCloser(c, verifier=Answers(lambda ref: None))
    poses = [pose(z=k) for k in range(6)]
    poses[5][1, 3] = 1.0
    images = [tex(k) for k in range(6)]
    images[5] = tex(0) // 2
    ev = drive(closer, poses, images)[5].loop
    if policy == "drift":
        assert ev is None
        return
    assert ev is not None and not ev.verified and ev.weight == ev.q == pytest.approx(0.64, abs=1e-12)
    np.testing.assert_allclose(ev.delta, [0.0, -1.0, -5.0], atol=1e-12)
    P = closer.positions
    for s in range(1, 6):
        g = 0.64 * gamma(1, 5 - s)
        np.testing.assert_allclose(P[s], [0.0, (1.0 if s == 5 else 0.0) - g, s - 5.0 * g], atol=1e-12)
    np.testing.assert_array_equal(P[0], [0.0, 0.0, 0.0])
