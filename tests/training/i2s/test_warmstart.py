"""Warm start from a shipped ONNX model, assignment or alignment: the rebuilt torch weights reproduce the model's
golden output."""

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from service.core.manifest import read_manifest
from service.inference.registry import version_key
from training.i2s.models import AlignmentNet, AssignmentNet
from training.i2s.warmstart import (
    assignment_ensemble,
    averaging_options,
    ensemble_members,
    ensemble_state,
    warm_start_from_shipped,
)

REPO = Path(__file__).resolve().parents[3]
ARCHIVE = REPO / "mlflow_snapshot" / "models"  # the shipped versions that are no longer served
ARCHIVED = ARCHIVE / "i2s_assignment"
ARCHIVED_ALIGNMENT = ARCHIVE / "i2s_alignment"


def _every_shipped(name: str = "i2s_assignment") -> list[Path]:
    """Every shipped version of ``name``: served or archived."""
    return sorted(p.parent for root in (REPO / "onnx_models", ARCHIVE) for p in (root / name).glob("*/manifest.json"))


def _float32(quantized: bool = False) -> Path:
    """The newest shipped float32 (or int8) assignment model that is one network (not an ensemble)."""
    dirs = _every_shipped()
    exporters = {d: read_manifest(d / "manifest.json").exporter for d in dirs}
    chosen = [d for d in dirs if ("quantization" in exporters[d]) == quantized and "ensemble_of" not in exporters[d]]
    return max(chosen, key=lambda d: version_key(d.name))


@pytest.mark.parametrize(
    "model_dir",
    [d for d in _every_shipped() if "quantization" not in read_manifest(d / "manifest.json").exporter],
    ids=lambda d: d.name,
)
def test_rebuilt_weights_match_the_shipped_model(model_dir: Path) -> None:
    """Every shipped float32 file, plain (1.0.0, 1.8.0) or averaged over turns (1.2.0 quarter turns, 1.4.0 also
    about gravity, 1.6.0 about gravity for the leg classes only), or an ensemble rebuilt from its members' files
    (1.9.0: the mean of 1.6.0's and 1.8.0's probabilities)."""
    exporter = read_manifest(model_dir / "manifest.json").exporter
    if "ensemble_of" in exporter:
        members = ensemble_members(exporter, ARCHIVE)
        net = assignment_ensemble(members, 128, 64, 16, 0.8)
        net.load_state_dict(ensemble_state(members, net))
    else:
        net = AssignmentNet(**averaging_options(exporter))
        net.load_state_dict(warm_start_from_shipped(model_dir, net))
    net.eval()
    with np.load(model_dir / "golden.npz") as golden, torch.no_grad():
        got = torch.softmax(net(torch.from_numpy(golden["imu"])), -1).numpy()
        np.testing.assert_allclose(got, golden["expected"], atol=1e-4)


@pytest.mark.parametrize(
    "model_dir",
    [d for d in _every_shipped("i2s_alignment") if "quantization" not in read_manifest(d / "manifest.json").exporter],
    ids=lambda d: d.name,
)
def test_rebuilt_alignment_weights_match_the_shipped_model(model_dir: Path) -> None:
    """Every shipped float32 alignment file (1.0.0 the paper's input, 2.0.0 / 3.0.0 with the canonical frame, 3.2.0
    also with the functional axes): the 2-layer LSTM comes back from two ONNX LSTM nodes in torch's gate order, so a
    fresh clone, whose restored runs carry no checkpoints, can fine-tune the shipped alignment."""
    exporter = read_manifest(model_dir / "manifest.json").exporter
    graph = onnx.load(str(model_dir / "model.onnx")).graph
    canonical = any(node.name.startswith("/canonical/") for node in graph.node)
    assert canonical == exporter.get("canonical_frame", canonical)
    stride = int(exporter.get("rnn_stride", 1))
    net = AlignmentNet(canonical=canonical, functional_axes=exporter.get("functional_axes"), rnn_stride=stride)
    net.load_state_dict(warm_start_from_shipped(model_dir, AlignmentNet(canonical=canonical, rnn_stride=stride)))
    net.eval()
    with np.load(model_dir / "golden.npz") as golden, torch.no_grad():
        got = net(torch.from_numpy(golden["imu"])).numpy()
        dot = np.abs(np.sum(got * golden["expected"], axis=-1))  # q and -q are one rotation
        np.testing.assert_allclose(dot, 1.0, atol=1e-5)


def test_a_model_of_the_other_task_is_refused() -> None:
    with pytest.raises(ValueError, match="is an i2s_alignment model; this run trains i2s_assignment"):
        warm_start_from_shipped(ARCHIVED_ALIGNMENT / "3.0.0", AssignmentNet())
    with pytest.raises(ValueError, match="is an i2s_assignment model; this run trains i2s_alignment"):
        warm_start_from_shipped(_float32(), AlignmentNet(canonical=True))


def test_a_wrong_golden_is_refused(tmp_path: Path) -> None:
    model_dir = _float32()
    (tmp_path / "manifest.json").write_bytes((model_dir / "manifest.json").read_bytes())
    (tmp_path / "model.onnx").write_bytes((model_dir / "model.onnx").read_bytes())
    with np.load(model_dir / "golden.npz") as golden:
        np.savez(tmp_path / "golden.npz", imu=golden["imu"], expected=golden["expected"][:, ::-1])
    with pytest.raises(ValueError, match="differ from its golden output"):
        warm_start_from_shipped(tmp_path, AssignmentNet())


def test_an_int8_model_is_refused_with_its_float32_source_named() -> None:
    with pytest.raises(ValueError, match="int8 model; warm start needs the float32 file"):
        warm_start_from_shipped(_float32(quantized=True), AssignmentNet())


