"""The training loop: its weight average (``train.ema_decay``) and which weights it returns (``train.keep``)."""

from pathlib import Path

import torch

from training.data.catalog import mocap_entries
from training.i2s.config import load_config
from training.i2s.data.mocap import build_kinematics
from training.i2s.train import build_model, train

CONFIG = Path(__file__).resolve().parents[3] / "training/configs/i2s_assignment.yaml"
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


def test_keep_last_returns_the_final_epoch_where_keep_best_returns_the_better_warm_start(
    data_dir: Path, kinematics_cache: Path
) -> None:
    """With a learning rate of 1 every epoch is worse than the warm start: ``keep: best`` returns the warm start
    (epoch 0) after ``patience`` epochs, ``keep: last`` trains the whole budget and returns its final weights."""
    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:2]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    sets = [*TINY, "train.max_epochs=3", "train.patience=1", "train.lr=1.0"]
    cfg = load_config(CONFIG, sets)
    torch.manual_seed(1)
    warm = build_model(cfg).state_dict()
    best = train(cfg, clips, clips, init_state=warm)
    last = train(load_config(CONFIG, [*sets, "train.keep=last"]), clips, clips, init_state=warm)
    assert best.best_epoch == 0 and len(best.history) == 1  # stopped after one worse epoch
    assert all(torch.equal(v, warm[k]) for k, v in best.model.state_dict().items())
    assert last.best_epoch == 3 and len(last.history) == 3
    changed = [k for k, v in last.model.state_dict().items() if v.is_floating_point() and not torch.equal(v, warm[k])]
    assert len(changed) > 10
