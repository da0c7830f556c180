"""Window sampling from cached kinematics, real-data mixing, and the training loop on tiny budgets."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from service.core.assignment import is_moving
from service.core.recordings import read_recording
from service.core.rotations import matrix_from_quat
from service.core.segments import MIRROR
from training.data.catalog import mocap_entries
from training.i2s.config import load_config
from training.i2s.data.mocap import build_kinematics
from training.i2s.data.windows import (
    Augmentation,
    Batch,
    RealWindowSampler,
    WindowSampler,
    grid_batches,
    real_window_samplers,
    source_balanced_weights,
)
from training.i2s.train import train

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def walk_clips(data_dir: Path, kinematics_cache: Path):
    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"]
    return build_kinematics(data_dir, entries, kinematics_cache)


@pytest.mark.parametrize("mirror", [False, True])
def test_sampled_labels_match_the_readings(walk_clips, mirror: bool) -> None:
    """Rotating the readings back by the label's R_SI gives the segment-frame gravity direction."""
    sampler = WindowSampler(walk_clips, Augmentation(alignment="grid", acc_noise_std_mps2=0.0, mirror=mirror))
    assert len(sampler.clips) == (2 if mirror else 1) * sum(c.n_samples > 128 for c in walk_clips)
    batch = sampler.sample(np.random.default_rng(0), 64)
    assert batch.imu.shape == (64, 128, 6) and batch.imu.dtype == np.float32
    assert np.all(batch.q_segment_imu[:, 0] >= -1e-6)
    R = matrix_from_quat(batch.q_segment_imu)
    acc_segment = np.einsum("bij,btj->bti", R, batch.imu[..., :3]).mean(axis=1)
    # averaged over ~2 s of walking, the specific force in the segment frame points mostly up (+z)
    for k in np.flatnonzero(np.isin(batch.segment, [1, 2, 3, 4, 5])):
        assert acc_segment[k, 2] > 5.0, (batch.segment[k], acc_segment[k])


def test_moving_only_draws_the_windows_the_service_answers(data_dir: Path, kinematics_cache: Path) -> None:
    """A clip with long still spells (CMU 'wash_self', a third moving) gives a full batch of moving windows; one that
    is still throughout (li2018 'basketball_signal') is refused with a message, not looped on."""
    washing = build_kinematics(data_dir, mocap_entries(data_dir, ["wash_self"]), kinematics_cache)
    plain = WindowSampler(washing, Augmentation()).sample(np.random.default_rng(0), 256)
    assert 0.1 < is_moving(plain.imu).mean() < 0.7
    batch = WindowSampler(washing, Augmentation(moving_only=True)).sample(np.random.default_rng(0), 256)
    assert batch.imu.shape == (256, 128, 6) and batch.segment.shape == (256,) and batch.q_segment_imu.shape == (256, 4)
    assert is_moving(batch.imu).all()
    signals = build_kinematics(data_dir, mocap_entries(data_dir, ["basketball_signal"]), kinematics_cache)
    with pytest.raises(ValueError, match="nearly all still"):
        WindowSampler(signals, Augmentation(moving_only=True)).sample(np.random.default_rng(0), 256)


def test_grid_evaluation_is_deterministic_and_complete(walk_clips) -> None:
    clip = walk_clips[:1]
    a = list(grid_batches(clip, Augmentation(), seed=3, batch_size=4096))
    b = [b for b, _ in grid_batches(clip, Augmentation(), seed=3, batch_size=4096)]
    n_windows = len(range(0, clip[0].n_samples - 127, 16))
    assert sum(len(x.segment) for x, _ in a) == n_windows * 7 * 64
    np.testing.assert_array_equal(a[0][0].imu, b[0].imu)
    # A body is the seven segments' windows at one moment with one alignment index.
    segment, body = (np.concatenate(x) for x in zip(*((x.segment, y) for x, y in a), strict=True))
    assert len(np.unique(body)) == n_windows * 64
    for k in np.unique(body)[[0, 1, 64, -1]]:
        assert sorted(segment[body == k].tolist()) == list(range(7))


def test_real_windows_are_moving_and_labelled(data_dir: Path) -> None:
    real = RealWindowSampler([read_recording(data_dir, "capacitive_sub01/CSBaseline")])
    assert set(np.unique(real.segment)) == set(range(7))
    batch = real.sample(np.random.default_rng(0), 32)
    assert np.isnan(batch.q_segment_imu).all()  # no alignment labels on real data


