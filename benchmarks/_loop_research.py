"""Loop-closure instruments the package does not carry: verifying every compared candidate (for
precision-recall with verification), counting the window sums computed, choosing the loop rule's
flags one by one. Used by benchmarks/ and experiments/.

As a script, the command line with these switches:

    python benchmarks/_loop_research.py [--search radius] [--verify-all] run SEQ ...
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from snaps_graph.loop.policy import POLICIES, LoopPolicy
from snaps_graph.loop.snaps import Choice, SnapsLoopCloser
from snaps_graph.loop.uiqi import Thumbnails, WindowStats
from snaps_graph.pipeline import SlamPipeline

__all__ = ["CountingThumbnails", "SnapsLoopCloser", "VerifyAllCloser", "policy", "use_closer", "with_switches"]


class VerifyAllCloser(SnapsLoopCloser):
    """A loop closer that also verifies every compared candidate it did not try, for the record
    (candidates.csv's verify_tried/verify_passed); the loops are the ones the rule picked."""

    def _choose(self, n: int, ids: np.ndarray, order: np.ndarray, passing: list[int], tracking: bool, in_pause: bool) -> Choice:
        c = super()._choose(n, ids, order, passing, tracking, in_pause)
        if self.verifier is not None:
            for i in order.tolist():
                if i not in c.outcome:
                    c.outcome[i] = self.verifier.verify(int(self.traj.index[int(ids[i])]))
        return c


class CountingThumbnails(Thumbnails):
    """Thumbnails that count the window sums they compute (cache misses)."""

    computed = 0

    def stats(self, k: int) -> WindowStats:
        if self.cached(k) is None:
            self.computed += 1
        return super().stats(k)

    def cache_size(self) -> tuple[int, int]:
        """(thumbnails whose window sums are cached, their bytes)."""
        return len(self._stats), sum(s.nbytes for s in self._stats.values())


def policy(name: str = "drift", **flags) -> LoopPolicy:
    """A loop rule by name with some of its flags or constants changed (an experiment's variant)."""
    return dataclasses.replace(POLICIES[name], **flags)


def use_closer(pipe: SlamPipeline, cls: type[SnapsLoopCloser] = SnapsLoopCloser, rule: LoopPolicy | None = None) -> None:
    """Replace a new pipeline's loop closer by ``cls`` under ``rule`` (default: the config's),
    with the pipeline's own verifier. Call before the first frame."""
    assert pipe.snaps is not None and len(pipe.snaps) == 0, "a new pipeline running SNAPS"
    old = pipe.snaps
    pipe.snaps = cls(old.cfg, old.odometry, old.pause_every, verifier=old.verifier, policy=rule or old.policy)


def with_switches(search: str | None, verify_all: bool) -> type[SnapsLoopCloser]:
    """A loop closer class whose rule has ``search`` as its gate and that verifies every candidate."""
    base = VerifyAllCloser if verify_all else SnapsLoopCloser

    class Closer(base):  # type: ignore[valid-type, misc]
        def __init__(self, cfg, odometry=None, pause_every=1, policy=None, **kw):
            rule = policy or POLICIES[cfg.policy]
            rule = dataclasses.replace(rule, search=search) if search else rule
            super().__init__(cfg, odometry, pause_every, policy=rule, **kw)

    return Closer


def main(argv: list[str] | None = None) -> int:
    """``snaps-graph`` ARGS with the pipeline's loop closer under the research switches."""
    import snaps_graph.pipeline
    from snaps_graph.cli import main as cli

    ap = argparse.ArgumentParser(description="snaps-graph with research switches of the loop closer")
    ap.add_argument("--search", choices=["drift", "radius"], default=None, help="the candidate gate (default: the policy's)")
    ap.add_argument("--verify-all", action="store_true", help="verify every compared candidate, for the record")
    args, rest = ap.parse_known_args(argv)
    snaps_graph.pipeline.SnapsLoopCloser = with_switches(args.search, args.verify_all)  # type: ignore[misc]
    sys.argv = ["snaps-graph", *rest]
    cli()
    return 0


if __name__ == "__main__":
    sys.exit(main())
