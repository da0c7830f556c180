"""The training loop: its weight average (``train.ema_decay``), which weights it returns (``train.keep``), and a
network taught by a shipped one (``train.distill_from``)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from training.data.catalog import mocap_entries
from training.i2s.config import load_config
from training.i2s.data.mocap import build_kinematics
from training.i2s.train import build_model, train

ROOT = Path(__file__).resolve().parents[3]
CONFIG = ROOT / "training/configs/i2s_assignment.yaml"
ALIGNMENT = ROOT / "training/configs/i2s_alignment.yaml"
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


def test_the_distillation_loss_is_the_cross_entropy_and_the_softened_kl_in_their_shares() -> None:
    """Hinton et al. 2015: weight 0 is the plain cross entropy; weight 1 is τ² × KL of the softened distributions,
    zero (with zero gradient) when the student already says what the teacher says, and positive otherwise."""
    from training.i2s.train import distillation_loss

    torch.manual_seed(0)
    logits, teacher = torch.randn(8, 7, requires_grad=True), torch.log_softmax(torch.randn(8, 7), -1)
    segment = torch.randint(0, 7, (8,))
    plain = torch.nn.functional.cross_entropy(logits, segment)
    torch.testing.assert_close(distillation_loss(logits, teacher, segment, 0.0, 2.0), plain)
    soft = distillation_loss(logits, teacher, segment, 1.0, 2.0)
    p_t, log_p_s = torch.softmax(teacher / 2.0, -1), torch.log_softmax(logits / 2.0, -1)
    expected = 4.0 * (p_t * (torch.log(p_t) - log_p_s)).sum(-1).mean()
    torch.testing.assert_close(soft, expected)
    assert float(soft) > 0.01
    # a mask: the untaught windows keep their cross entropy, the taught ones the soft term alone
    taught = torch.tensor([True, False] * 4)
    per_window_ce = torch.nn.functional.cross_entropy(logits, segment, reduction="none")
    per_window_kl = 4.0 * (p_t * (torch.log(p_t) - log_p_s)).sum(-1)
    masked = distillation_loss(logits, teacher[taught], segment, 1.0, 2.0, taught)
    torch.testing.assert_close(masked, torch.where(taught, per_window_kl, per_window_ce).mean())
    half = distillation_loss(logits, teacher[taught], segment, 0.5, 2.0, taught)
    torch.testing.assert_close(
        half, torch.where(taught, 0.5 * per_window_ce + 0.5 * per_window_kl, per_window_ce).mean()
    )
    none = torch.zeros(8, dtype=torch.bool)
    torch.testing.assert_close(distillation_loss(logits, teacher[none], segment, 0.9, 2.0, none), plain)
    same = teacher.clone().requires_grad_(True)
    agreed = distillation_loss(same, teacher, segment, 1.0, 2.0)
    agreed.backward()
    assert abs(float(agreed)) < 1e-6 and float(same.grad.abs().max()) < 1e-6


def test_the_teacher_is_the_shipped_file_in_log_probabilities() -> None:
    """The archived 1.9.0 (the mean of 1.6.0's sixteen turns and 1.8.0) and the one-pass 1.8.0, rebuilt in torch as
    teachers, give their shipped graphs' golden probabilities as log probabilities, frozen."""
    from training.i2s.train import build_teacher

    for version in ("1.9.0", "1.8.0"):
        teacher_dir = Path(__file__).resolve().parents[3] / f"mlflow_snapshot/models/i2s_assignment/{version}"
        teacher = build_teacher(load_config(CONFIG, [f"train.distill_from={teacher_dir}"]))
        assert teacher is not None and not any(p.requires_grad for p in teacher.parameters())
        with np.load(teacher_dir / "golden.npz") as golden, torch.no_grad():
            p = torch.exp(teacher(torch.from_numpy(golden["imu"]))).numpy()
            np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)
            np.testing.assert_allclose(p, golden["expected"], atol=1e-4)