def test_mirrored_real_windows_swap_sides_and_flip_the_mirrored_axes(data_dir: Path) -> None:
    """``mirror``: about that share of drawn windows is read as the mirror-image body's sensor (accelerometer y,
    gyroscope x and z negated) and labelled as the other side's segment; the rest are drawn as without it, and a
    share of 0 draws exactly the windows it drew before."""
    recording = read_recording(data_dir, "capacitive_sub01/CSBaseline")
    plain = RealWindowSampler([recording])
    half = RealWindowSampler([recording], mirror=0.5)
    a = plain.sample(np.random.default_rng(0), 512)
    b = half.sample(np.random.default_rng(0), 512)  # the same windows (idx is drawn first), some mirrored
    flipped = ~np.isclose(a.imu, b.imu).all(axis=(1, 2))
    assert 0.4 < flipped.mean() < 0.6
    np.testing.assert_array_equal(b.segment[flipped], np.asarray(MIRROR)[a.segment[flipped]])
    np.testing.assert_array_equal(b.segment[~flipped], a.segment[~flipped])
    sign = np.array([1, -1, 1, -1, 1, -1], np.float32)
    np.testing.assert_array_equal(b.imu[flipped], a.imu[flipped] * sign)
    assert (b.segment[flipped] != a.segment[flipped]).mean() > 0.6  # only the pelvis keeps its label
    # a share of 0 draws nothing more than the sampler without it: the generator is where it would be
    rng_plain, rng_zero = np.random.default_rng(1), np.random.default_rng(1)
    plain.sample(rng_plain, 64)
    RealWindowSampler([recording], mirror=0.0).sample(rng_zero, 64)
    assert rng_plain.bit_generator.state == rng_zero.bit_generator.state
    # and the validation windows are read as recorded
    cfg = load_config(
        REPO / "training/configs/i2s_assignment_real.yaml",
        ["data.real_mirror=0.5", "data.real_train_recordings=[capacitive_sub01/CSBaseline]"],
    )
    train_part, val_part = real_window_samplers(cfg, [recording])
    assert (train_part.mirror, val_part.mirror) == (0.5, 0.0)


def test_turned_real_windows_are_the_same_windows_read_by_a_sensor_strapped_another_way(data_dir: Path) -> None:
    """``rotate``: the same windows as without it (drawn first), each turned by one rotation of its own: every
    sample's accelerometer and gyroscope keep their lengths and the angle between them, and the windows differ;
    ``data.real_rotation`` asks for it only where a teacher answers an alignment run."""
    recording = read_recording(data_dir, "capacitive_sub01/CSBaseline")
    a = RealWindowSampler([recording]).sample(np.random.default_rng(0), 64)
    b = RealWindowSampler([recording], rotate=True).sample(np.random.default_rng(0), 64)
    np.testing.assert_array_equal(a.segment, b.segment)
    for x in (slice(0, 3), slice(3, 6)):
        np.testing.assert_allclose(np.linalg.norm(b.imu[..., x], axis=-1), np.linalg.norm(a.imu[..., x], axis=-1), 1e-4)
    dot = lambda w: (w[..., :3] * w[..., 3:]).sum(-1)  # noqa: E731
    np.testing.assert_allclose(dot(b.imu), dot(a.imu), rtol=1e-3, atol=1e-3)
    assert not np.isclose(a.imu, b.imu, atol=1e-2).all(axis=(1, 2)).any()
    alignment = REPO / "training/configs/i2s_alignment_distilled.yaml"
    assert load_config(alignment, ["data.real_rotation=true"]).data.real_rotation
    with pytest.raises(ValueError, match="real_rotation turns real windows for a teacher"):
        load_config(REPO / "training/configs/i2s_assignment_real.yaml", ["data.real_rotation=true"])


def test_real_validation_windows_come_after_every_training_window(data_dir: Path) -> None:
    """The time split: the validation part is the last fifth of each sensor's recording, and no validation window
    shares a sample with a training window."""
    recording = read_recording(data_dir, "capacitive_sub01/CSBaseline")
    train_part = RealWindowSampler([recording], "train", 0.2)
    val_part = RealWindowSampler([recording], "validation", 0.2)
    whole = RealWindowSampler([recording])
    assert 0.1 < len(val_part.segment) / len(whole.segment) < 0.3
    assert len(train_part.segment) + len(val_part.segment) <= len(whole.segment)
    sensor = next(s for s in recording.sensors if s.segment is not None)
    cut = int(round(len(sensor.imu) * 0.8))
    first_val = val_part.imu[val_part.segment == sensor.segment][0]
    windows = np.lib.stride_tricks.sliding_window_view(sensor.imu.astype(np.float32), (128, 6))[:, 0]
    starts = np.flatnonzero((np.abs(windows - first_val) < 1e-6).all(axis=(1, 2)))
    assert len(starts) and starts[0] >= cut  # it begins after the cut: no sample shared with a training window
    with pytest.raises(ValueError, match="validation part"):
        RealWindowSampler([recording], "validation", 1e-4)  # too short for one window


