"""The alignment network's in-graph geometry: matrix → quaternion, the canonical frame, and its equivariance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from scipy.spatial.transform import Rotation

from service.core.segments import SEGMENTS
from training.data.catalog import mocap_entries
from training.i2s.data.mocap import build_kinematics
from training.i2s.data.windows import Augmentation, WindowSampler
from training.i2s.export import export_onnx, golden_pair, onnx_parity
from training.i2s.models import (
    AlignmentNet,
    AssignmentNet,
    CanonicalFrame,
    FunctionalAxes,
    quat_from_matrix,
    rotate_imu,
)


def _moving_windows(n: int, seed: int = 0) -> torch.Tensor:
    """Windows with gravity, a dominant skewed rotation axis and noise (no degenerate, motionless windows)."""
    g = torch.Generator().manual_seed(seed)
    imu = torch.randn(n, 128, 6, generator=g) * torch.tensor([0.5, 0.5, 0.5, 0.2, 0.4, 0.1])
    imu[..., 2] += 9.81
    exponential = -torch.log1p(-torch.rand(n, 128, generator=g))  # Exp(1), drawn from the seeded generator
    imu[..., 4] += exponential * 2.0 - 2.0  # skewed flexion-like axis
    return imu


def test_quat_from_matrix_matches_scipy_including_half_turns() -> None:
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(300, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rotations = Rotation.concatenate(
        [
            Rotation.random(1000, random_state=1),
            Rotation.from_rotvec(axes * np.pi),  # w = 0: where a trace-only formula loses the signs
            Rotation.from_rotvec(axes * (np.pi - 1e-3)),
            Rotation.identity(1),
        ]
    )
    q = quat_from_matrix(torch.tensor(rotations.as_matrix(), dtype=torch.float32)).numpy()
    same = np.abs(np.sum(q * rotations.as_quat(scalar_first=True), axis=1))  # q and −q are one rotation
    assert np.all(same > 1.0 - 1e-6), same.min()


def test_canonical_frame_is_a_rotation_even_for_a_still_window() -> None:
    still = torch.zeros(2, 128, 6)
    still[..., 2] = 9.81
    for imu in (_moving_windows(32), still):
        R = CanonicalFrame()(imu)
        assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand_as(R), atol=1e-5)
        assert torch.allclose(torch.linalg.det(R), torch.ones(len(R)), atol=1e-5)
    # z_c is the mean specific force
    assert torch.allclose(CanonicalFrame()(still)[:, 2], torch.tensor([0.0, 0.0, 1.0]).expand(2, 3), atol=1e-6)


def test_canonical_frame_turns_with_the_sensor() -> None:
    """R_c(Q · imu) · Q = R_c(imu): the frame belongs to the motion, not to how the sensor is mounted.

    Exact in float64; in float32 the sums over 128 samples round differently once the readings are turned,
    which moves the frame by up to ~2e-4 (measured over 200 seeds), so float32 gets a 1e-3 bound.
    """
    imu = _moving_windows(64)
    Q = torch.tensor(Rotation.random(64, random_state=3).as_matrix(), dtype=torch.float64)
    for dtype, atol in ((torch.float64, 1e-9), (torch.float32, 1e-3)):
        x, q = imu.to(dtype), Q.to(dtype)
        R, R_turned = CanonicalFrame()(x), CanonicalFrame()(rotate_imu(x, q))
        torch.testing.assert_close(R_turned @ q, R, atol=atol, rtol=0)


def test_canonical_alignment_net_is_equivariant_and_exports() -> None:
    """Turning the sensor by Qᵀ turns every predicted R_segment_imu by Qᵀ, for any weights; ONNX agrees."""
    torch.manual_seed(0)
    net = AlignmentNet(hidden=16, channels=8, kernel=4, canonical=True).eval()
    imu = _moving_windows(16, seed=1)
    Q = torch.tensor(Rotation.random(16, random_state=4).as_matrix(), dtype=torch.float32)
    with torch.no_grad():
        q, q_turned = net(imu), net(rotate_imu(imu, Q))
    R = Rotation.from_quat(q.reshape(-1, 4).numpy(), scalar_first=True).as_matrix().reshape(16, 7, 3, 3)
    R_turned = Rotation.from_quat(q_turned.reshape(-1, 4).numpy(), scalar_first=True).as_matrix().reshape(16, 7, 3, 3)
    expected = R @ Q.transpose(1, 2).numpy()[:, None]
    np.testing.assert_allclose(R_turned, expected, atol=1e-3)  # float32 rounding: ≤ 1.3e-4 over 40 seeds
    # The plain (paper) net has no such property: the same check fails for it.
    plain = AlignmentNet(hidden=16, channels=8, kernel=4).eval()
    with torch.no_grad():
        P = Rotation.from_quat(plain(imu).reshape(-1, 4).numpy(), scalar_first=True).as_matrix().reshape(16, 7, 3, 3)
        P_turned = plain(rotate_imu(imu, Q)).reshape(-1, 4).numpy()
    assert not np.allclose(
        Rotation.from_quat(P_turned, scalar_first=True).as_matrix().reshape(16, 7, 3, 3),
        P @ Q.transpose(1, 2).numpy()[:, None],
        atol=1e-2,
    )


def test_canonical_assignment_net_does_not_depend_on_the_mounting() -> None:
    """With the canonical frame, class logits are the same however the sensor is turned (any weights)."""
    torch.manual_seed(0)
    imu = _moving_windows(16, seed=5)
    Q = torch.tensor(Rotation.random(16, random_state=6).as_matrix(), dtype=torch.float32)
    net = AssignmentNet(hidden=16, channels=8, kernel=4, canonical=True).eval()
    with torch.no_grad():
        torch.testing.assert_close(net(rotate_imu(imu, Q)), net(imu), atol=2e-4, rtol=0)
        plain = AssignmentNet(hidden=16, channels=8, kernel=4).eval()
        assert (plain(rotate_imu(imu, Q)) - plain(imu)).abs().max() > 1e-3  # 10x the canonical net's tolerance


def test_canonical_alignment_net_onnx_parity(tmp_path: Path) -> None:
    net = AlignmentNet(hidden=16, channels=8, kernel=4, canonical=True).eval()
    path = export_onnx(net, "alignment", tmp_path / "model.onnx")
    assert onnx_parity(path, golden_pair(net, _moving_windows(8, seed=2).numpy())) < 1e-4


@pytest.fixture(scope="module")
def walk_clips(data_dir: Path, kinematics_cache: Path):
    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"]
    return build_kinematics(data_dir, entries, kinematics_cache)


def test_leg_segments_sit_at_a_fixed_rotation_from_the_canonical_frame(walk_clips) -> None:
    """On sensors simulated from real walking mocap (eq. 8 grid alignments), R_segment_imu · R_cᵀ of a leg
    segment is one constant rotation to within a few degrees: what is left for the network to learn is small."""
    batch = WindowSampler(walk_clips, Augmentation(alignment="grid")).sample(np.random.default_rng(0), 2048)
    R_c = CanonicalFrame()(torch.from_numpy(batch.imu)).numpy()
    R_seg_imu = Rotation.from_quat(batch.q_segment_imu, scalar_first=True).as_matrix()
    residual = Rotation.from_matrix(R_seg_imu @ np.transpose(R_c, (0, 2, 1)))
    for name in ("LeftUpperLeg", "LeftLowerLeg", "RightUpperLeg", "RightLowerLeg"):
        r = residual[batch.segment == SEGMENTS.index(name)]
        centre = r.mean()
        for _ in range(3):  # robust centre: re-average the closer half
            d = (centre.inv() * r).magnitude()
            centre = r[d <= np.median(d)].mean()
        spread = np.degrees((centre.inv() * r).magnitude())
        assert np.median(spread) < 8.0, (name, np.median(spread))
        assert np.mean(spread > 30.0) < 0.05, (name, np.mean(spread > 30.0))


def _turned_about_z(q: np.ndarray, deg: np.ndarray) -> np.ndarray:
    """q_segment_imu with the segment frame turned about its own z: R_z(deg) · R(q), w ≥ 0."""
    r = Rotation.from_rotvec(np.radians(deg)[:, None] * [0.0, 0.0, 1.0]) * Rotation.from_quat(q, scalar_first=True)
    out = r.as_quat(scalar_first=True)
    return out * np.where(out[:, :1] < 0, -1.0, 1.0)


LEGS_AND_FEET = ("LeftFoot", "LeftLowerLeg", "LeftUpperLeg", "RightUpperLeg", "RightLowerLeg", "RightFoot")


def _random_hypotheses(n: int, seed: int) -> np.ndarray:
    q = Rotation.random(n * 7, random_state=seed).as_quat(scalar_first=True).reshape(n, 7, 4)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def _turn_about_own_z_deg(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Rotation vectors (degrees) of R_after · R_before⁻¹: (0, 0, ψ) for a turn about the frame's own z."""
    r = Rotation.from_quat(after, scalar_first=True) * Rotation.from_quat(before, scalar_first=True).inv()
    return np.degrees(r.as_rotvec())


