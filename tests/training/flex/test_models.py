"""The Table 5 networks: shapes, the median layer, the calibration module, and ONNX parity for each variant."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from training.flex.config import FlexModelConfig
from training.flex.export import export_flex_onnx
from training.flex.models import DynamicCalibration, FlexEnsemble, FlexNet, log_resistance, median3
from training.flex.simulate import DIVIDER_OHM, SensorParams, counts, draw_sensor, resistance_ohm

VARIANTS = [
    ("bilstm", False, False),
    ("transformer", False, False),
    ("fcn", False, False),
    ("tcn", False, False),
    ("bilstm", True, False),
    ("bilstm", False, True),
    ("bilstm", True, True),
]


def _net(
    kind: str, calibration: bool, median: bool, channels: int = 4, joints: int = 3, input_norm: str = "minmax"
) -> FlexNet:
    torch.manual_seed(0)
    cfg = FlexModelConfig(kind=kind, calibration=calibration, median=median, input_norm=input_norm)
    return FlexNet(
        cfg,
        channels,
        joints,
        3,
        torch.zeros(channels),
        torch.full((channels,), 4095.0),
        torch.zeros(joints * 3),
        torch.ones(joints * 3) * 20.0,
    ).eval()


def test_median3_is_the_median_of_each_step_and_its_neighbours() -> None:
    p = torch.randn(5, 7, 4)
    padded = torch.cat([p[:, :1], p, p[:, -1:]], dim=1)
    expected = torch.stack([padded[:, :-2], padded[:, 1:-1], padded[:, 2:]]).median(dim=0).values
    torch.testing.assert_close(median3(p), expected)


def test_the_calibration_module_pools_as_eq_2_and_keeps_the_window() -> None:
    cal = DynamicCalibration(100, 15, 10, 8)
    assert cal.linear.in_features == (100 - 15 + 1) + 16 - 10 + 1  # min pool, then average pool padded by 8
    assert cal(torch.rand(3, 100, 4)).shape == (3, 100, 4)
    y = torch.full((3, 100, 4), 0.5)
    # the baseline is built from the running minimum: a spike does not move it, a dip does
    spiky, dipped = y.clone(), y.clone()
    spiky[:, 50] += 5.0
    dipped[:, 50] -= 5.0
    torch.testing.assert_close(cal.baseline(spiky), cal.baseline(y))
    assert not torch.allclose(cal.baseline(dipped), cal.baseline(y))


def test_the_baseline_init_starts_the_calibration_as_a_subtraction_of_the_window_baseline() -> None:
    cal = DynamicCalibration(100, 15, 10, 8, init="baseline")
    y = torch.rand(3, 100, 4)
    with torch.no_grad():
        out, shifted = cal(y), cal(y + 0.7)
    torch.testing.assert_close(shifted, out)  # a drifted baseline (an offset of every reading) is taken out
    with torch.no_grad():  # a window that does not move reads zero
        torch.testing.assert_close(cal(torch.full((1, 100, 2), 0.4)), torch.zeros(1, 100, 2))


def _exact_sensor(**fixed: float) -> SensorParams:
    exact = {"noise_counts": 0.0, "amp_tol": 0.0, "divider_tol": 0.0, "baseline_rate_per_min": 0.0}
    return draw_sensor(np.random.default_rng(3), **(exact | fixed))


def test_log_resistance_reads_the_strip_back_through_eq_1_and_turns_ageing_into_an_offset() -> None:
    theta = np.abs(np.sin(np.linspace(0, 12, 100))) * 100.0  # bending and straightening, 5 s at 20 Hz
    rng = np.random.default_rng(0)
    new, aged = _exact_sensor(baseline0=0.0), _exact_sensor(baseline0=0.45)
    r_new = resistance_ohm(theta, new)
    c_new, c_aged = counts(r_new, new, rng), counts(resistance_ohm(theta, aged), aged, rng)
    back = np.exp(log_resistance(torch.from_numpy(c_new)).numpy()) * DIVIDER_OHM
    np.testing.assert_allclose(back, r_new, rtol=2e-3)  # within a count's quantisation
    shift = log_resistance(torch.from_numpy(c_aged)) - log_resistance(torch.from_numpy(c_new))
    # ageing multiplies R by 1.45: log R moves by log 1.45 at every angle, where the counts' step shrinks as the
    # strip bends (the divider's curve)
    np.testing.assert_allclose(shift.numpy(), np.log(1.45), atol=3e-3)
    step = c_aged - c_new
    assert step[theta < 5].mean() > 1.5 * step[theta > 90].mean()
    cal = DynamicCalibration(100, 15, 10, 8, init="baseline")
    with torch.no_grad():  # so the calibration module, started as a subtraction, takes the ageing out
        a = cal(log_resistance(torch.from_numpy(c_new)).view(1, 100, 1))
        b = cal(log_resistance(torch.from_numpy(c_aged)).view(1, 100, 1))
    torch.testing.assert_close(a, b, atol=4e-3, rtol=0)


@pytest.mark.parametrize(
    "kind, calibration, median, input_norm",
    [(*v, "minmax") for v in VARIANTS]
    + [("bilstm", True, True, "log_resistance"), ("bilstm", True, True, "window_standardised")],
)
def test_each_variant_answers_one_pose_per_window_and_exports_with_parity(
    kind, calibration, median, input_norm, tmp_path: Path
) -> None:
    net = _net(kind, calibration, median, input_norm=input_norm)
    x = torch.from_numpy(np.random.default_rng(0).uniform(500, 3500, size=(6, 100, 4)).astype(np.float32))
    with torch.no_grad():
        y = net(x)
        steps = net.steps_deg(x)
    assert y.shape == (6, 3, 3) and steps.shape == (6, 5, 9)
    assert net.latency_samples == (1 if median else 0)
    torch.testing.assert_close(y.reshape(6, 9), steps[:, net.answer_step])
    path = export_flex_onnx(net, tmp_path / "model.onnx")
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"counts": x.numpy()[:3]})[0]
    np.testing.assert_allclose(got, y.numpy()[:3], atol=1e-3)


def test_an_ensemble_answers_the_mean_of_its_members_and_exports_with_parity(tmp_path: Path) -> None:
    members = [_net("bilstm", True, True, input_norm="window_relative") for _ in range(3)]
    for k, m in enumerate(members[1:], start=1):  # other weights, as other seeds would give
        torch.manual_seed(k)
        for p in m.net.parameters():
            p.data.add_(0.05 * torch.randn_like(p))
    ensemble = FlexEnsemble(members).eval()
    x = torch.from_numpy(np.random.default_rng(0).uniform(500, 3500, size=(4, 100, 4)).astype(np.float32))
    with torch.no_grad():
        answers = [m(x) for m in members]
        y = ensemble(x)
    assert not torch.allclose(answers[0], answers[1])
    torch.testing.assert_close(y, (answers[0] + answers[1] + answers[2]) / 3)
    assert ensemble.latency_samples == 1 and ensemble.cfg == members[0].cfg
    path = export_flex_onnx(ensemble, tmp_path / "ensemble.onnx")
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"counts": x.numpy()})[0]
    np.testing.assert_allclose(got, y.numpy(), atol=1e-3)
    with pytest.raises(ValueError, match="one recipe"):
        FlexEnsemble([members[0], _net("bilstm", True, False, input_norm="window_relative")])
    with pytest.raises(ValueError, match="two or more"):
        FlexEnsemble(members[:1])


def test_the_linear_path_adds_a_linear_map_of_each_step_that_exports_with_parity(tmp_path: Path) -> None:
    """``model.linear_path``: with the network's own output held at zero, the answer is linear in the normalised
    readings of the last steps, so readings twice as far from the bounds' minimum answer twice as far."""
    torch.manual_seed(0)
    cfg = FlexModelConfig(kind="bilstm", bilstm_sizes=(8, 8, 8, 8, 8), linear_path=True)
    net = FlexNet(cfg, 4, 3, 3, torch.zeros(4), torch.full((4,), 4095.0), torch.zeros(9), torch.ones(9)).eval()
    x = torch.from_numpy(np.random.default_rng(2).uniform(500, 2000, size=(3, 100, 4)).astype(np.float32))
    with torch.no_grad():
        for p in net.net.out.parameters():
            p.zero_()
        net.linear_path.bias.zero_()
        one, two = net(x), net(2 * x)
    assert one.abs().min() > 0
    torch.testing.assert_close(two, 2 * one)
    path = export_flex_onnx(net, tmp_path / "linear.onnx")
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"counts": x.numpy()})[0]
    np.testing.assert_allclose(got, one.numpy(), atol=1e-4)
    assert _net("bilstm", False, False).linear_path is None