def test_source_balance_draws_each_source_and_each_of_its_people_alike(data_dir: Path) -> None:
    """``balance="source"``: a source of one short recording is drawn as often as one of many long ones, and the people
    of a source share its draws equally, whatever their windows."""
    owner = [("a", "p1")] * 90 + [("a", "p2")] * 10 + [("b", "q")] * 5
    w = source_balanced_weights(owner)
    assert np.isclose(w.sum(), 1.0)
    assert np.isclose(w[:90].sum(), 0.25) and np.isclose(w[90:100].sum(), 0.25) and np.isclose(w[100:].sum(), 0.5)
    recordings = [read_recording(data_dir, "capacitive_sub01/CSBaseline"), read_recording(data_dir, "ximu3_lowerbody")]
    plain, balanced = RealWindowSampler(recordings), RealWindowSampler(recordings, balance="source")
    n_first = len(RealWindowSampler(recordings[:1]).segment)
    assert n_first / len(plain.segment) > 0.8  # the capacitive trial holds most windows
    assert plain.p is None and np.isclose(balanced.p[:n_first].sum(), 0.5)
    drawn = np.random.default_rng(0).choice(len(balanced.p), 20_000, p=balanced.p)
    assert 0.47 < np.mean(drawn < n_first) < 0.53
    batch = balanced.sample(np.random.default_rng(1), 64)
    assert batch.imu.shape == (64, 128, 6) and np.isin(batch.segment, balanced.segment).all()
    cfg = load_config(REPO / "training/configs/i2s_assignment_real.yaml", ["data.real_balance=source"])
    train_part, val_part = real_window_samplers(cfg, recordings)  # the config reaches both parts
    assert np.isclose(train_part.p[: len(RealWindowSampler(recordings[:1], "train").segment)].sum(), 0.5)
    direct = RealWindowSampler(recordings, "validation", cfg.data.real_val_fraction, balance="source")
    assert val_part.p is not None and np.array_equal(val_part.p, direct.p)
    # half the draws balanced, half by window: each window's chance is the mean of the two rules'
    half = RealWindowSampler(recordings, balance="source", balance_share=0.5)
    assert np.allclose(half.p, 0.5 * balanced.p + 0.5 / len(balanced.p))
    assert np.isclose(half.p[:n_first].sum(), 0.5 * 0.5 + 0.5 * n_first / len(plain.segment))
    cfg = load_config(
        REPO / "training/configs/i2s_assignment_real.yaml", ["data.real_balance=source", "data.real_balance_share=0.5"]
    )
    train_half = real_window_samplers(cfg, recordings)[0]
    n_train_first = len(RealWindowSampler(recordings[:1], "train").segment)
    assert np.isclose(train_half.p[:n_train_first].sum(), 0.25 + 0.5 * n_train_first / len(train_half.p))


def test_training_mixes_real_windows_and_refuses_them_for_alignment(walk_clips, data_dir: Path) -> None:
    cfg = load_config(
        REPO / "training/configs/i2s_assignment.yaml",
        [
            "train.steps_per_epoch=2",
            "train.max_epochs=1",
            "train.batch_size=32",
            "train.val_windows=64",
            "data.real_fraction=0.25",
        ],
    )
    recording = read_recording(data_dir, "capacitive_sub01/CSBaseline")
    real, real_val = RealWindowSampler([recording], "train"), RealWindowSampler([recording], "validation")
    result = train(cfg, walk_clips[2:], walk_clips[:2], real=real, real_val=real_val)
    assert len(result.history) == 1 and np.isfinite(result.history[0]["train_loss"])
    assert 0.0 <= result.history[0]["val_real_accuracy"] <= 1.0  # the real validation windows, reported alone
    align = cfg.model_copy(update={"task": "alignment"})
    with pytest.raises(ValueError, match="alignment labels"):
        train(align, walk_clips[2:], walk_clips[:2], real=real)


