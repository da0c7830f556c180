"""How the pose training draws its sequences."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from training.pose.train import clip_weights


def _clip(source: str, activity: str, frames: int) -> SimpleNamespace:
    return SimpleNamespace(source=source, activity=activity, motion=SimpleNamespace(n_frames=frames))


def test_clips_are_drawn_by_frames_with_capped_activities_and_an_optional_bandai_share() -> None:
    clips = [
        _clip("bandai_namco_2", "wave", 90_000),
        _clip("bandai_namco_2", "walk", 9_000),
        _clip("cmu_li2018", "walk", 1_000),
        _clip("cmu_iclone", "dance", 2_000),
    ]
    w = clip_weights(clips, cap_frames=30_000)
    # the waves count 30,000 of their 90,000 frames (the cap); the walks (10,000) and the dance by their frames
    np.testing.assert_allclose(w, np.array([30_000, 9_000, 1_000, 2_000]) / 42_000)
    shared = clip_weights(clips, cap_frames=30_000, bandai_share=0.5)
    assert np.isclose(shared[:2].sum(), 0.5) and np.isclose(shared[2:].sum(), 0.5)
    np.testing.assert_allclose(shared[:2] / shared[:2].sum(), w[:2] / w[:2].sum())  # within a side, as before
    assert np.isclose(clip_weights(clips[2:], cap_frames=30_000, bandai_share=0.5).sum(), 1.0)  # one side only


def test_a_run_evaluates_an_offline_model_in_the_chunks_the_service_runs_it_in() -> None:
    """The figures a run logs are the served model's: the network sees the served chunks (window 120, context 30
    here), stacked as the service stacks them, never the whole clip, and every frame's answer comes from the chunk
    the service takes it from."""
    import torch

    from service.inference.pose import chunk_plan
    from training.pose.config import PoseConfig, served_chunks
    from training.pose.train import torch_predictor

    seen = []

    class Net(torch.nn.Module):
        look_ahead = 0

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            seen.append(tuple(x.shape[:2]))
            chunk = torch.arange(x.shape[0], dtype=torch.float32).reshape(-1, 1, 1, 1, 1)
            return chunk.expand(x.shape[0], x.shape[1], 1, 3, 3)  # each chunk answers its index in the stack

    cfg = PoseConfig.model_validate({"name": "t", "train": {"sequence_frames": 120, "context_frames": 30}})
    assert served_chunks(cfg) == (120, 30)
    out = torch_predictor(Net(), served_chunks(cfg))(np.zeros((400, 4), dtype=np.float32))
    plan = chunk_plan(400, 120, 30)
    assert seen == [(len(plan), 120)]  # one call, every chunk the window long
    for k, (_, _, keep_from, keep_to) in enumerate(plan):
        assert np.all(out[keep_from:keep_to] == k)
    seen.clear()
    torch_predictor(Net(), served_chunks(cfg))(np.zeros((100, 4), dtype=np.float32))
    assert seen == [(1, 100)]  # a clip shorter than the window in one piece
    streaming = PoseConfig.model_validate({"name": "s", "model": {"kind": "lstm", "look_ahead": 5}})
    assert served_chunks(streaming) is None  # a live model runs over the whole recording, as the service runs it


def test_a_clip_s_digest_does_not_change_with_the_offsets_noise() -> None:
    """The digest names a clip in the motion cache and the registry's evaluation digest: noise-level entries of its
    rig's offsets (a negative zero, 1e-9) must not change it; a turn of 0.01° must."""
    from pathlib import Path

    from scipy.spatial.transform import Rotation

    from training.pose.data import _digest

    path = Path(__file__)
    offsets = np.stack([np.eye(3)] * 21)
    noisy = offsets.copy()
    noisy[:, 0, 2], noisy[:, 1, 2] = -1e-17, 3e-9
    assert _digest(path, offsets) == _digest(path, noisy)
    turned = offsets @ Rotation.from_euler("z", 0.01, degrees=True).as_matrix()
    assert _digest(path, offsets) != _digest(path, turned)


