"""The heuristic trajectory SNAPS corrects: per stream position the orientation, position, heading,
dataset frame number and distance driven, in arrays grown in place (the candidate index and eq. 6
read and write them by slice)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import SnapsGraphError
from ..geometry import yaw_deg

# A frame-number gap is driven at this running mean of the speed (metres per frame number): the
# new step's share of it (one frame's speed is noisy, a slow mean lags behind braking).
SPEED_GAIN = 0.1


class Trajectory:
    """Stream positions 0 .. len-1: ``R`` (3x3), ``p`` (m), ``yaw`` (deg), ``index`` (the
    dataset's frame number) and ``s`` (distance driven up to the frame, m). The arrays are
    replaced when they grow: read them through the attributes, never keep them."""

    def __init__(self, capacity: int = 1024):
        self.R = np.empty((capacity, 3, 3))
        self.p = np.empty((capacity, 3))
        self.yaw = np.empty(capacity)
        self.index = np.empty(capacity, dtype=np.int64)
        self.s = np.empty(capacity)
        self.n = 0
        self._speed = 0.0  # metres per frame number, running mean

    def __len__(self) -> int:
        return self.n

    @property
    def capacity(self) -> int:
        return len(self.p)

    def append(self, index: int, T_rel: np.ndarray) -> int:
        """Compose the VO step ``T_rel`` (T_prev_cur; ignored for the first frame, the identity)
        onto the last pose; returns the new stream position."""
        n = self.n
        if n == 0:
            R, p, s = np.eye(3), np.zeros(3), 0.0
        else:
            T = np.asarray(T_rel, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise SnapsGraphError(f"SNAPS: frame {index}: T_rel must be a finite 4x4 transform")
            R_prev = self.R[n - 1]
            R = R_prev @ T[:3, :3]
            p = self.p[n - 1] + R_prev @ T[:3, 3]
            s = self.s[n - 1] + self._driven(index, math.sqrt(float(T[0, 3] ** 2 + T[1, 3] ** 2 + T[2, 3] ** 2)))
        self._grow(n + 1)
        self.R[n], self.p[n], self.s[n] = R, p, s
        self.yaw[n] = yaw_deg(R)
        self.index[n] = index
        self.n = n + 1
        return n

    def _driven(self, index: int, step_m: float) -> float:
        """Distance driven by a step: a jump in the frame numbers (frames left out) is driven at the
        speed of the frames before it, never less than the straight line across it."""
        n = self.n
        gap = max(1, int(index) - int(self.index[n - 1]))
        if gap == 1:
            self._speed += SPEED_GAIN * (step_m - self._speed) if n > 1 else step_m - self._speed
        return step_m if gap == 1 else max(step_m, gap * self._speed)

    def pose(self, k: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R[k]
        T[:3, 3] = self.p[k]
        return T

    def poses(self) -> np.ndarray:
        """(N, 4, 4) T_world_cam (a copy)."""
        n = self.n
        out = np.zeros((n, 4, 4))
        out[:, :3, :3] = self.R[:n]
        out[:, :3, 3] = self.p[:n]
        out[:, 3, 3] = 1.0
        return out

    def _grow(self, need: int) -> None:
        cap = self.capacity
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name in ("R", "p", "yaw", "index", "s"):
            old = getattr(self, name)
            arr = np.empty((new_cap,) + old.shape[1:], dtype=old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)