def test_only_the_last_steps_reach_the_network_without_calibration() -> None:
    """Without the calibration module the answer depends on the last ``steps`` samples only; with it, on the
    whole window (its baseline)."""
    x = torch.from_numpy(np.random.default_rng(1).uniform(500, 3500, size=(2, 100, 4)).astype(np.float32))
    earlier = x.clone()
    earlier[:, :50] = 100.0
    for calibration, same in ((False, True), (True, False)):
        net = _net("bilstm", calibration, False)
        with torch.no_grad():
            assert torch.allclose(net(x), net(earlier)) is same


@pytest.mark.parametrize("keep", ["best", "last"])
def test_training_keeps_the_best_validation_epoch_or_the_last(keep: str) -> None:
    from training.flex.config import FlexConfig
    from training.flex.data import FlexClip, window_set
    from training.flex.train import train_flex, validation_mae

    rng = np.random.default_rng(0)
    bend = np.abs(np.cumsum(rng.standard_normal((400, 4)), axis=0)).astype(np.float32)
    angles = np.repeat(bend[:, :1, None], 3, axis=2)[:, [0] * 12]  # 12 joints that follow the first sensor
    clip = FlexClip("c", "cmu_iclone", "g", "walk", angles.astype(np.float32), bend, 99)
    ws = window_set([clip], 1, 0, 100)
    cfg = FlexConfig(
        name="t",
        model={"kind": "fcn", "window": 100, "steps": 5},
        train={"max_epochs": 4, "windows_per_epoch": 64, "patience": 100, "keep": keep, "threads": 1},
    )
    result = train_flex(cfg, ws, ws)
    scores = [h["val_mae_deg"] for h in result.history]
    assert len(scores) == 4
    kept = int(np.argmin(scores)) if keep == "best" else 3
    assert result.best_epoch == kept
    assert validation_mae(result.net, ws) == pytest.approx(scores[kept], rel=1e-5)
    assert result.member_best_epochs == [result.best_epoch]


