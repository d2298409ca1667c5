"""The part of the dataset protocol every reader shares: a selected range ``start:stop`` of its
frames, with their timestamps and ground truth (``_times_all``, ``_gt_all`` over all frames)."""

from __future__ import annotations

import numpy as np

from ..types import SequenceBase


class FrameSelection(SequenceBase):
    start: int
    stop: int
    _times_all: np.ndarray
    _gt_all: np.ndarray | None

    def __len__(self) -> int:
        return self.stop - self.start

    def _position(self, i: int) -> int:
        """The position among all frames of selected frame ``i`` (negative counts from the end);
        IndexError outside the selection."""
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        return self.start + i

    @property
    def indices(self) -> np.ndarray:
        """The selected frames' numbers (positions, unless a reader numbers its frames itself)."""
        return np.arange(self.start, self.stop)

    @property
    def timestamps(self) -> np.ndarray:
        return self._times_all[self.start : self.stop]

    @property
    def gt_poses(self) -> np.ndarray | None:
        """Ground truth for the selected frames, re-based so the first selected frame is identity."""
        if self._gt_all is None:
            return None
        gt = self._gt_all[self.start : self.stop]
        return np.linalg.inv(gt[0]) @ gt

    @property
    def gt_origin(self) -> np.ndarray | None:
        """The ground truth's own pose of the first selected frame (what ``gt_poses`` re-bases)."""
        return None if self._gt_all is None else np.array(self._gt_all[self.start])
