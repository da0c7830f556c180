"""Quaternion conventions of the project (docs/conventions.md): Hamilton, scalar first, unit, w >= 0.

All heavy lifting is scipy's ``Rotation`` with ``scalar_first=True`` said explicitly (two closed forms,
``matrix_from_quat`` and ``quat_from_matrix``, are on the service's per-window and per-frame paths and tested
against scipy).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

UNIT_QUAT_TOLERANCE = 0.1  # |q| within 1 ± this reads as a unit quaternion rounded or scaled, normalised; beyond, bad


def canonical_quat(q_wxyz: np.ndarray) -> np.ndarray:
    """Normalise quaternions ``(..., 4)`` (w, x, y, z) and fix the sign so that w >= 0.

    At w = 0 (180° rotations) q and -q both qualify; the first non-zero component decides, so the
    canonical form is unique.
    """
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    nonzero = np.abs(q) > 1e-12
    first = np.argmax(nonzero, axis=-1)[..., None]
    lead = np.take_along_axis(q, first, axis=-1)
    return np.where(lead < 0.0, -q, q)


def is_unit_quaternion(q_wxyz: np.ndarray | list[float]) -> bool:
    """One quaternion (w, x, y, z) that reads as a unit one: finite, norm within 1 ± ``UNIT_QUAT_TOLERANCE``."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return bool(np.isfinite(q).all() and abs(np.linalg.norm(q) - 1.0) <= UNIT_QUAT_TOLERANCE)


def repair_quaternions(q_wxyz: np.ndarray, tolerance: float = UNIT_QUAT_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """A series of orientations ``(T, 4)`` (w, x, y, z) as unit quaternions, and which rows were repaired ``(T,)``.

    Rows whose norm is within 1 ± ``tolerance`` are normalised; the others (and NaN or Inf rows) are taken by slerp
    between the nearest good rows before and after (held at the series' ends). A recorder's export can interpolate
    each component on its own across a sign flip of q (the capacitive study's left femur sensor: norms 0.01-1.45 in
    5-12 % of its rows), which passes near zero and turns the normalised row up to 40° off its neighbours.
    A series with no good row raises ValueError."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1)
    good = np.isfinite(norm) & (np.abs(norm - 1.0) <= tolerance)
    if not good.any():
        raise ValueError(f"no row of {len(q)} is a unit quaternion within 1 ± {tolerance:g} (norms {norm[:5]}…)")
    if good.all():
        return q / norm[:, None], ~good
    t = np.arange(len(q), dtype=np.float64)
    known = Rotation.from_quat(q[good], scalar_first=True)
    if good.sum() == 1:
        return np.repeat(known.as_quat(scalar_first=True), len(q), axis=0), ~good
    out = Slerp(t[good], known)(np.clip(t, t[good][0], t[good][-1])).as_quat(scalar_first=True)
    out[good] = q[good] / norm[good, None]  # the good rows exactly as given, only normalised
    return out, ~good


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` to canonical quaternions ``(..., 4)``.

    Markley (2008), "Unit quaternion from rotation matrix": of the four candidate quaternion columns (from the trace
    and from each diagonal element) the one with the largest norm is taken, so no division by a small number. A
    closed form in a few numpy calls (tested equal to scipy's ``Rotation``): the live pose converts 21 segments per
    frame, where scipy's ``from_matrix``, which orthogonalises every matrix by SVD, cost 1.4 ms per packet.
    """
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    d0, d1, d2 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    trace = d0 + d1 + d2
    choice = np.argmax(np.stack([d0, d1, d2, trace], axis=1), axis=1)
    q = np.empty((len(m), 4))  # x, y, z, w, as Markley's table
    i = choice < 3
    ii = choice[i]
    jj, kk = (ii + 1) % 3, (ii + 2) % 3
    rows = np.nonzero(i)[0]
    mi = m[i]
    q[rows, ii] = 1 - trace[i] + 2 * mi[np.arange(len(ii)), ii, ii]
    q[rows, jj] = mi[np.arange(len(ii)), jj, ii] + mi[np.arange(len(ii)), ii, jj]
    q[rows, kk] = mi[np.arange(len(ii)), kk, ii] + mi[np.arange(len(ii)), ii, kk]
    q[rows, 3] = mi[np.arange(len(ii)), kk, jj] - mi[np.arange(len(ii)), jj, kk]
    t = ~i
    mt = m[t]
    q[t, 0] = mt[:, 2, 1] - mt[:, 1, 2]
    q[t, 1] = mt[:, 0, 2] - mt[:, 2, 0]
    q[t, 2] = mt[:, 1, 0] - mt[:, 0, 1]
    q[t, 3] = 1 + trace[t]
    wxyz = np.ascontiguousarray(q[:, [3, 0, 1, 2]])  # fancy indexing may give another memory order
    return canonical_quat(wxyz.reshape(R.shape[:-2] + (4,)))


def _quadratic_forms() -> np.ndarray:
    """``A[i, j]`` with R_ij = qᵀ A_ij q / qᵀq for q = (w, x, y, z): the rotation matrix of any non-zero q."""
    terms = {
        (0, 0): [(0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)],
        (0, 1): [(1, 2, 2), (0, 3, -2)],
        (0, 2): [(1, 3, 2), (0, 2, 2)],
        (1, 0): [(1, 2, 2), (0, 3, 2)],
        (1, 1): [(0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)],
        (1, 2): [(2, 3, 2), (0, 1, -2)],
        (2, 0): [(1, 3, 2), (0, 2, -2)],
        (2, 1): [(2, 3, 2), (0, 1, 2)],
        (2, 2): [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)],
    }
    A = np.zeros((3, 3, 4, 4))
    for (i, j), entries in terms.items():
        for a, b, c in entries:
            A[i, j, a, b] = c
    return A