def test_a_distilled_network_learns_what_its_teacher_says(data_dir: Path, kinematics_cache: Path, monkeypatch) -> None:
    """Trained on a teacher's answers alone (weight 1), a network learns them even where they are not the labels:
    a teacher that gives every window the same distribution, most of it on the first class, pulls the network's
    mean probability of that class towards its own; the same network trained on the labels does not."""
    import training.i2s.train as loop

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:2]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    sets = [*TINY, "train.steps_per_epoch=40", "train.lr=0.003", "train.keep=last", "train.distill_temperature=1.0"]
    classes = build_model(load_config(CONFIG, TINY)).head.out_features
    favoured = torch.full((classes,), 0.2 / (classes - 1))
    favoured[0] = 0.8

    class Constant(torch.nn.Module):
        def forward(self, imu: torch.Tensor) -> torch.Tensor:
            return torch.log(favoured).expand(len(imu), classes)

    monkeypatch.setattr(loop, "build_teacher", lambda cfg: Constant() if cfg.train.distill_weight > 0 else None)
    windows = torch.from_numpy(loop.WindowSampler(clips, loop.Augmentation()).sample(np.random.default_rng(9), 256).imu)

    def first_class_share(weight: float) -> float:
        net = loop.train(load_config(CONFIG, [*sets, f"train.distill_weight={weight}"]), clips, clips).model
        with torch.no_grad():
            return float(torch.softmax(net(windows), -1)[:, 0].mean())

    taught, labelled = first_class_share(1.0), first_class_share(0.0)
    assert taught > 0.5 and labelled < 0.3, (taught, labelled)


def test_a_teacher_teaches_a_network_of_its_own_task_that_trains() -> None:
    from training.i2s.train import build_teacher

    teacher = f"train.distill_from={ROOT}/mlflow_snapshot/models/i2s_assignment/1.8.0"
    with pytest.raises(ValueError, match="is an i2s_assignment model; this run trains alignment"):
        build_teacher(load_config(ALIGNMENT, [teacher]))
    with pytest.raises(ValueError, match="is an i2s_alignment model; this run trains assignment"):
        build_teacher(load_config(CONFIG, [f"train.distill_from={alignment_teacher_dir()}"]))
    ensemble = (
        "train.ensemble_of=[mlflow_snapshot/models/i2s_assignment/1.6.0,mlflow_snapshot/models/i2s_assignment/1.8.0]"
    )
    with pytest.raises(ValueError, match="assembled, not trained"):
        load_config(CONFIG, [teacher, ensemble, "train.max_epochs=0"])
    # real windows carry no alignment label: an alignment run takes them only with a teacher, and validates without
    real = ["data.real_train_recordings=[ximu3_lowerbody]", "data.real_fraction=0.25", "data.real_val_fraction=0"]
    with pytest.raises(ValueError, match="need a teacher"):
        load_config(ALIGNMENT, real)
    with pytest.raises(ValueError, match="set data.real_val_fraction 0"):
        load_config(ALIGNMENT, [*real, "data.real_val_fraction=0.2", teacher])
    # an alignment teacher answers quaternions without functional axes: the student learns them so, wrapped after
    aligned = f"train.distill_from={alignment_teacher_dir()}"
    with pytest.raises(ValueError, match="through the quaternion loss"):
        load_config(ALIGNMENT, [aligned, "train.canonical_frame=false", "train.alignment_loss=stereographic_l2"])
    with pytest.raises(ValueError, match="train the student without them"):
        load_config(ALIGNMENT, [aligned, "train.functional_axes=[Pelvis]"])
    wrap = load_config(ALIGNMENT, [aligned, "train.functional_axes=[Pelvis]", "train.max_epochs=0"])
    assert wrap.train.functional_axes == ["Pelvis"]
    with pytest.raises(ValueError, match="data.real_fraction > 0"):
        load_config(ALIGNMENT, [aligned, "data.real_rotation=true"])
    with pytest.raises(ValueError, match="float32 alignment file"):  # its int8 twin
        build_teacher(load_config(ALIGNMENT, [aligned.replace("3.10.0", "3.11.0")]))
    with pytest.raises(ValueError, match="set train.distill_from"):
        load_config(CONFIG, ["train.distill_activities=[walk]"])
    with pytest.raises(ValueError, match="must be some of data.activities"):
        load_config(CONFIG, [teacher, "train.distill_activities=[wlak]"])