def test_flexion_axis_turns_y_onto_the_windows_dominant_axis_and_keeps_z() -> None:
    """A leg hypothesis whose y is 20° off the window's rotation axis is turned about its z onto that axis; a
    still window, an axis more than 45° from y and an unnamed segment are left as the network gave them."""
    n, t = 6, np.linspace(0, 4 * np.pi, 128)
    q = _random_hypotheses(n, seed=3)
    k = SEGMENTS.index("LeftLowerLeg")
    R = Rotation.from_quat(q[:, k], scalar_first=True).as_matrix()  # rows: segment axes in sensor coordinates
    axis_deg = np.array([20.0, -20.0, 20.0, 60.0, 20.0, 20.0])  # 60°: further from y than the half of 90°
    axis_seg = np.stack([np.sin(np.radians(axis_deg)), np.cos(np.radians(axis_deg)), np.full(n, 0.1)], 1)
    axis_imu = np.einsum("nji,nj->ni", R, axis_seg)  # Rᵀ · axis
    rate = np.array([3.0, 3.0, 3.0, 3.0, 0.05, 3.0])  # window 4 is nearly still
    imu = np.zeros((n, 128, 6))
    imu[..., 2] = 9.81
    imu[..., 3:] = rate[:, None, None] * np.sin(t)[None, :, None] * axis_imu[:, None]
    imu[..., 3:] += 0.02 * np.random.default_rng(0).normal(size=(n, 128, 3))
    names = [s for s in LEGS_AND_FEET if s != "RightFoot"]
    with torch.no_grad():
        out = FunctionalAxes(names)(torch.tensor(q, dtype=torch.float32), torch.tensor(imu, dtype=torch.float32))
    turn = _turn_about_own_z_deg(q[:, k], out[:, k].numpy())
    np.testing.assert_allclose(turn[[0, 1, 2, 5], 2], [20.0, -20.0, 20.0, 20.0], atol=1.0)
    np.testing.assert_allclose(turn[[0, 1, 2, 5], :2], 0.0, atol=1e-3)  # about z only: z is kept
    np.testing.assert_allclose(out[[3, 4], k], q[[3, 4], k], atol=1e-6)  # axis > 45° off, or still: as given
    for unnamed in ("RightFoot", "Pelvis"):
        np.testing.assert_allclose(out[:, SEGMENTS.index(unnamed)], q[:, SEGMENTS.index(unnamed)], atol=1e-6)
    with pytest.raises(ValueError, match="Pelvic"):
        FunctionalAxes(["Pelvic"])