QUADRATIC_FORMS = _quadratic_forms()  # (3, 3, 4, 4); also the alignment graph's R(q) (training.i2s.models)


def matrix_from_quat(q_wxyz: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` (w, x, y, z) to rotation matrices ``(..., 3, 3)``.

    A closed form (tested equal to scipy's ``Rotation``) in three numpy calls: it is on the service's
    per-window path, where scipy's per-call overhead dominates for a few quaternions.
    """
    q = np.asarray(q_wxyz, dtype=np.float64)
    outer = q[..., :, None] * q[..., None, :]
    return np.tensordot(outer, QUADRATIC_FORMS, axes=([-2, -1], [2, 3])) / (q * q).sum(axis=-1)[..., None, None]


def stereographic_to_quat(p: np.ndarray) -> np.ndarray:
    """Inverse stereographic projection ``(..., 3)`` -> unit quaternion ``(..., 4)``.

    Zimmermann et al. 2018 §2.2.5 (ref. 56, Terzakis et al.): the projection from the pole (-1, 0, 0, 0) maps
    q = (w, v) to p = v / (1 + w); its inverse is q = ((1 - |p|^2), 2 p) / (1 + |p|^2).
    """
    p = np.asarray(p, dtype=np.float64)
    n2 = np.sum(p * p, axis=-1, keepdims=True)
    q = np.concatenate([1.0 - n2, 2.0 * p], axis=-1) / (1.0 + n2)
    return canonical_quat(q)


def quat_to_stereographic(q_wxyz: np.ndarray) -> np.ndarray:
    """Stereographic projection of canonical (w >= 0) quaternions: ``(..., 4)`` -> ``(..., 3)``."""
    q = canonical_quat(q_wxyz)
    return q[..., 1:] / (1.0 + q[..., :1])


def error_angles_xyz_deg(q_true: np.ndarray, q_pred: np.ndarray) -> np.ndarray:
    """Absolute error angles about the segment axes, Zimmermann et al. 2018 §3.3.

    The deviation q_true ⊗ q_pred⁻¹ is decomposed into Euler angles of order XYZ (intrinsic, about
    the segment frame's axes); returns ``(N, 3)`` absolute angles in degrees, each in [0, 180].
    """
    r_true = Rotation.from_quat(np.asarray(q_true).reshape(-1, 4), scalar_first=True)
    r_pred = Rotation.from_quat(np.asarray(q_pred).reshape(-1, 4), scalar_first=True)
    return np.abs((r_true * r_pred.inv()).as_euler("XYZ", degrees=True))


def geodesic_angle_deg(q_true: np.ndarray, q_pred: np.ndarray) -> np.ndarray:
    """Total rotation angle of q_true ⊗ q_pred⁻¹ in degrees, ``(N,)``."""
    r_true = Rotation.from_quat(np.asarray(q_true).reshape(-1, 4), scalar_first=True)
    r_pred = Rotation.from_quat(np.asarray(q_pred).reshape(-1, 4), scalar_first=True)
    return np.degrees((r_true * r_pred.inv()).magnitude())