def test_an_ensemble_is_refused_with_its_members_named() -> None:
    ensembles = [d for d in _every_shipped() if "ensemble_of" in read_manifest(d / "manifest.json").exporter]
    assert ensembles  # 1.9.0 is one
    for model_dir in ensembles:
        if "quantization" not in read_manifest(model_dir / "manifest.json").exporter:
            with pytest.raises(ValueError, match="is an ensemble; warm start from one of its members"):
                warm_start_from_shipped(model_dir, AssignmentNet())


def test_an_ensemble_is_assembled_not_trained() -> None:
    from training.i2s.config import load_config

    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_assignment.yaml"
    archived = "mlflow_snapshot/models/i2s_assignment"
    members = f"train.ensemble_of=[{archived}/1.6.0,{archived}/1.8.0]"
    assert load_config(config, [members, "train.max_epochs=0"]).train.ensemble_of
    for extra in ("train.max_epochs=3", "train.quarter_turns=true", "train.init_from_run=abc"):
        with pytest.raises(ValueError, match="ensemble_of assembles two or more shipped models"):
            load_config(config, [members, "train.max_epochs=0", extra])
    with pytest.raises(ValueError, match="got 1 members"):
        load_config(config, ["train.ensemble_of=[mlflow_snapshot/models/i2s_assignment/1.6.0]", "train.max_epochs=0"])


def test_an_ensemble_must_hold_its_members_real_training_recordings_out_of_evaluation(tmp_path: Path) -> None:
    """A member fine-tuned on real recordings (manifest ``training_data.real_train_recordings``) makes them the
    ensemble's training data too: the ensemble's config must name them, or its real-data evaluation would score
    windows a member learnt from."""
    import json
    import shutil

    from training.i2s.config import load_config
    from training.i2s.warmstart import check_real_recordings_declared

    member = tmp_path / "i2s_assignment" / "9.9.9"
    shutil.copytree(ARCHIVED / "1.8.0", member)
    manifest = json.loads((member / "manifest.json").read_text())
    manifest["training_data"]["real_train_recordings"] = ["ximu3_lowerbody"]
    (member / "manifest.json").write_text(json.dumps(manifest))
    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_assignment.yaml"
    members = f"train.ensemble_of=[mlflow_snapshot/models/i2s_assignment/1.6.0,{member}]"
    with pytest.raises(ValueError, match=r"trained on the real recordings \['ximu3_lowerbody'\]"):
        unnamed = load_config(config, [members, "train.max_epochs=0"])
        check_real_recordings_declared(unnamed.train.ensemble_of, unnamed.data.real_train_recordings, "member")
    named = load_config(config, [members, "train.max_epochs=0", "data.real_train_recordings=[ximu3_lowerbody]"])
    check_real_recordings_declared(named.train.ensemble_of, named.data.real_train_recordings, "member")


def test_the_warm_start_competes_as_epoch_zero(data_dir: Path, kinematics_cache: Path) -> None:
    """Fine-tuning that never beats the warm-start weights on validation returns them unchanged (best epoch 0);
    an epoch that does beat them is kept. A learning rate of 1 wrecks the shipped weights in two steps."""
    from training.data.catalog import mocap_entries
    from training.i2s.config import load_config
    from training.i2s.data.mocap import build_kinematics
    from training.i2s.train import train

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:3]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_assignment.yaml"
    tiny = ["train.steps_per_epoch=2", "train.val_windows=256", "train.batch_size=64", "train.threads=2"]
    net = AssignmentNet()
    init = warm_start_from_shipped(_float32(), net)
    wrecked = train(load_config(config, [*tiny, "train.max_epochs=1", "train.lr=1.0"]), clips, clips, init_state=init)
    assert wrecked.best_epoch == 0 and len(wrecked.history) == 1
    for key, value in wrecked.model.state_dict().items():
        torch.testing.assert_close(value, init[key], msg=key)
    from_scratch = train(load_config(config, [*tiny, "train.max_epochs=1"]), clips, clips)
    assert from_scratch.best_epoch == 1  # without a warm start, the first epoch is the first candidate


def test_fit_fine_tunes_a_shipped_alignment_file(data_dir: Path, kinematics_cache: Path, tmp_path: Path) -> None:
    """`fit` (the trainer for another machine: no MLflow, no data directory) starts from a shipped float32 file.
    A learning rate of 1 wrecks the weights in two steps, so the warm start, epoch 0, is what it keeps."""
    from typer.testing import CliRunner

    from training.cli import app
    from training.i2s.config import load_config
    from training.i2s.data.split import load_clips, save_pack

    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_alignment.yaml"
    shipped = ARCHIVED_ALIGNMENT / "3.0.0"
    overrides = [
        "data.activities=[walk]",
        "train.steps_per_epoch=2",
        "train.max_epochs=1",
        "train.val_windows=256",
        "train.batch_size=64",
        "train.threads=2",
        "train.lr=1.0",
        f"train.init_from_onnx={shipped}",
    ]
    save_pack(load_clips(load_config(config, overrides), data_dir, kinematics_cache), tmp_path / "clips.npz")
    args = ["fit", str(config), str(tmp_path / "clips.npz"), str(tmp_path / "fitted.pt")]
    for item in overrides:
        args += ["-s", item]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "best epoch 0 of 1" in result.output
    payload = torch.load(tmp_path / "fitted.pt", weights_only=True)
    for key, value in warm_start_from_shipped(shipped, AlignmentNet(canonical=True)).items():
        torch.testing.assert_close(payload["state"][key], value, msg=key)
    # the warm start's validation travels with the weights: step 0 of the tracked run's learning curves
    warm, first = payload["warm_start"], payload["history"][0]
    assert set(warm) == {k for k in first if k.startswith("val_")} and warm["val_loss"] < first["val_loss"]