def test_pelvis_x_is_turned_onto_the_direction_of_travel_of_a_gait_like_window() -> None:
    """A pelvis that accelerates forwards once per step (0.55 s) and sideways once per stride, and tilts once
    per step and rolls once per stride: a hypothesis whose x is 20° off the forward axis is turned onto it;
    a still window and a window with no step rhythm are left alone."""
    n, t = 5, np.arange(128) / 60.0
    q = _random_hypotheses(n, seed=4)
    p = SEGMENTS.index("Pelvis")
    off = np.array([20.0, -20.0, 20.0, 0.0, 20.0])
    true = _turned_about_z(q[:, p], -off)  # the frame the motion below is expressed in
    step, stride = 2 * np.pi * t / 0.55, np.pi * t / 0.55
    seg = np.zeros((n, 128, 6))  # in the true pelvis frame: forward x, left y, up z
    seg[..., 0], seg[..., 1], seg[..., 2] = 1.5 * np.sin(step), 1.0 * np.sin(stride), 9.81 + 2.0 * np.cos(step)
    seg[..., 3], seg[..., 4], seg[..., 5] = 0.5 * np.sin(stride + 0.3), 0.3 * np.sin(step), 0.4 * np.cos(stride)
    seg[3, :, [0, 1, 3, 4, 5]] = 0.0  # window 3: standing still
    seg[3, :, 2] = 9.81
    seg[4, :, 2] = 9.81 + 2.0 * np.random.default_rng(1).normal(size=128)  # window 4: no step rhythm
    R_true = Rotation.from_quat(true, scalar_first=True).as_matrix()
    to_sensor = [np.einsum("nji,ntj->nti", R_true, seg[..., k : k + 3]) for k in (0, 3)]  # Rᵀ · v
    imu = np.concatenate(to_sensor, -1)
    with torch.no_grad():
        out = FunctionalAxes(["Pelvis"])(torch.tensor(q, dtype=torch.float32), torch.tensor(imu, dtype=torch.float32))
    turn = _turn_about_own_z_deg(q[:, p], out[:, p].numpy())
    np.testing.assert_allclose(turn[:3, 2], -off[:3], atol=1.0)
    np.testing.assert_allclose(turn[:3, :2], 0.0, atol=1e-3)
    np.testing.assert_allclose(out[3:, p], q[3:, p], atol=1e-6)
    others = [i for i in range(7) if i != p]
    np.testing.assert_allclose(out[:, others], q[:, others], atol=1e-6)


