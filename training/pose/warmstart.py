"""Warm-start a pose network from a shipped ONNX file (``train.init_from_onnx``): fine-tuning a served model on one's
own motion capture (``data.own``) without its MLflow run, anywhere the shipped files are.

The graph's weights are read back into a ``PoseNet`` of the config's recipe: the feature standardisation (kept as
shipped, not recomputed on the new data, so that the network's inputs mean what they meant), the input layer, the
LSTM layers (``training.onnx_weights``) and the output layer. The rebuilt network must reproduce the file's
``golden.npz`` before a step is taken on it.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from service.core.manifest import read_manifest
from training.onnx_weights import LSTM_GATES, recurrent_state
from training.pose.config import PoseConfig, is_streaming
from training.pose.export import golden_pair
from training.pose.models import PoseNet

GOLDEN_ATOL = 1e-4


def state_from_onnx(onnx_path: Path, net: PoseNet) -> dict[str, torch.Tensor]:
    """``net``'s state dict filled from an exported pose graph of the same architecture, offline or streaming
    (whose names carry the ``StreamingExport`` wrapper's ``net.`` prefix)."""
    graph = onnx.load(str(onnx_path)).graph
    inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    prefix = "net." if "net.mean" in inits else ""
    own = net.state_dict()
    state = {k: v.clone() for k, v in own.items()}
    for key in ("mean", "std", "embed.0.bias", "out.bias"):
        state[key] = torch.from_numpy(inits[prefix + key].copy())
    # the two linear layers are MatMul nodes on (in, out) weights: the input layer's reads the standardised
    # features, the output layer's is the last
    matmuls = [n for n in graph.node if n.op_type == "MatMul" and n.input[1] in inits]
    if len(matmuls) != 2:
        raise ValueError(f"expected the input and output layers' two MatMul nodes, the graph has {len(matmuls)}")
    state["embed.0.weight"] = torch.from_numpy(inits[matmuls[0].input[1]].T.copy())
    state["out.weight"] = torch.from_numpy(inits[matmuls[-1].input[1]].T.copy())
    layers = [n for n in graph.node if n.op_type == "LSTM"]
    if net.rnn is not None:
        if len(layers) != net.rnn.num_layers:
            raise ValueError(f"the config's network has {net.rnn.num_layers} LSTM layers, the graph {len(layers)}")
        for layer, node in enumerate(layers):
            state |= recurrent_state(node, inits, layer, net.rnn.hidden_size, LSTM_GATES)
    elif layers:
        raise ValueError("the config's network is a feed-forward one, the graph has LSTM layers")
    wrong = {k: (tuple(v.shape), tuple(own[k].shape)) for k, v in state.items() if v.shape != own[k].shape}
    if wrong:
        raise ValueError(f"the graph's weights do not fit the config's network (graph, config shapes): {wrong}")
    return state


def warm_start_from_shipped(model_dir: Path, cfg: PoseConfig, net: PoseNet) -> dict[str, torch.Tensor]:
    """The state dict of a shipped single-network pose model, checked against ``cfg`` (task, sensors, output
    segments, representation, look-ahead and the segment frames it answers in) and against its golden output."""
    manifest = read_manifest(model_dir / "manifest.json")
    if manifest.task != "imu_pose" or manifest.pose is None:
        raise ValueError(f"{model_dir} is an {manifest.task} model; this run trains imu_pose")
    members = manifest.training_data.get("ensemble_of")
    if members:
        raise ValueError(
            f"{model_dir} averages {len(members)} networks (runs {members}); warm-start from one of them: its shipped "
            "file (python -m training.cli restore-model NAME VERSION brings an archived one back)"
        )
    spec, td = manifest.pose, manifest.training_data
    expected = {
        "sensors": (spec.sensors, cfg.sensors),
        "output segments": (spec.output_segments, cfg.outputs),
        "representation": (spec.representation, cfg.model.representation),
        "streaming": (spec.streaming, is_streaming(cfg)),
        "look-ahead frames": (spec.look_ahead_frames if spec.streaming else 0, cfg.model.look_ahead),
        "limb frames (data.limb_twist)": (td.get("limb_twist", "rig"), cfg.data.limb_twist),
        "trunk frames (data.trunk_axes)": (td.get("trunk_axes", "spine"), cfg.data.trunk_axes),
    }
    differ = {k: {"shipped": a, "config": b} for k, (a, b) in expected.items() if a != b}
    if differ:
        raise ValueError(f"{model_dir} is not of this config's recipe: {differ}")
    state = state_from_onnx(model_dir / "model.onnx", net)
    probe = copy.deepcopy(net)
    probe.load_state_dict(state)
    probe.eval()
    with np.load(model_dir / "golden.npz") as golden:
        got = golden_pair(probe, golden["features"][0], cfg)["expected"]
        err = float(np.max(np.abs(got - golden["expected"])))
    if err > GOLDEN_ATOL:
        raise ValueError(
            f"weights rebuilt from {model_dir} differ from its golden output by {err:.2e} > {GOLDEN_ATOL}: the config "
            "differs from the file's recipe where its manifest does not say (model.anchored)"
        )
    return state
