"""Synthetic videos with real motion for the evaluation tests."""

from __future__ import annotations

import numpy as np


def panning_videos(seed, b=2, t=9, size=32):
    """``(b, t, size, size, 3)`` float32 in [0, 1]: blocky random frames panning 2 pixels a frame."""
    rng = np.random.default_rng(seed)
    coarse = rng.random((b, 1, size // 8, size // 8, 3)).astype(np.float32)
    frame = np.kron(coarse, np.ones((1, 1, 8, 8, 1), np.float32))
    return np.stack([np.roll(frame[:, 0], 2 * i, axis=2) for i in range(t)], axis=1)  # panning