def test_functional_axes_recover_the_functional_frames_of_simulated_walking(walk_clips) -> None:
    """On sensors simulated from real walking mocap, the true alignment turned 10° or -10° about the segment z
    is turned back to within the clip-versus-window difference of the functional frames' axes."""
    batch = WindowSampler(walk_clips, Augmentation(alignment="grid")).sample(np.random.default_rng(1), 2048)
    off = np.where(np.arange(len(batch.segment)) % 2 == 0, 10.0, -10.0)
    q = np.repeat(_turned_about_z(batch.q_segment_imu.astype(np.float64), off)[:, None], 7, axis=1)
    with torch.no_grad():
        out = FunctionalAxes(SEGMENTS)(torch.tensor(q, dtype=torch.float32), torch.from_numpy(batch.imu)).numpy()
    picked = out[np.arange(len(out)), batch.segment]
    truth = Rotation.from_quat(batch.q_segment_imu, scalar_first=True)
    before = np.abs((truth * Rotation.from_quat(q[:, 0], scalar_first=True).inv()).as_euler("XYZ", degrees=True))
    after = np.abs((truth * Rotation.from_quat(picked, scalar_first=True).inv()).as_euler("XYZ", degrees=True))
    for name, bound in [(n, 1.5) for n in LEGS_AND_FEET] + [("Pelvis", 4.0)]:  # measured: ≤ 0.94°, 2.7°
        m = batch.segment == SEGMENTS.index(name)
        assert np.median(before[m, 2]) > 9.0
        assert np.median(after[m, 2]) < bound, (name, np.median(after[m, 2]))