def test_the_windows_a_teacher_speaks_for_are_those_of_its_activities(
    data_dir: Path, kinematics_cache: Path, monkeypatch
) -> None:
    """``taught_activities`` marks each drawn window by its clip's activity, window by window through the
    moving-window filter and the mixing with real windows (which count as taught), and leaves the draws as they
    were."""
    import training.i2s.data.windows as windows

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:1]
    entries += [e for e in mocap_entries(data_dir, ["dance"]) if e.group == "cmu_05"][:1]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    aug = windows.Augmentation(moving_only=True)
    marked = windows.WindowSampler(clips, aug, taught_activities=["walk"])
    plain = windows.WindowSampler(clips, aug)
    monkeypatch.setattr(windows, "is_moving", lambda imu: np.arange(len(imu)) % 3 != 0)  # a third dropped
    draws, draw = [], marked._draw
    monkeypatch.setattr(marked, "_draw", lambda rng, n: draws.append(draw(rng, n)) or draws[-1])
    b = marked.sample(np.random.default_rng(0), 256)
    assert len(draws) == 2  # two draws of 256 keep 2 × 170 windows
    keep = np.arange(256) % 3 != 0
    np.testing.assert_array_equal(b.taught, np.concatenate([d.taught[keep] for d in draws])[:256])
    np.testing.assert_array_equal(b.imu, np.concatenate([d.imu[keep] for d in draws])[:256])
    for activity, clip in (("walk", clips[:1]), ("dance", clips[1:])):  # each mark is its clip's activity
        alone = windows.WindowSampler(clip, windows.Augmentation(), taught_activities=["walk"])
        assert (alone.sample(np.random.default_rng(1), 32).taught == (activity == "walk")).all()
    same = plain.sample(np.random.default_rng(0), 256)
    assert same.taught is None
    for f in ("imu", "segment", "q_segment_imu"):
        np.testing.assert_array_equal(getattr(b, f), getattr(same, f))
    assert b.taught is not None and len(b.taught) == 256 and 0 < b.taught.sum() < 256
    real = windows.Batch(np.zeros((4, 128, 6), np.float32), np.zeros(4, np.int64), np.zeros((4, 4), np.float32))
    mixed = windows.concat_batches(b, real)
    assert mixed.taught is not None and mixed.taught[-4:].all() and (mixed.taught[:256] == b.taught).all()


def test_a_distilled_networks_manifest_names_its_teacher() -> None:
    from service.core.manifest import read_manifest
    from training.i2s.ship import _teacher

    teacher_dir = Path(__file__).resolve().parents[3] / "mlflow_snapshot/models/i2s_assignment/1.9.0"
    cfg = load_config(CONFIG, [f"train.distill_from={teacher_dir}", "train.distill_activities=[walk,run]"])
    record = _teacher(cfg)["distilled_from"]
    assert record["model"] == "i2s_assignment/1.9.0" and record["activities"] == ["walk", "run"]
    assert record["sha256"] == read_manifest(teacher_dir / "manifest.json").sha256
    assert (record["weight"], record["temperature"]) == (0.9, 2.0)


def alignment_teacher_dir() -> Path:
    """The float32 file of the alignment the service served from 2026-12-05 to 2026-12-08 (3.10.0; archived since),
    where it lies now: the teacher of training/configs/i2s_alignment_distilled.yaml."""
    for root in ("onnx_models", "mlflow_snapshot/models"):
        if (ROOT / root / "i2s_alignment/3.10.0/model.onnx").exists():
            return ROOT / root / "i2s_alignment/3.10.0"
    raise FileNotFoundError("i2s_alignment 3.10.0 is neither served nor archived")


def test_the_alignment_distillation_loss_is_the_label_and_the_teacher_in_their_shares() -> None:
    """Per window the true segment's row: weight 0 is the distance to the label, weight 1 the distance to the
    teacher's row; a window without a label (NaN, real) learns the teacher's alone whatever the weight, one the
    teacher does not speak for its label alone; a student that says what both say has zero loss and gradient."""
    from training.i2s.train import alignment_distillation_loss, quat_distance

    torch.manual_seed(0)
    unit = lambda x: x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    student = unit(torch.randn(8, 7, 4)).requires_grad_(True)
    teacher, q_true = unit(torch.randn(8, 7, 4)), unit(torch.randn(8, 4))
    segment = torch.randint(0, 7, (8,))
    rows = torch.arange(8)
    to_label = quat_distance(student[rows, segment], q_true)
    to_teacher = quat_distance(student[rows, segment], teacher[rows, segment])
    torch.testing.assert_close(alignment_distillation_loss(student, teacher, segment, q_true, 0.0), to_label.mean())
    torch.testing.assert_close(alignment_distillation_loss(student, teacher, segment, q_true, 1.0), to_teacher.mean())
    real = torch.tensor([False, True] * 4)
    unlabelled = torch.where(real[:, None], torch.full_like(q_true, float("nan")), q_true)
    mixed = alignment_distillation_loss(student, teacher, segment, unlabelled, 0.25)
    torch.testing.assert_close(mixed, torch.where(real, to_teacher, 0.75 * to_label + 0.25 * to_teacher).mean())
    taught = real.clone()  # the simulated windows untaught: their labels alone
    torch.testing.assert_close(
        alignment_distillation_loss(student, teacher, segment, unlabelled, 0.25, taught),
        torch.where(real, to_teacher, to_label).mean(),
    )
    with pytest.raises(ValueError, match="without an alignment label must be one the teacher speaks for"):
        alignment_distillation_loss(student, teacher, segment, unlabelled, 0.25, ~real)
    agreed = teacher.clone().requires_grad_(True)
    loss = alignment_distillation_loss(agreed, teacher, segment, teacher[rows, segment].clone(), 0.5)
    loss.backward()
    radial = (agreed.grad * agreed).sum(-1, keepdim=True) * agreed  # off the unit sphere, which the net's norm fixes
    assert float(loss) < 1e-6 and float((agreed.grad - radial).abs().max()) < 1e-5
    assert float(alignment_distillation_loss(student, teacher, segment, q_true, 0.5)) > 0.1