def test_the_position_term_is_the_forward_kinematics_of_the_answers_and_weighs_proximal_errors_more() -> None:
    """``forward_kinematics`` is ``segment_origins`` in torch; the term is 0 for the true answers, and the same
    10° error costs more on the thigh (it moves knee, ankle and toes) than on the foot (it moves the toe)."""
    import torch
    from scipy.spatial.transform import Rotation

    from service.core.body import BODY_SEGMENTS, segment_origins
    from training.pose.train import _position_loss, forward_kinematics

    rng = np.random.default_rng(0)
    S, T = len(BODY_SEGMENTS), 5
    R = Rotation.random(T * S, random_state=1).as_matrix().reshape(T, S, 3, 3)
    offsets = rng.normal(0.0, 0.2, (S, 3))
    got = forward_kinematics(torch.from_numpy(R[None]), torch.from_numpy(offsets[None]))[0].numpy()
    np.testing.assert_allclose(got, segment_origins(R, offsets), atol=1e-9)

    out = [k for k, s in enumerate(BODY_SEGMENTS) if s not in ("Pelvis", "Head", "LeftForeArm", "RightForeArm")]
    full = torch.from_numpy(R[None]).float()
    off, lengths = torch.from_numpy(offsets[None]).float(), torch.tensor([T])
    truth = full[:, :, out].clone()
    assert _position_loss(truth, full, off, out, lengths, 0).item() < 1e-10
    turn = torch.from_numpy(Rotation.from_euler("x", 10, degrees=True).as_matrix()).float()

    def cost(segment: str) -> float:
        pred = truth.clone()
        j = out.index(BODY_SEGMENTS.index(segment))
        pred[:, :, j] = pred[:, :, j] @ turn
        return _position_loss(pred, full, off, out, lengths, 0).item()

    assert cost("LeftUpperLeg") > cost("LeftFoot") > 0.0
    assert cost("LeftToe") == 0.0  # a leaf moves no joint: its rotation is the rotation loss's alone


def test_the_position_term_s_truth_is_shifted_with_the_targets() -> None:
    """With a look-ahead the output at frame t answers frame t - L: the whole body's truth (``_shifted``) must sit
    where ``_batch`` puts the targets, or the term would judge each answer against another frame."""
    import torch

    from service.core.body import BODY_SEGMENTS
    from training.pose.train import _batch, _shifted

    rng = np.random.default_rng(2)
    out = [3, 7, 12]
    full = [rng.normal(size=(n, len(BODY_SEGMENTS), 3, 3)).astype(np.float32) for n in (40, 40)]
    sessions = [SimpleNamespace(features=np.zeros((len(f), 4), np.float32), targets=f[:, out]) for f in full]
    for look_ahead in (0, 5):
        x, y, _ = _batch(sessions, look_ahead)
        shifted = _shifted(full, x.shape[1], look_ahead)
        assert torch.equal(shifted[:, :, out], y)
        assert torch.equal(shifted[:, look_ahead + 1, 0], torch.from_numpy(np.stack([f[1, 0] for f in full])))