def test_the_pelvis_is_turned_round_where_its_walk_says_it_faces_backwards(walk_clips) -> None:
    """On pelvis sensors simulated from real walking mocap, a hypothesis turned by a half turn about z is turned
    back (the forward acceleration leads the vertical one) and the true frame is left as it is; a window with no
    step rhythm is never turned round."""
    batch = WindowSampler(walk_clips, Augmentation(alignment="grid")).sample(np.random.default_rng(1), 2048)
    p = SEGMENTS.index("Pelvis")
    keep = (batch.segment == p) & (np.linalg.norm(batch.imu[..., 3:], axis=-1).mean(-1) > 0.35)
    q_true = batch.q_segment_imu[keep].astype(np.float64)
    imu = torch.from_numpy(batch.imu[keep])
    truth = Rotation.from_quat(q_true, scalar_first=True)
    backwards = (Rotation.from_rotvec([0.0, 0.0, np.pi]) * truth).as_quat(scalar_first=True)
    axes = FunctionalAxes(["Pelvis"], pelvis_half_turn=0.3)

    def wrong(q: np.ndarray, windows: torch.Tensor = imu) -> np.ndarray:
        hypotheses = torch.tensor(np.repeat(q[:, None], 7, axis=1), dtype=torch.float32)
        with torch.no_grad():
            out = axes(hypotheses, windows)[:, p].numpy()
        return np.degrees((truth * Rotation.from_quat(out, scalar_first=True).inv()).magnitude()) > 90.0

    assert keep.sum() > 100
    assert wrong(q_true).mean() <= 0.02  # measured: 0 of 630 on cmu_07
    assert wrong(backwards).mean() <= 0.1  # measured: 2.2 %
    noise = torch.randn_like(imu) * torch.tensor([1.0, 1.0, 2.0, 0.3, 0.3, 0.3])
    noise[..., 2] += 9.81
    assert not wrong(q_true, noise).any()
    with pytest.raises(ValueError, match="Pelvis"):
        FunctionalAxes(["LeftFoot"], pelvis_half_turn=0.3)


def test_lagged_products_of_all_lags_at_once_equal_one_slice_per_lag() -> None:
    """The step search's lagged products (one shifting convolution for every lag) are the per-lag means they
    replace, for two signals and for one signal with itself."""
    from training.i2s.models import FunctionalAxes, _lagged

    a, b = torch.randn(21, 128, dtype=torch.float64), torch.randn(21, 128, dtype=torch.float64)
    for k_index, k in enumerate(FunctionalAxes.STEP_LAGS):
        expected = 0.5 * (a[..., :-k] * b[..., k:] + b[..., :-k] * a[..., k:]).mean(-1)
        torch.testing.assert_close(_lagged(a, b, FunctionalAxes.STEP_LAGS)[..., k_index], expected)
        itself = (a[..., :-k] * a[..., k:]).mean(-1)
        torch.testing.assert_close(_lagged(a, a, FunctionalAxes.STEP_LAGS)[..., k_index], itself)


def test_the_lagged_products_train_after_an_inference_call() -> None:
    """The shifting kernels are cached: a first call under ``torch.inference_mode`` (evaluation) must not leave a
    tensor behind that a later training step cannot use for its gradients."""
    from training.i2s.models import _lagged

    lags = (3, 4, 5)  # lags of no other test, so the cache starts empty here
    with torch.inference_mode():
        _lagged(torch.randn(2, 32), torch.randn(2, 32), lags)
    a = torch.randn(2, 32, requires_grad=True)
    _lagged(a, a, lags).sum().backward()
    assert a.grad is not None and a.grad.abs().sum() > 0


def test_the_step_lags_products_at_one_lag_per_window_are_that_lags_column() -> None:
    """The pelvis contrasts read the lagged products at each window's step lag only (one gather for all the
    signals); their symmetric part equals that lag's column of the all-lags products, whichever lag each window
    picks."""
    from training.i2s.models import FunctionalAxes, _lagged, _lagged_matrix_at

    x = torch.randn(5, 2, 2, 128, dtype=torch.float64)  # two groups of two signals per window
    lags = FunctionalAxes.STEP_LAGS
    assert lags == tuple(range(lags[0], lags[0] + len(lags)))  # the step is argmax + the first lag
    pick = torch.tensor([0, 3, 17, 29, len(lags) - 1])
    S = _lagged_matrix_at(x, pick + lags[0])
    for g in range(2):
        for i in range(2):
            for j in range(2):
                expected = _lagged(x[:, g, i], x[:, g, j], lags)[torch.arange(5), pick]
                torch.testing.assert_close(0.5 * (S[:, g, i, j] + S[:, g, j, i]), expected)