def test_the_alignment_teacher_is_the_shipped_network_without_its_functional_axes() -> None:
    """Frozen, one answer per segment, no functional axes of its own; its weights in the shipped graph's form (the
    functional axes and the pelvis rule of its manifest) give the shipped golden quaternions."""
    from training.i2s.models import AlignmentNet
    from training.i2s.train import build_teacher

    teacher_dir = alignment_teacher_dir()
    teacher = build_teacher(load_config(ALIGNMENT, [f"train.distill_from={teacher_dir}"]))
    assert isinstance(teacher, AlignmentNet) and not teacher.training
    assert not any(p.requires_grad for p in teacher.parameters())
    assert teacher.functional_axes is None and teacher.rnn_stride == 1
    manifest = json.loads((teacher_dir / "manifest.json").read_text())
    shipped = AlignmentNet(
        128,
        64,
        16,
        canonical=True,
        functional_axes=manifest["exporter"]["functional_axes"],
        pelvis_half_turn=manifest["exporter"]["pelvis_half_turn"],
    )
    shipped.load_state_dict(teacher.state_dict())
    shipped.eval()
    with np.load(teacher_dir / "golden.npz") as golden, torch.no_grad():
        imu = torch.from_numpy(golden["imu"])
        raw, wrapped = teacher(imu).numpy(), shipped(imu).numpy()
        expected = golden["expected"]
    assert raw.shape == expected.shape == (len(imu), 7, 4)
    np.testing.assert_allclose(np.minimum(abs(wrapped - expected), abs(wrapped + expected)).max(), 0.0, atol=1e-4)
    assert np.minimum(abs(raw - expected), abs(raw + expected)).max() > 1e-2  # the functional axes do turn it


def test_an_alignment_network_learns_its_teachers_answer_on_real_windows(
    data_dir: Path, kinematics_cache: Path, monkeypatch
) -> None:
    """Trained with a teacher that answers one fixed rotation for every window, on simulated windows without a
    teacher's say (weight 0) and real windows, which have no label: the real windows pull the network's answer on
    real windows towards the teacher's; the same network without the real windows stays away from it."""
    import training.i2s.train as loop
    from service.core.recordings import read_recording
    from training.i2s.data.windows import RealWindowSampler

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:2]
    clips = build_kinematics(data_dir, entries, kinematics_cache)
    fixed = torch.tensor([0.5, 0.5, -0.5, 0.5])

    class Constant(torch.nn.Module):
        def forward(self, imu: torch.Tensor) -> torch.Tensor:
            return fixed.expand(len(imu), 7, 4)

    monkeypatch.setattr(loop, "build_teacher", lambda cfg: Constant())
    real = RealWindowSampler([read_recording(data_dir, "ximu3_lowerbody")])
    probe = real.sample(np.random.default_rng(5), 128)
    sets = [
        *TINY,
        "train.steps_per_epoch=40",
        "train.lr=0.003",
        "train.keep=last",
        "train.canonical_frame=true",
        "train.distill_weight=0",
        "train.distill_from=unused",  # the teacher is the constant above
        "data.real_val_fraction=0",
    ]

    def distance_to_teacher(real_fraction: float) -> float:
        cfg = load_config(ALIGNMENT, [*sets, f"data.real_fraction={real_fraction}"])
        net = loop.train(cfg, clips, clips, real=real if real_fraction else None).model
        with torch.no_grad():
            q = net(torch.from_numpy(probe.imu))[torch.arange(len(probe.segment)), torch.from_numpy(probe.segment)]
        return float(loop.quat_distance(q, fixed.expand_as(q)).mean())

    taught, alone = distance_to_teacher(0.5), distance_to_teacher(0.0)
    assert taught < 0.5 * alone, (taught, alone)
