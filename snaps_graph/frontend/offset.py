"""The running estimate of a rig's disparity offset (measured - true, px, at the centre column):
the local-BA solves' information-weighted mean, applied once it is well determined and differs
from the configured one (the rule: docs/frontend.md)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OffsetRule:
    """When the running estimate replaces the configured offset: only once it is well determined
    (a drive with little depth change leaves it unobservable) and clearly differs (an offset-free
    rig's early noise stays out)."""

    prior_px: float = 0.5  # prior sigma of the offset in each local-BA solve: a rig's residual is a fraction of a pixel
    max_px: float = 2.0  # the estimate is clamped to +- this
    min_solves: int = 3  # solves before an estimate may be applied
    min_px: float = 0.05  # applied when it differs from the configured offset by at least this
    max_sd_px: float = 0.05  # ...and its standard error is at most this
    min_z: float = 4.0  # ...and it differs by at least this many standard errors
    memory_solves: int = 20  # once applied, older solves fade with weight 1 - 1/this (0 = never): a worse offset was in place


OFFSET_RULE = OffsetRule()


class DisparityOffsetEstimator:
    """``add`` the solves' (offset px, information 1/px^2); ``offset`` is the offset to apply,
    starting at the configured ``px``."""

    def __init__(self, px: float, cfg: OffsetRule | None = None):
        self.cfg = cfg if cfg is not None else OFFSET_RULE
        self.px = float(px)
        self.offset = float(px)
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
            if self.applied or abs(est - self.px) >= need:
                self.offset = est
                self.applied = True
        return self.applied