def test_stiff_knee_variants_follow_their_clip_and_take_their_share(
    data_dir: Path, kinematics_cache: Path, tmp_path: Path
) -> None:
    """Two variants per walking clip (left and right knee braced), rebuilt identically from the cache; in the
    LOSO split they go where their recorded clip goes and never into the test set; draws give them their share."""
    from training.i2s.data.mocap import braced_side, stiff_knee_variants
    from training.i2s.data.split import load_pack, save_pack, split_clips
    from training.i2s.data.windows import _draw_probabilities

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group in ("cmu_07", "cmu_05", "cmu_02")]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    variants = stiff_knee_variants(data_dir, clips, kinematics_cache, keep_max=0.4, seed=0)
    assert len(variants) == 2 * len(clips)
    assert {braced_side(v) for v in variants} == {"left", "right"}
    with pytest.raises(ValueError, match="not a stiff-knee variant"):
        braced_side(dataclasses.replace(variants[0], variant="mirror-left-0.1"))
    assert all(0.0 <= float(v.variant.split("-")[2]) <= 0.4 for v in variants)
    again = stiff_knee_variants(data_dir, clips, kinematics_cache, keep_max=0.4, seed=0)
    assert [v.digest for v in again] == [v.digest for v in variants]
    np.testing.assert_array_equal(again[0].kin.gyr_rads, variants[0].kin.gyr_rads)
    packed = load_pack(save_pack(variants[:2], tmp_path / "variants.npz"))  # a pack carries them to `fit`
    assert [(c.digest, c.variant, c.source_digest) for c in packed] == [
        (c.digest, c.variant, c.source_digest) for c in variants[:2]
    ]
    # a braced left knee changes the left shank, not the right one
    source = next(c for c in clips if c.digest == variants[0].source_digest)
    assert not np.allclose(variants[0].kin.gyr_rads[:, 1], source.kin.gyr_rads[:, 1], atol=0.1)
    np.testing.assert_allclose(variants[0].kin.gyr_rads[:, 5], source.kin.gyr_rads[:, 5], atol=1e-9)

    train_clips, val_clips, test_clips = split_clips(clips + variants, ["cmu_07"], 0.3, seed=0)
    recorded_train, recorded_val, recorded_test = split_clips(clips, ["cmu_07"], 0.3, seed=0)
    assert [c.digest for c in test_clips] == [c.digest for c in recorded_test]  # the test set is as recorded
    for part, recorded in ((train_clips, recorded_train), (val_clips, recorded_val)):
        sources = {c.digest for c in recorded}
        assert [c.digest for c in part if not c.variant] == [c.digest for c in recorded]
        assert {c.source_digest for c in part if c.variant} == sources
        assert sum(bool(c.variant) for c in part) == 2 * len(recorded)

    p = _draw_probabilities(train_clips, 0.2)
    assert p.sum() == pytest.approx(1.0)
    assert p[[bool(c.variant) for c in train_clips]].sum() == pytest.approx(0.2)
    with pytest.raises(ValueError, match="share in"):
        _draw_probabilities(train_clips, 0.0)
    sampler = WindowSampler(train_clips, Augmentation(stiff_knee_share=0.2))
    assert sampler.sample(np.random.default_rng(0), 32).imu.shape == (32, 128, 6)


def test_real_val_weight_sets_the_real_share_of_the_loss_that_selects_the_epoch() -> None:
    """By window count the 4,096 simulated windows outweigh the real ones; ``data.real_val_weight`` gives the real
    set a fixed share. A network that always answers class 0 is right on the simulated batch and wrong on the
    real one, so the two losses differ and each weighting has one answer."""
    import torch

    from training.i2s.train import _validation

    class AlwaysFirst(torch.nn.Module):
        def forward(self, imu: torch.Tensor) -> torch.Tensor:
            logits = torch.zeros(len(imu), 7)
            logits[:, 0] = 2.0
            return logits

    def batch(n: int, segment: int) -> Batch:
        return Batch(np.zeros((n, 128, 6), np.float32), np.full(n, segment, np.int64), np.zeros((n, 4), np.float32))

    sim, real = [batch(300, 0)], [batch(100, 3)]
    cpu = torch.device("cpu")
    alone_sim = _validation(AlwaysFirst(), "assignment", sim, [], cpu)["val_loss"]
    by_count = _validation(AlwaysFirst(), "assignment", sim, real, cpu)
    halves = _validation(AlwaysFirst(), "assignment", sim, real, cpu, real_weight=0.5)
    real_loss = by_count["val_real_loss"]
    assert real_loss > alone_sim + 1.0
    assert by_count["val_loss"] == pytest.approx(0.75 * alone_sim + 0.25 * real_loss)
    assert halves["val_loss"] == pytest.approx(0.5 * alone_sim + 0.5 * real_loss)
    assert halves["val_accuracy"] == pytest.approx(0.5)