def test_quaternion_and_vector_products_by_tables_match_scipy() -> None:
    """The geometry's products written as constant tables: the Hamilton product composes rotations, R(q) is the
    rotation matrix, and the cross product is torch's."""
    from training.i2s.models import _cross, quat_multiply, rotation_matrix

    r1, r2 = Rotation.random(200, random_state=1), Rotation.random(200, random_state=2)
    q1, q2 = (torch.tensor(r.as_quat(scalar_first=True)) for r in (r1, r2))
    torch.testing.assert_close(rotation_matrix(q1), torch.tensor(r1.as_matrix()))
    torch.testing.assert_close(rotation_matrix(quat_multiply(q1, q2)), torch.tensor((r1 * r2).as_matrix()))
    a, b = torch.randn(50, 3, dtype=torch.float64), torch.randn(50, 3, dtype=torch.float64)
    torch.testing.assert_close(_cross(a, b), torch.linalg.cross(a, b))


def test_the_alignment_geometry_exports_as_few_nodes(tmp_path: Path) -> None:
    """onnxruntime pays for each small node about as much as for its arithmetic, so the canonical frame, the
    quaternions and the functional axes around the network are written as few, larger operations: about 350
    nodes beside the network (the graph that wrote them out term by term had about 710)."""
    net = AlignmentNet(canonical=True, functional_axes=SEGMENTS, pelvis_half_turn=0.3).eval()
    path = export_onnx(net, "alignment", tmp_path / "model.onnx")
    network = ("/cnn/", "/rnn/", "/head/")
    geometry = [
        n for n in onnx.load(str(path)).graph.node if n.op_type != "Constant" and not n.name.startswith(network)
    ]
    assert len(geometry) <= 400


def test_the_lstm_can_take_pooled_steps_with_the_same_weights(tmp_path: Path) -> None:
    """rnn_stride averages the CNN features over runs of samples before the LSTM: the weights keep their shapes
    (a stride-1 network warm-starts it), the output does change, and the graph exports with parity."""
    kwargs = dict(hidden=16, channels=8, kernel=4, canonical=True, functional_axes=SEGMENTS)
    torch.manual_seed(1)  # random weights: small networks answer nearly alike, so the weights are fixed
    plain, pooled = AlignmentNet(**kwargs).eval(), AlignmentNet(**kwargs, rnn_stride=4).eval()
    pooled.load_state_dict(plain.state_dict())
    imu = _moving_windows(8, seed=5)
    with torch.no_grad():
        q_plain, q_pooled = plain(imu), pooled(imu)
    assert q_pooled.shape == q_plain.shape == (8, len(SEGMENTS), 4)
    torch.testing.assert_close(q_pooled.norm(dim=-1), torch.ones(8, len(SEGMENTS)))
    assert (q_pooled - q_plain).abs().max() > 1e-3
    path = export_onnx(pooled, "alignment", tmp_path / "model.onnx")
    assert onnx_parity(path, golden_pair(pooled, imu.numpy())) < 1e-4
    with pytest.raises(ValueError, match="rnn_stride must be"):
        AlignmentNet(rnn_stride=0)


@pytest.mark.parametrize("half_turn", [None, 0.3])
def test_functional_axes_alignment_net_onnx_parity(tmp_path: Path, half_turn: float | None) -> None:
    net = AlignmentNet(
        hidden=16, channels=8, kernel=4, canonical=True, functional_axes=SEGMENTS, pelvis_half_turn=half_turn
    ).eval()
    path = export_onnx(net, "alignment", tmp_path / "model.onnx")
    assert onnx_parity(path, golden_pair(net, _moving_windows(8, seed=3).numpy())) < 1e-4


def test_the_papers_stereographic_loss_is_refused_with_a_canonical_frame() -> None:
    from pydantic import ValidationError

    from training.i2s.config import load_config

    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_alignment.yaml"
    with pytest.raises(ValidationError, match="needs canonical_frame false"):
        load_config(config, ["train.alignment_loss=stereographic_l2"])
    assert load_config(config, ["train.alignment_loss=stereographic_l2", "train.canonical_frame=false"])


