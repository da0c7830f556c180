"""The training loop's weight average (``train.ema_decay``)."""

from pathlib import Path

import torch

from training.config import load_config
from training.data.catalog import mocap_entries
from training.data.mocap import build_kinematics
from training.train import build_model, train

CONFIG = Path(__file__).resolve().parents[2] / "training/configs/i2s_assignment.yaml"
TINY = ["train.steps_per_epoch=1", "train.max_epochs=1", "train.val_windows=128", "train.batch_size=64"]


def test_the_moving_average_of_the_weights_is_what_is_returned(data_dir: Path, kinematics_cache: Path) -> None:
    """With one step, the average is decay · W₀ + (1 − decay) · W₁ for every float weight and batch-norm
    statistic, where W₀ are the seeded initial weights and W₁ the weights that the same run without the average
    returns (same seed, same batches)."""
    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:2]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    raw_cfg = load_config(CONFIG, TINY)
    torch.manual_seed(raw_cfg.seed)
    initial = build_model(raw_cfg).state_dict()
    raw = train(raw_cfg, clips, clips).model.state_dict()
    decay = 0.25
    averaged = train(load_config(CONFIG, [*TINY, f"train.ema_decay={decay}"]), clips, clips).model.state_dict()
    moved = 0
    for key, value in averaged.items():
        if not value.is_floating_point():
            continue
        torch.testing.assert_close(value, decay * initial[key] + (1 - decay) * raw[key], msg=key)
        moved += int(not torch.equal(initial[key], raw[key]))
    assert moved > 10  # the step changed the weights, so the average differs from both ends
