import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from service.core.rotations import (
    canonical_quat,
    error_angles_xyz_deg,
    geodesic_angle_deg,
    matrix_from_quat,
    quat_from_matrix,
    quat_to_stereographic,
    stereographic_to_quat,
)


def _assert_same_canonical(got: np.ndarray, want: np.ndarray) -> None:
    """Equal quaternions; within rounding of the w = 0 tie either sign of the same rotation may come back."""
    if abs(want[0]) < 1e-9:
        assert np.allclose(got, want, atol=1e-9) or np.allclose(got, -want, atol=1e-9), (got, want)
    else:
        np.testing.assert_allclose(got, want, atol=1e-9)


unit = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1)


@given(unit)
@settings(max_examples=200)
def test_stereographic_round_trip(v: list[float]) -> None:
    q = canonical_quat(np.array(v))
    _assert_same_canonical(stereographic_to_quat(quat_to_stereographic(q)), q)


@given(unit)
def test_matrix_round_trip_keeps_w_nonnegative(v: list[float]) -> None:
    q = canonical_quat(np.array(v))
    back = quat_from_matrix(matrix_from_quat(q))
    assert back[0] >= -1e-12  # w = 0 (180°) ties are broken by the next component
    _assert_same_canonical(back, q)


@given(unit)
def test_matrix_closed_form_equals_scipy(v: list[float]) -> None:
    q = np.array(v) * 3.0  # not normalised on purpose
    expected = Rotation.from_quat(q, scalar_first=True).as_matrix()
    np.testing.assert_allclose(matrix_from_quat(q), expected, atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat(np.stack([q, -q])[None]), np.stack([expected] * 2)[None], atol=1e-12)


def test_quat_from_matrix_equals_scipy_for_every_branch() -> None:
    rng = np.random.default_rng(0)
    R = Rotation.random(501, random_state=1).as_matrix()
    half_turns = Rotation.from_rotvec(np.pi * np.eye(3)).as_matrix()  # the trace branch cannot take these
    axes = rng.normal(size=(3, 3))
    near_half = Rotation.from_rotvec((np.pi - 1e-4) * axes / np.linalg.norm(axes, axis=1, keepdims=True)).as_matrix()
    R = np.concatenate([R, half_turns, near_half, np.eye(3)[None]]).reshape(-1, 2, 3, 3)  # batch shape (., 2)
    expected = canonical_quat(Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(scalar_first=True))
    np.testing.assert_allclose(quat_from_matrix(R).reshape(-1, 4), expected, atol=1e-12)
    noisy = (R + rng.normal(scale=1e-7, size=R.shape)).astype(np.float32)  # a network's float32 output
    q = quat_from_matrix(noisy).reshape(-1, 4)
    assert np.abs(np.abs(np.sum(q * expected, axis=1)) - 1).max() < 1e-6


def test_stereographic_of_identity_is_zero() -> None:
    np.testing.assert_allclose(quat_to_stereographic(np.array([1.0, 0, 0, 0])), 0.0)


def test_error_angles_about_single_axis() -> None:
    q_true = Rotation.from_euler("z", 30, degrees=True).as_quat(scalar_first=True)
    q_pred = np.array([1.0, 0, 0, 0])
    np.testing.assert_allclose(error_angles_xyz_deg(q_true, q_pred), [[0, 0, 30]], atol=1e-9)
    np.testing.assert_allclose(geodesic_angle_deg(q_true, -q_true), [0.0], atol=1e-6)


def test_rows_interpolated_across_a_sign_flip_are_repaired_from_their_neighbours() -> None:
    """A turn at 180°/s sampled at 100 Hz whose export flipped the sign of q halfway and interpolated each
    component on its own across the flip (as the capacitive study's left femur file): the rows whose norm is off
    by more than the tolerance are taken by slerp from the good rows around them and land within a degree of the
    true turn, where normalising them alone leaves them up to tens of degrees off; good rows are kept as given."""
    from service.core.rotations import UNIT_QUAT_TOLERANCE, repair_quaternions

    t = np.arange(200) / 100.0
    truth = Rotation.from_rotvec(np.radians(180.0) * t[:, None] * np.array([0.0, 0.6, 0.8]))
    q = truth.as_quat(scalar_first=True)
    q[100:] *= -1.0  # the export's sign flip: the same rotations
    bad = np.arange(95, 105)
    w = (bad - 94) / 11.0
    q[bad] = (1 - w)[:, None] * q[94] + w[:, None] * q[105]  # component-wise across the flip: norms near zero
    q[150] = np.nan  # a dropped row
    q[20] *= 1.05  # a row scaled within the tolerance: kept, normalised
    off = np.abs(np.linalg.norm(q, axis=1) - 1.0)
    assert np.nanmax(off[bad]) > 0.5  # the corruption is real

    fixed, repaired = repair_quaternions(q)
    assert set(np.flatnonzero(repaired)) == {*bad[off[bad] > UNIT_QUAT_TOLERANCE], 150}
    np.testing.assert_allclose(np.linalg.norm(fixed, axis=1), 1.0, atol=1e-12)
    error = np.degrees((truth.inv() * Rotation.from_quat(fixed, scalar_first=True)).magnitude())
    assert error.max() < 1.0, error.max()
    plain = Rotation.from_quat(np.nan_to_num(q[bad]), scalar_first=True)  # normalising only
    assert np.degrees((truth[bad].inv() * plain).magnitude()).max() > 10.0
    np.testing.assert_allclose(fixed[20], q[20] / np.linalg.norm(q[20]))
    np.testing.assert_allclose(fixed[:19], q[:19], atol=1e-15)  # unit rows as given

    with pytest.raises(ValueError, match="no row"):
        repair_quaternions(np.zeros((5, 4)))
