"""Windowing of sensor streams: 128 samples shifted by 16 (Zimmermann et al. 2018 §2.1, docs/conventions.md)."""

from __future__ import annotations

import numpy as np

WINDOW_SAMPLES = 128
HOP_SAMPLES = 16
MODEL_RATE_HZ = 60.0


def window_starts(n_samples: int, window: int = WINDOW_SAMPLES, hop: int = HOP_SAMPLES) -> np.ndarray:
    """Start indices of all complete windows in a stream of ``n_samples``."""
    if n_samples < window:
        return np.zeros(0, dtype=np.int64)
    return np.arange(0, n_samples - window + 1, hop, dtype=np.int64)


def sliding_windows(x: np.ndarray, window: int = WINDOW_SAMPLES, hop: int = HOP_SAMPLES) -> np.ndarray:
    """Windows ``(N, window, C)`` of a stream ``(T, C)``, shifted by ``hop`` (views, no copy)."""
    if x.shape[0] < window:
        return np.zeros((0, window) + x.shape[1:], dtype=x.dtype)
    views = np.lib.stride_tricks.sliding_window_view(x, window, axis=0)  # (T-window+1, C, window)
    return np.moveaxis(views[::hop], -1, 1)