def test_quarter_turns_are_exact_sensor_rotations_and_the_average_is_invariant(tmp_path: Path) -> None:
    """_quarter_turn(k) is the reading of a sensor turned k · 90° about its z; averaging over the four makes the
    class probabilities invariant to those turns for any weights (the plain net is not), and it exports."""
    from training.i2s.models import _quarter_turn

    imu = _moving_windows(8, seed=7)
    for k in range(4):
        R = torch.tensor(Rotation.from_euler("z", 90.0 * k, degrees=True).as_matrix().T, dtype=torch.float32)
        torch.testing.assert_close(_quarter_turn(imu, k), rotate_imu(imu, R.expand(8, 3, 3)), atol=1e-5, rtol=0)
    torch.manual_seed(0)
    averaged = AssignmentNet(hidden=16, channels=8, kernel=4, quarter_turns=True).eval()
    plain = AssignmentNet(hidden=16, channels=8, kernel=4).eval()
    plain.load_state_dict(averaged.state_dict())  # same weights, same keys
    with torch.no_grad():
        probs = torch.softmax(averaged(imu), -1)
        torch.testing.assert_close(probs.sum(-1), torch.ones(8))
        mean_of_plain = torch.stack([torch.softmax(plain(_quarter_turn(imu, k)), -1) for k in range(4)]).mean(0)
        torch.testing.assert_close(probs, mean_of_plain, atol=1e-5, rtol=0)
        for k in (1, 2, 3):
            torch.testing.assert_close(torch.softmax(averaged(_quarter_turn(imu, k)), -1), probs, atol=1e-5, rtol=0)
        assert not torch.allclose(torch.softmax(plain(_quarter_turn(imu, 1)), -1), torch.softmax(plain(imu), -1))
    onnx_path = export_onnx(averaged, "assignment", tmp_path / "model.onnx")
    assert onnx_parity(onnx_path, golden_pair(averaged, imu.numpy())) < 1e-4
    # the manifest's output shape [batch, 7] must hold in the graph, or the service refuses the model
    import onnx

    dims = onnx.load(str(onnx_path)).graph.output[0].type.tensor_type.shape.dim
    assert [d.dim_value or d.dim_param for d in dims][1] == len(SEGMENTS)


def test_gravity_turns_rotate_about_the_mean_specific_force_and_the_average_is_invariant(tmp_path: Path) -> None:
    """turned_about_gravity(n)[j] is the window rotated by j · 360°/n about its own mean specific force (which it
    leaves fixed); with the quarter turns too, the average over all 4n passes is invariant to either kind of
    turn, for any weights (the plain net is not), and it exports with the class dimension fixed."""
    from training.i2s.models import _quarter_turn, turned_about_gravity

    imu = _moving_windows(8, seed=3)
    axis = imu[..., :3].mean(1).numpy()
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    views = turned_about_gravity(imu, 3)
    torch.testing.assert_close(views[0], imu)
    for j, view in enumerate(views):
        R = Rotation.from_rotvec(axis * np.radians(120.0 * j)).as_matrix()
        torch.testing.assert_close(view, rotate_imu(imu, torch.tensor(R, dtype=torch.float32)), atol=1e-4, rtol=0)
        torch.testing.assert_close(view[..., :3].mean(1), imu[..., :3].mean(1), atol=1e-4, rtol=0)
    torch.manual_seed(0)
    averaged = AssignmentNet(hidden=16, channels=8, kernel=4, quarter_turns=True, gravity_turns=3).eval()
    plain = AssignmentNet(hidden=16, channels=8, kernel=4).eval()
    plain.load_state_dict(averaged.state_dict())
    with torch.no_grad():
        probs = torch.softmax(averaged(imu), -1)
        torch.testing.assert_close(probs.sum(-1), torch.ones(8))
        for turned in (views[1], views[2], _quarter_turn(imu, 1), _quarter_turn(views[1], 3)):
            torch.testing.assert_close(averaged(turned), averaged(imu), atol=2e-6, rtol=0)  # log-probabilities
        assert float((plain(views[1]) - plain(imu)).abs().max()) > 1e-4  # the plain net's logits do move
    onnx_path = export_onnx(averaged, "assignment", tmp_path / "model.onnx")
    assert onnx_parity(onnx_path, golden_pair(averaged, imu.numpy())) < 1e-4
    import onnx

    dims = onnx.load(str(onnx_path)).graph.output[0].type.tensor_type.shape.dim
    assert [d.dim_value or d.dim_param for d in dims][1] == len(SEGMENTS)
    with pytest.raises(ValueError, match="at least 1"):
        AssignmentNet(gravity_turns=0)


