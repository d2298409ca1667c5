"""The running estimate of a rig's disparity offset (measured - true, px, at the centre column):
the local-BA solves' information-weighted mean, applied once it is well determined and differs
from the configured one (the rule: docs/frontend.md)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..config import OffsetConfig


class DisparityOffsetEstimator:
    """``add`` the solves' (offset px, information 1/px^2); ``offset`` is the offset to apply."""

    def __init__(self, cfg: OffsetConfig):
        self.cfg = cfg
        self.offset = float(cfg.px)
        self.applied = False  # the estimate replaced the configured offset
        self._acc = [0.0, 0.0, 0]  # sum of info * offset, sum of info, solves

    def add(self, solves: Iterable[tuple[float, float]]) -> bool:
        """Fold new solves into the estimate; True once it is applied (``offset`` is then it)."""
        cfg, acc = self.cfg, self._acc
        mem = cfg.memory_solves
        for off, info in solves:
            if np.isfinite(off) and np.isfinite(info) and info > 0:
                if self.applied and mem > 0:
                    acc[0] *= 1.0 - 1.0 / mem
                    acc[1] *= 1.0 - 1.0 / mem
                acc[0] += info * off
                acc[1] += info
                acc[2] += 1
        observed = acc[1] > 0 and acc[1] ** -0.5 <= cfg.max_sd_px
        if acc[2] >= cfg.min_solves and observed:
            lim = cfg.max_px
            est = float(np.clip(acc[0] / acc[1], -lim, lim))
            need = max(cfg.min_px, cfg.min_z * acc[1] ** -0.5)
            if self.applied or abs(est - cfg.px) >= need:
                self.offset = est
                self.applied = True
        return self.applied