def test_an_ensemble_answers_rotations_between_its_members_and_exports_as_one_graph(tmp_path) -> None:
    """``PoseEnsemble``: of two copies of one network it answers that network's rotations; of two networks it
    answers proper rotations that lie between theirs (nearer each than they are to each other), and its ONNX file
    gives torch's answer. ``train.ensemble_of`` takes two or more offline networks."""
    from pathlib import Path

    import pytest
    import torch

    from service.core.calibration import features_per_frame
    from training.pose.config import load_pose_config
    from training.pose.export import export_pose_onnx, golden_pair, onnx_parity
    from training.pose.models import PoseEnsemble
    from training.pose.train import build_net

    config = Path(__file__).resolve().parents[3] / "training/configs/pose_full6.yaml"
    cfg = load_pose_config(config, ["model.hidden=32", "train.ensemble_of=[a,b]"])
    F = features_per_frame(len(cfg.sensors))
    torch.manual_seed(0)
    a, b = build_net(cfg, F).eval(), build_net(cfg, F).eval()
    x = torch.randn(2, 40, F)
    with torch.no_grad():
        twin = PoseEnsemble([a, a]).eval()
        torch.testing.assert_close(twin(x), a(x), atol=1e-5, rtol=0)
        ens = PoseEnsemble([a, b]).eval()
        Ra, Rb, Re = a(x), b(x), ens(x)
    eye = torch.eye(3).expand_as(Re)
    torch.testing.assert_close(Re @ Re.transpose(-1, -2), eye, atol=1e-5, rtol=0)
    assert torch.allclose(torch.linalg.det(Re), torch.ones(Re.shape[:-2]), atol=1e-5)

    def angle(P: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
        cos = ((P.transpose(-1, -2) @ Q).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
        return torch.arccos(cos.clamp(-1, 1))

    apart = angle(Ra, Rb)
    assert float(apart.mean()) > 0.1  # two seeds answer differently
    assert (angle(Re, Ra) < apart + 1e-4).all() and (angle(Re, Rb) < apart + 1e-4).all()
    path = export_pose_onnx(ens, cfg, tmp_path / "model.onnx")
    golden = golden_pair(ens, x[0].numpy(), cfg)
    assert onnx_parity(path, golden, cfg, ens) < 1e-4
    with pytest.raises(ValueError, match="two or more offline"):
        load_pose_config(config, ["train.ensemble_of=[a]"])
    with pytest.raises(ValueError, match="two or more offline"):
        load_pose_config(config, ["train.ensemble_of=[a,b]", "model.kind=lstm"])


def test_the_mirror_image_of_features_and_answers(tmp_path) -> None:
    """``Mirror``: the features it makes of a motion are those of the mirror-image motion (left and right sensors
    swapped, every rotation M R M and vector M v, M = diag(1, −1, 1)); an ensemble with the mirror answers the mirror
    image of a motion with the mirror image of its answer, and exports as one graph. Sensors or outputs without
    their other side are refused."""
    from pathlib import Path

    import numpy as np
    import pytest
    import torch
    from scipy.spatial.transform import Rotation

    from service.core.body import other_side
    from service.core.calibration import features_per_frame, pose_features
    from training.pose.config import load_pose_config
    from training.pose.export import export_pose_onnx, golden_pair, onnx_parity
    from training.pose.models import Mirror, PoseEnsemble
    from training.pose.train import build_net

    config = Path(__file__).resolve().parents[3] / "training/configs/pose_full6.yaml"
    cfg = load_pose_config(config, ["model.hidden=32", "train.ensemble_of=[a]", "train.ensemble_mirror=true"])
    mirror = Mirror(cfg.sensors, cfg.outputs)
    T, N = 30, len(cfg.sensors)
    R = Rotation.random(T * N, random_state=3).as_matrix().reshape(T, N, 3, 3)
    acc = np.random.default_rng(3).normal(size=(T, N, 3))
    M = np.diag([1.0, -1.0, 1.0])
    swap = [cfg.sensors.index(other_side(s)) for s in cfg.sensors]
    assert swap != list(range(N))
    x = torch.from_numpy(pose_features(R, acc))
    x_mirror = torch.from_numpy(pose_features(M @ R[:, swap] @ M, acc[:, swap] @ M))
    torch.testing.assert_close(mirror.features(x), x_mirror, atol=1e-6, rtol=0)
    torch.testing.assert_close(mirror.features(mirror.features(x)), x)

    torch.manual_seed(0)
    net = build_net(cfg, features_per_frame(N)).eval()
    ens = PoseEnsemble([net], mirror).eval()
    with torch.no_grad():
        plain, answer, answer_mirror = net(x[None]), ens(x[None]), ens(x_mirror[None])
    torch.testing.assert_close(answer_mirror, mirror.answers(answer), atol=1e-5, rtol=0)
    assert float((answer - plain).abs().max()) > 1e-3  # an untrained network is not its own mirror image
    path = export_pose_onnx(ens, cfg, tmp_path / "model.onnx")
    assert onnx_parity(path, golden_pair(ens, x.numpy(), cfg), cfg, ens) < 1e-4

    with pytest.raises(ValueError, match="have none"):
        Mirror(["Pelvis", "LeftForeArm", "Head"], cfg.outputs)
    with pytest.raises(ValueError, match="name them"):
        load_pose_config(config, ["train.ensemble_mirror=true"])


def test_anchored_outputs_turn_with_the_sensed_segment_next_to_them(tmp_path) -> None:
    """``model.anchored``: a thigh and a foot answer relative to their shank, an upper arm and a hand to their forearm,
    the neck to the head, the rest to the pelvis; each answer is its anchor sensor's pelvis-relative rotation (read
    from the features) times the network's own, so turning a shank's reading turns its thigh's answer with it; the
    file exports with ONNX parity; a look-ahead model refuses it."""
    from pathlib import Path

    import numpy as np
    import pytest
    import torch
    from scipy.spatial.transform import Rotation

    from service.core.calibration import features_per_frame, pose_features
    from training.pose.config import load_pose_config
    from training.pose.export import export_pose_onnx, golden_pair, onnx_parity
    from training.pose.models import anchor_sensors
    from training.pose.train import build_net

    configs = Path(__file__).resolve().parents[3] / "training/configs"
    six = load_pose_config(configs / "pose_full6.yaml", ["model.hidden=32", "model.anchored=true"])
    named = {o: six.sensors[k] for o, k in zip(six.outputs, anchor_sensors(six.sensors, six.outputs), strict=True)}
    assert named["LeftUpperLeg"] == named["LeftFoot"] == "LeftLowerLeg" and named["Neck"] == "Head"
    assert (
        named["RightUpperArm"] == named["RightHand"] == "RightForeArm" and named["T8"] == named["LeftToe"] == "Pelvis"
    )

    cfg = load_pose_config(configs / "pose_lower3.yaml", ["model.hidden=32", "model.anchored=true"])
    torch.manual_seed(0)
    net = build_net(cfg, features_per_frame(len(cfg.sensors))).eval()
    T, N = 20, len(cfg.sensors)
    R = Rotation.random(T * N, random_state=5).as_matrix().reshape(T, N, 3, 3)
    acc = np.random.default_rng(5).normal(size=(T, N, 3))
    x = torch.from_numpy(pose_features(R, acc))[None]
    plain = build_net(cfg.model_copy(update={"model": cfg.model.model_copy(update={"anchored": False})}), x.shape[-1])
    plain.load_state_dict(net.state_dict())
    thigh = cfg.outputs.index("LeftUpperLeg")
    turn = Rotation.from_euler("y", 40, degrees=True).as_matrix()
    rel = np.einsum("tji,tnjk->tnik", R[:, 0], R)  # each sensor relative to the pelvis
    turned = x.clone()
    turned[0, :, 6:15] = torch.from_numpy((rel[:, 1] @ turn).reshape(T, 9))  # the left shank's 9 numbers
    with torch.no_grad():
        torch.testing.assert_close(net(x), net.anchor_rotations(x) @ plain.eval()(x), atol=1e-5, rtol=0)
        shank = net.anchor_rotations(turned)[0, :, thigh]
    torch.testing.assert_close(shank, torch.from_numpy(rel[:, 1] @ turn).float(), atol=1e-5, rtol=0)
    path = export_pose_onnx(net, cfg, tmp_path / "model.onnx")
    assert onnx_parity(path, golden_pair(net, x[0].numpy(), cfg), cfg, net) < 1e-4
    with pytest.raises(ValueError, match="not with look_ahead"):
        load_pose_config(configs / "pose_full6_stream.yaml", ["model.anchored=true"])


def test_the_best_epoch_s_weights_come_back_and_training_stops_after_its_patience_or_budget() -> None:
    import torch

    from training.pose.train import BestEpoch

    net = torch.nn.Linear(2, 1)
    keeper = BestEpoch(net, patience=2, time_budget_s=100.0)
    figures = [5.0, 3.0, 4.0, 3.5]
    reasons = []
    for epoch, val in enumerate(figures, start=1):
        with torch.no_grad():
            net.weight.fill_(float(epoch))
        reasons.append(keeper.record(epoch, val, elapsed_s=1.0))
    assert reasons == ["", "", "", "no validation gain for 2 epochs"]
    keeper.restore()
    assert keeper.best == 3.0 and keeper.best_epoch == 2 and float(net.weight[0, 0]) == 2.0 and not net.training
    late = BestEpoch(torch.nn.Linear(2, 1), patience=5, time_budget_s=10.0)
    assert late.record(1, 1.0, elapsed_s=5.0) == "" and late.record(2, 0.5, elapsed_s=11.0) == "time budget 10 s spent"
    warm = BestEpoch(torch.nn.Linear(2, 1), patience=1, best=2.0)  # a warm start's own figure to beat
    assert warm.record(1, 2.5, elapsed_s=0.0) == "no validation gain for 1 epochs" and warm.best_epoch == 0


def test_a_sequence_played_at_another_speed_and_size_keeps_its_length_and_scales_its_motion() -> None:
    """``train.speed`` / ``train.size``: a sequence of n frames covers about n · s frames of the clip, resampled to
    the model rate (the same path at s times the speed); the body scaled by b moves b times as far; (1, 1) draws
    nothing, so the plain draw is the crop it always was."""
    from scipy.spatial.transform import Rotation

    from service.core.body import BodyMotion
    from training.pose.data import MotionClip
    from training.pose.train import _crop, _drawn_sequence

    T, S = 400, 21
    t = np.arange(T) / 60.0
    R = np.broadcast_to(Rotation.from_rotvec(np.outer(np.sin(t), [0.0, 0.0, 1.0])).as_matrix()[:, None], (T, S, 3, 3))
    origin = np.zeros((T, S, 3))
    origin[..., 0] = 1.2 * t[:, None]  # walking along x at 1.2 m/s
    clip = MotionClip("c.bvh", "cmu_iclone", "cmu_01", "walk", BodyMotion(R.copy(), origin, origin + 0.1, 60.0), "d")
    plain, rng = _drawn_sequence(clip, 100, (1.0, 1.0), (1.0, 1.0), np.random.default_rng(3)), np.random.default_rng(3)
    start = int(rng.integers(0, T - 100 + 1))
    np.testing.assert_array_equal(plain.motion.origin_m, _crop(clip, start, start + 100).motion.origin_m)
    fast = _drawn_sequence(clip, 100, (1.5, 1.5), (1.0, 1.0), np.random.default_rng(0))
    assert fast.motion.n_frames == 100 and fast.motion.sample_rate_hz == 60.0
    step = np.diff(fast.motion.origin_m[:, 0, 0]) * 60.0
    np.testing.assert_allclose(step, 1.2 * 1.5, rtol=0.02)  # 1.8 m/s
    big = _drawn_sequence(clip, 100, (1.0, 1.0), (1.1, 1.1), np.random.default_rng(3))  # the start of `plain`
    np.testing.assert_allclose(np.diff(big.motion.origin_m[:, 0, 0]) * 60.0, 1.2 * 1.1, rtol=1e-9)
    np.testing.assert_array_equal(big.motion.R_world_segment, plain.motion.R_world_segment)
    short = _drawn_sequence(_crop(clip, 0, 120), 100, (1.5, 1.5), (1.0, 1.0), np.random.default_rng(0))
    assert short.motion.n_frames == 100  # as fast as the clip's length allows