def test_members_train_from_consecutive_seeds_and_answer_as_their_mean() -> None:
    from training.flex.config import FlexConfig
    from training.flex.data import FlexClip, window_set
    from training.flex.train import train_flex

    rng = np.random.default_rng(0)
    bend = np.abs(np.cumsum(rng.standard_normal((400, 4)), axis=0)).astype(np.float32)
    angles = np.repeat(bend[:, :1, None], 3, axis=2)[:, [0] * 12]
    ws = window_set([FlexClip("c", "cmu_iclone", "g", "walk", angles.astype(np.float32), bend, 99)], 1, 0, 100)
    train = {"max_epochs": 3, "windows_per_epoch": 64, "patience": 100, "threads": 1}
    cfg = FlexConfig(name="t", seed=5, model={"kind": "fcn", "window": 100, "steps": 5}, train=train | {"members": 2})
    steps: list[int] = []
    result = train_flex(cfg, ws, ws, on_epoch=lambda step, row: steps.append(step))
    assert isinstance(result.net, FlexEnsemble) and len(result.net.members) == 2
    assert steps == list(range(6)) and [h["member"] for h in result.history] == [0, 0, 0, 1, 1, 1]
    assert len(result.member_best_epochs) == 2 and result.best_epoch == result.member_best_epochs[0]
    # each member is the network its seed trains alone
    for k, member in enumerate(result.net.members):
        alone = train_flex(
            cfg.model_copy(update={"seed": 5 + k, "train": cfg.train.model_copy(update={"members": 1})}), ws, ws
        )
        x, _ = ws.batch(np.zeros(4, int), ws.ends[:4], 1)
        with torch.no_grad():
            torch.testing.assert_close(member(torch.from_numpy(x)), alone.net(torch.from_numpy(x)))


