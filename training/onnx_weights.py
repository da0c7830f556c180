"""Recurrent weights read back from a graph the TorchScript exporter wrote (a warm start from a shipped file, on a
fresh clone whose restored runs carry no checkpoints).

The exporter stores one ONNX GRU or LSTM node per layer, with the weights in ONNX gate order: GRU (z, r, h) where
torch uses (r, z, n), LSTM (i, o, f, c) where torch uses (i, f, g, o); W, R and B carry one block per direction
(forward, then reverse), and B is the input bias followed by the recurrent one.
"""

from __future__ import annotations

import numpy as np
import torch

# Gate blocks along axis 0: where each torch gate sits in the ONNX layout (torch order, ONNX positions).
GRU_GATES = (1, 0, 2)  # ONNX (z, r, h) → torch (r, z, n)
LSTM_GATES = (0, 2, 3, 1)  # ONNX (i, o, f, c) → torch (i, f, g, o)


def reorder_gates(w: np.ndarray, hidden: int, order: tuple[int, ...]) -> np.ndarray:
    """ONNX gate blocks along axis 0 → torch's order (``GRU_GATES``, ``LSTM_GATES``)."""
    return np.concatenate([w[g * hidden : (g + 1) * hidden] for g in order])


def recurrent_state(
    node, inits: dict[str, np.ndarray], layer: int, hidden: int, order: tuple[int, ...], prefix: str = "rnn."
) -> dict[str, torch.Tensor]:
    """The torch ``nn.GRU`` / ``nn.LSTM`` state entries of one layer from its ONNX node (``inits``: the graph's
    initializers by name), both directions where the node has two (torch's ``_reverse`` keys)."""
    W, R, B = (inits[name] for name in node.input[1:4])
    gates = len(order)
    state = {}
    for direction in range(W.shape[0]):
        suffix = f"l{layer}" + ("_reverse" if direction else "")
        b = B[direction]
        state[f"{prefix}weight_ih_{suffix}"] = torch.from_numpy(reorder_gates(W[direction], hidden, order))
        state[f"{prefix}weight_hh_{suffix}"] = torch.from_numpy(reorder_gates(R[direction], hidden, order))
        state[f"{prefix}bias_ih_{suffix}"] = torch.from_numpy(reorder_gates(b[: gates * hidden], hidden, order))
        state[f"{prefix}bias_hh_{suffix}"] = torch.from_numpy(reorder_gates(b[gates * hidden :], hidden, order))
    return state