def test_gravity_turn_segments_mix_the_two_averages_per_class(tmp_path: Path) -> None:
    """With gravity_turn_segments the named classes take the 4n-pass average and the others the window's own
    quarter turns, renormalised; the mixture stays exactly invariant to the quarter turns, the leg classes keep
    their invariance to the turns about gravity, and the graph exports with the class dimension fixed."""
    from training.i2s.models import _quarter_turn, turned_about_gravity

    legs = ["LeftLowerLeg", "LeftUpperLeg", "RightUpperLeg", "RightLowerLeg"]
    is_leg = torch.tensor([s in legs for s in SEGMENTS])
    imu = _moving_windows(8, seed=5)
    torch.manual_seed(1)
    mixed = AssignmentNet(
        hidden=16, channels=8, kernel=4, quarter_turns=True, gravity_turns=4, gravity_turn_segments=legs
    )
    full = AssignmentNet(hidden=16, channels=8, kernel=4, quarter_turns=True, gravity_turns=4)
    quarter = AssignmentNet(hidden=16, channels=8, kernel=4, quarter_turns=True)
    with torch.no_grad():
        mixed.head.weight.mul_(50.0)  # an untrained net is near uniform; make the passes disagree
    full.load_state_dict(mixed.state_dict())
    quarter.load_state_dict(mixed.state_dict())
    for net in (mixed, full, quarter):
        net.eval()
    with torch.no_grad():
        expected = torch.where(is_leg, full(imu).exp(), quarter(imu).exp())
        expected = expected / expected.sum(-1, keepdim=True)
        torch.testing.assert_close(mixed(imu).exp(), expected, atol=1e-6, rtol=0)
        assert (
            float((mixed(imu) - full(imu)).abs().max()) > 1e-4 and float((mixed(imu) - quarter(imu)).abs().max()) > 1e-4
        )
        torch.testing.assert_close(mixed(_quarter_turn(imu, 1)), mixed(imu), atol=2e-6, rtol=0)
        # the leg classes' unnormalised evidence (the 16-pass mean) does not move with a turn about gravity
        turned = turned_about_gravity(imu, 4)[1]
        torch.testing.assert_close(full(turned)[:, is_leg], full(imu)[:, is_leg], atol=2e-6, rtol=0)
    onnx_path = export_onnx(mixed, "assignment", tmp_path / "model.onnx")
    assert onnx_parity(onnx_path, golden_pair(mixed, imu.numpy())) < 1e-4
    import onnx

    dims = onnx.load(str(onnx_path)).graph.output[0].type.tensor_type.shape.dim
    assert [d.dim_value or d.dim_param for d in dims][1] == len(SEGMENTS)
    for bad in ({"gravity_turns": 1}, {"gravity_turns": 4, "gravity_turn_segments": ["Head"]}):
        with pytest.raises(ValueError, match="gravity_turn_segments"):
            AssignmentNet(**{"gravity_turn_segments": legs, **bad})


def test_quarter_turns_and_the_canonical_frame_are_refused_together() -> None:
    from pydantic import ValidationError

    from training.i2s.config import load_config

    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_assignment.yaml"
    with pytest.raises(ValidationError, match="quarter_turns"):
        load_config(config, ["train.quarter_turns=true", "train.canonical_frame=true"])
    with pytest.raises(ValidationError, match="gravity_turns"):
        load_config(config, ["train.gravity_turns=4", "train.canonical_frame=true"])
    for overrides in (
        ["train.gravity_turn_segments=[LeftFoot]"],
        ["train.gravity_turns=4", "train.gravity_turn_segments=[Hip]"],
    ):
        with pytest.raises(ValidationError, match="gravity_turn_segments"):
            load_config(config, ["train.quarter_turns=true", *overrides])
    assert load_config(config, ["train.quarter_turns=true"]).train.quarter_turns


def test_rnn_stride_is_refused_for_the_assignment_network() -> None:
    from training.i2s.config import load_config
    from training.i2s.train import build_model

    config = Path(__file__).resolve().parents[3] / "training/configs/i2s_assignment.yaml"
    with pytest.raises(ValueError, match="rnn_stride pools the alignment"):
        build_model(load_config(config, ["train.rnn_stride=2"]))