def test_a_run_in_the_hinge_frames_scores_the_network_as_the_service_answers_it() -> None:
    """Its torch predictor (validation, epoch choice and every logged figure) holds the hinge frames' zeros at zero,
    as ``service.inference.flex.FlexModel`` answers the shipped file; in a rig's own frames, and for a capacitive
    sleeve, the network's answer as it is."""
    from service.core.flex import hinge_mask
    from service.core.joint_angles import JOINT_COMPONENTS
    from training.flex.config import CapacitiveConfig, FlexConfig
    from training.flex.train import answer_mask, torch_predictor

    model = {"kind": "fcn", "window": 100, "steps": 5}
    hinge = FlexConfig(name="t", model=model, data={"limb_twist": "hinge"})
    assert answer_mask(FlexConfig(name="t", model=model)) is None and answer_mask(CapacitiveConfig(name="c")) is None
    mask = answer_mask(hinge)
    np.testing.assert_array_equal(mask, hinge_mask(hinge.joints, JOINT_COMPONENTS))

    class Constant(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.ones(x.shape[0], len(hinge.joints), 3)

    x = np.zeros((2, 100, 4), np.float32)
    np.testing.assert_array_equal(torch_predictor(Constant(), mask)(x), np.broadcast_to(mask, (2, *mask.shape)))
    np.testing.assert_array_equal(torch_predictor(Constant())(x), np.ones((2, len(hinge.joints), 3)))


def test_channel_gain_swings_each_channel_about_its_window_mean_within_the_range() -> None:
    from training.flex.train import swing_about_mean

    rng = np.random.default_rng(0)
    x = rng.normal(1000.0, 20.0, size=(256, 100, 7)).astype(np.float32)
    y = swing_about_mean(x, 1.0, rng)
    np.testing.assert_allclose(y.mean(axis=1), x.mean(axis=1), rtol=1e-5)
    factor = (y - y.mean(axis=1, keepdims=True)).std(axis=1) / (x - x.mean(axis=1, keepdims=True)).std(axis=1)
    assert factor.min() >= 0.5 - 1e-3 and factor.max() <= 2.0 + 1e-3  # log-uniform in [1/2, 2]
    assert factor.min() < 0.6 and factor.max() > 1.8 and abs(np.log(factor).mean()) < 0.05
    assert not np.allclose(factor[:, 0], factor[:, 1])  # drawn per channel


def test_bending_further_keeps_a_proportional_channel_on_its_line_and_only_deepens_the_stride() -> None:
    from training.flex.train import bent_further

    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 4.0 * np.pi, 100)
    angle = (20.0 + 25.0 * np.sin(t[None] + rng.uniform(0, 6, size=(256, 1)))).astype(np.float32)[..., None]
    gain = np.array([3.0, -1.5, 0.2], np.float32)  # channels that rise, fall, barely move with flexion
    x = (500.0 + angle * gain).astype(np.float32)
    x2, y2 = bent_further(x, angle, 5, 0.5, rng)
    assert x2.shape == x.shape and y2.shape == (256, 5, 1)
    factor = (x2.max(axis=1) - x2.min(axis=1))[:, 1] / (x.max(axis=1) - x.min(axis=1))[:, 1]
    assert factor.min() >= 1.0 - 1e-4 and factor.max() <= 1.5 + 1e-4 and factor.max() > 1.4  # in [1, 1.5]
    # the least-flexed sample stays where it was; every reading stays on its channel's line through the new angles
    np.testing.assert_allclose(x2.min(axis=1)[:, 0], x.min(axis=1)[:, 0], rtol=1e-5)
    bent = angle.min(axis=1, keepdims=True) + factor[:, None, None] * (angle - angle.min(axis=1, keepdims=True))
    np.testing.assert_allclose(y2, bent[:, -5:], rtol=1e-4)
    np.testing.assert_allclose(x2[:, -5:], 500.0 + y2 * gain, rtol=1e-4)
    with pytest.raises(ValueError, match="one joint's flexion"):
        bent_further(x, np.repeat(angle, 2, axis=2), 5, 0.5, rng)
