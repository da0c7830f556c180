"""Stepping a streaming graph (``features``, ``h0``, ``c0`` → output, ``h``, ``c``: the streaming pose networks and
the pelvis velocity networks export alike, ``training.pose.export.export_stateful``) for many live sessions at
once, each with its own LSTM state."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnxruntime as ort


@dataclass
class StreamState:
    h: np.ndarray  # (layers, 1, hidden)
    c: np.ndarray


def zero_state(layers: int, hidden: int) -> StreamState:
    """The state at the start of a recording or stream."""
    return StreamState(np.zeros((layers, 1, hidden), np.float32), np.zeros((layers, 1, hidden), np.float32))


def batchable(session: ort.InferenceSession) -> bool:
    """Whether the graph takes several sessions in one call (its batch dimension is symbolic)."""
    return isinstance(session.get_inputs()[0].shape[0], str)


def step_many(
    session: ort.InferenceSession, features: list[np.ndarray], states: list[StreamState]
) -> tuple[list[np.ndarray], list[StreamState]]:
    """Frames ``(n_k, F)`` of several live sessions → each one's outputs ``(n_k, ...)`` and new state: those with
    the same number of frames share one call (the LSTM states stacked along their batch axis) where the graph
    allows it."""
    names = [i.name for i in session.get_inputs()]
    together = batchable(session)
    ys: list[np.ndarray] = [np.empty(0)] * len(features)
    out_states: list[StreamState] = list(states)
    groups: dict[int, list[int]] = {}
    for k, f in enumerate(features):
        groups.setdefault(len(f), []).append(k)
    for members in groups.values():
        for batch in [members] if together else [[k] for k in members]:
            x = np.stack([features[k] for k in batch]).astype(np.float32)
            h = np.concatenate([states[k].h for k in batch], axis=1)
            c = np.concatenate([states[k].c for k in batch], axis=1)
            y, h, c = session.run(None, {names[0]: x, names[1]: h, names[2]: c})
            for row, k in enumerate(batch):
                ys[k] = y[row]
                out_states[k] = StreamState(h[:, row : row + 1].copy(), c[:, row : row + 1].copy())
    return ys, out_states
