"""The networks of Zimmermann et al. 2018 §2.2 and Table A1: a shared CNN front end, a GRU for assignment and a
2-layer LSTM for alignment, plus our optional ``CanonicalFrame`` in front of either (not in the paper; README
"Canonical frame"). Only the models live here; training is in ``training.i2s.train``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import nn

from service.core.rotations import QUADRATIC_FORMS
from service.core.segments import SEGMENTS
from service.core.units import GRAVITY_MPS2

GYRO_SCALE_RADS = 3.14159


class InputScale(nn.Module):
    """Fixed per-channel scaling (acc / g, gyr / π rad/s), part of the exported graph (docs/conventions.md)."""

    def __init__(self) -> None:
        super().__init__()
        scale = torch.tensor([1 / GRAVITY_MPS2] * 3 + [1 / GYRO_SCALE_RADS] * 3)
        self.register_buffer("scale", scale)

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        return imu * self.scale


class ConvFrontEnd(nn.Module):
    """3 × (Conv1d 64 kernels of 16, batch norm, ReLU), eq. 2–3; ``(B, T, 6)`` → ``(B, T, 64)``."""

    def __init__(self, channels: int = 64, kernel: int = 16, layers: int = 3, keep_prob: float = 0.8) -> None:
        super().__init__()
        self.input_dropout = nn.Dropout(1.0 - keep_prob)  # §2.2.4: input dropout, keep probability 0.8
        blocks: list[nn.Module] = []
        in_ch = 6
        for _ in range(layers):
            blocks += [nn.Conv1d(in_ch, channels, kernel, padding="same"), nn.BatchNorm1d(channels), nn.ReLU()]
            in_ch = channels
        self.net = nn.Sequential(*blocks)

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        x = self.input_dropout(imu).transpose(1, 2)
        return self.net(x).transpose(1, 2)


def _unit(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return v / torch.sqrt((v * v).sum(-1, keepdim=True) + eps)


def _hamilton_terms(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b of quaternions (w, x, y, z), written out: the definition ``_HAMILTON`` is read from."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def _cross_terms(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a × b, written out: the definition ``_LEVI_CIVITA`` is read from."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


def _shepperd_terms(R: torch.Tensor) -> torch.Tensor:
    """4 q qᵀ of the unit quaternion q of a rotation matrix R, which is affine in R (Shepperd 1978), written out:
    the definition ``_SHEPPERD`` is read from."""
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    rows = [
        [1 + r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01],
        [r21 - r12, 1 + r00 - r11 - r22, r01 + r10, r02 + r20],
        [r02 - r20, r01 + r10, 1 - r00 + r11 - r22, r12 + r21],
        [r10 - r01, r02 + r20, r12 + r21, 1 - r00 - r11 + r22],
    ]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def _bilinear_table(terms: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], n_a: int, n_b: int) -> torch.Tensor:
    """``(n_a, n_b, *K)``: T[i, j] = terms(e_i, e_j), so that terms(a, b) = Σ_ij a_i b_j T[i, j] for bilinear terms."""
    eye_a, eye_b = torch.eye(n_a, dtype=torch.float64), torch.eye(n_b, dtype=torch.float64)
    return torch.stack([torch.stack([terms(eye_a[i], eye_b[j]) for j in range(n_b)]) for i in range(n_a)]).float()


_HAMILTON = _bilinear_table(_hamilton_terms, 4, 4)  # (4, 4, 4)
_LEVI_CIVITA = _bilinear_table(_cross_terms, 3, 3)  # (3, 3, 3)
# R(q)_ab = Σ_ij q_i q_j _ROTATION[i, j, a, b] for unit q: the service's quadratic forms (service.core.rotations)
_ROTATION = torch.from_numpy(QUADRATIC_FORMS).permute(2, 3, 0, 1).float()  # (4, 4, 3, 3)
# 4 q qᵀ = I + Σ_ab R_ab · _SHEPPERD[a, b]: the terms at each basis matrix, less those at R = 0 (the identity)
_SHEPPERD = (
    (_shepperd_terms(torch.eye(9, dtype=torch.float64).reshape(9, 3, 3)) - _shepperd_terms(torch.zeros(3, 3)))
    .reshape(3, 3, 4, 4)
    .float()
)


def _bilinear(a: torch.Tensor, b: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Σ_ij a_i b_j table[i, j, …]: ``a`` ``(..., I)``, ``b`` ``(..., J)``, ``table`` ``(I, J, *K)`` → ``(..., *K)``.

    Products of quaternions and vectors written out term by term export as one graph node per term, and onnxruntime
    pays about as much per small node as for its arithmetic (docs/models.md, "Served alignment"); as one product
    with a constant table they are a handful of nodes."""
    extra = (None,) * (table.dim() - 2)
    outer = (a[..., :, None] * b[..., None, :])[(..., *extra)]
    return (outer * table.to(a)).sum((-2 - len(extra), -1 - len(extra)))


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product over the last axis (``torch.linalg.cross`` has no ONNX export)."""
    return _bilinear(a, b, _LEVI_CIVITA)


def rotation_matrix(q: torch.Tensor) -> torch.Tensor:
    """R(q) ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (w, x, y, z): v' = R v, so R's rows are the rotated
    frame's axes in the original coordinates. q must be unit: the forms are homogeneous (w² + x² − y² − z², not
    1 − 2(y² + z²)), so another norm scales R by |q|² (``matrix_from_quat`` divides by it; the graph's q is unit)."""
    return _bilinear(q, q, _ROTATION)


def _sign(x: torch.Tensor) -> torch.Tensor:
    """+1 for x ≥ 0, else −1 (never 0, so a frame built from it stays a rotation)."""
    return torch.where(x >= 0, 1.0, -1.0)


def _half_angle(cos2: torch.Tensor, sin2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(cos θ, sin θ) from the doubled angle (cos 2θ, sin 2θ), with θ in (−90°, 90°]: the direction of a 2 × 2
    covariance's principal axis, whose sign is free, from its doubled-angle form (exportable: no atan2)."""
    cos = torch.sqrt(((1.0 + cos2) / 2.0).clamp(min=0.0))
    sin = _sign(sin2) * torch.sqrt(((1.0 - cos2) / 2.0).clamp(min=0.0))
    return cos, sin


def quat_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` (w, x, y, z) of rotation matrices ``(..., 3, 3)``, exportable to ONNX.

    Shepperd's method: 4 q qᵀ is linear in R; its largest diagonal element 4 q_k² picks the column 4 q_k q that is
    read most accurately, so 180° rotations are exact too. That column, normalised, is q up to its sign.
    """
    eye = torch.eye(4, dtype=R.dtype, device=R.device)
    S = (R[..., :, :, None, None] * _SHEPPERD.to(R)).sum((-4, -3)) + eye  # (..., 4, 4): 4 q qᵀ
    pivots = (S * eye).sum(-1)  # its diagonal, 4 q_k²
    pick = nn.functional.one_hot(pivots.argmax(-1), 4).to(R.dtype)
    return _unit((S * pick[..., None, :]).sum(-1))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b of ``(..., 4)`` quaternions (w, x, y, z)."""
    return _bilinear(a, b, _HAMILTON)


class CanonicalFrame(nn.Module):
    """A frame computed from the window itself, so the network only has to learn what is left over.

    Not in Zimmermann et al. 2018; our addition (README "Canonical frame"). z_c is the mean specific force (gravity, up
    to the motion's mean acceleration); y_c is the dominant axis of the angular velocity in the plane normal to z_c (for
    the legs the flexion axis, the segment's y), signed so that the third moment of ω·y_c is positive (the swing phase
    is faster than the stance); x_c = y_c × z_c. Returned is ``R_c`` ``(B, 3, 3)`` with rows x_c, y_c, z_c in sensor
    coordinates, i.e. v_c = R_c · v_imu. On sensor data simulated from the training clips, R_segment_imu · R_cᵀ is then
    constant per segment to within a few degrees, up to a 180° turn about z_c that the network resolves (it sees the
    window expressed in the canonical frame).
    """

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        acc, gyr = imu[..., :3], imu[..., 3:]
        z = _unit(acc.mean(1))  # (B, 3)
        ref = torch.where(z[:, :1].abs() < 0.9, z.new_tensor([1.0, 0.0, 0.0]), z.new_tensor([0.0, 1.0, 0.0]))
        e1 = _unit(_cross(z, ref))
        e2 = _cross(z, e1)
        uv = torch.einsum("btk,bjk->bjt", gyr, torch.stack([e1, e2], 1))  # (B, 2, T) in-plane components
        u, v = uv[:, 0], uv[:, 1]
        # Principal axis of the in-plane 2 × 2 covariance: direction of the doubled angle, then halved.
        d = _unit(torch.stack([(u * u - v * v).mean(1), 2.0 * (u * v).mean(1)], -1))
        cos, sin = _half_angle(d[:, 0], d[:, 1])
        y = cos[:, None] * e1 + sin[:, None] * e2
        y = y * _sign((((gyr * y[:, None]).sum(-1)) ** 3).mean(1))[:, None]
        return torch.stack([_cross(y, z), y, z], dim=1)


class AssignmentNet(nn.Module):
    """CNN → GRU(128) → linear → 7 logits in ``SEGMENTS`` order (Zimmermann et al. 2018 Fig. 2, Table A1).

    With ``canonical=True`` the window is first rotated into its ``CanonicalFrame`` (our addition), so the
    network no longer has to learn invariance to how the sensor is mounted.

    With ``quarter_turns=True`` (our addition) the class probabilities are averaged over the window turned by
    0°, 90°, 180° and 270° about the sensor's z axis, and ``forward`` returns their log. Eq. 8 turns the sensor
    about its own z by a uniform θ₁, so each turned copy is as plausible a mounting as the original; the
    average is invariant to those four turns, whatever the weights. The turns are exact axis permutations.
    With ``gravity_turns=n > 1`` (our addition) the average also runs over the window turned by 360°/n steps about
    its own mean specific force. On the legs that direction is the segment's long axis to within its mean
    inclination (10-20°), so each copy is the sensor moved around the limb, eq. 8's other angle θ₂; on the feet it
    is close to the surface normal (θ₁ again); the pelvis is classified alike at any turn. The network is not
    invariant to these turns on real recordings whose motion it has not seen (a real thigh sensor read 34-88 %
    depending on the turn, in an ad-hoc scan; README "Method"), and the average removes that dependence.
    Passes: n × (4 with ``quarter_turns``).

    With ``gravity_turn_segments`` (a subset of ``SEGMENTS``) only those classes take their probability from the
    average over the turns about gravity; the others take it from the passes of the window as it came (its
    quarter turns), and the mixture is renormalised. The turn about the mean specific force is eq. 8's θ₂ only
    for a segment whose long axis is near gravity: the thighs and shanks. For a foot it is near the surface
    normal and for the pelvis the heading, which the network was never trained to see turned that way, so the
    hypothesis "this is a foot" is best scored on the window's own quarter turns (the cmu_05 LOSO fold lost its
    feet to the full average; README "Method").
    The weights and state-dict keys are those of the plain net, so a trained plain net can be wrapped as it is.
    """

    def __init__(
        self,
        hidden: int = 128,
        channels: int = 64,
        kernel: int = 16,
        keep_prob: float = 0.8,
        canonical: bool = False,
        quarter_turns: bool = False,
        gravity_turns: int = 1,
        gravity_turn_segments: Sequence[str] | None = None,
    ) -> None:
        super().__init__()
        if gravity_turns < 1:
            raise ValueError(f"gravity_turns must be at least 1 (no turning), got {gravity_turns}")
        turned = SEGMENTS if gravity_turn_segments is None else tuple(gravity_turn_segments)
        if gravity_turn_segments is not None and (gravity_turns == 1 or not set(turned) <= set(SEGMENTS)):
            raise ValueError(f"gravity_turn_segments {turned} needs gravity_turns > 1 and names from SEGMENTS")
        self.gravity_turn_segments = None if gravity_turn_segments is None else turned
        # not in the state dict: the weights stay those of the plain net
        mask = torch.tensor([s in turned for s in SEGMENTS])
        self.register_buffer("_turned_classes", mask, persistent=False)
        self.scale = InputScale()
        self.canonical = CanonicalFrame() if canonical else None
        self.quarter_turns = quarter_turns
        self.gravity_turns = gravity_turns
        self.cnn = ConvFrontEnd(channels, kernel, 3, keep_prob)
        self.rnn = nn.GRU(channels, hidden, num_layers=1, batch_first=True)
        self.head = nn.Linear(hidden, len(SEGMENTS))

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        x = self.scale(imu)
        if self.canonical is not None:
            x = rotate_imu(x, self.canonical(x).detach())
        if not self.quarter_turns and self.gravity_turns == 1:
            return self._logits(x)
        views = [x] if self.gravity_turns == 1 else turned_about_gravity(x, self.gravity_turns)
        turns = range(4) if self.quarter_turns else range(1)
        # One pass per turn (not one batch of all turns): a reshape back would leave the exported class dimension
        # symbolic, and the service checks the manifest's [batch, 7] against the graph; one batch was not faster
        # in onnxruntime either (ad-hoc timing, docs/benchmarks.md). The first pass is the window as it came
        # (training.i2s.warmstart reads it).
        passes = torch.stack([torch.log_softmax(self._logits(_quarter_turn(v, k)), -1) for v in views for k in turns])
        averaged = torch.logsumexp(passes, dim=0) - math.log(len(views) * len(turns))  # log of the mean probability
        if self.gravity_turn_segments is None:
            return averaged
        unturned = torch.logsumexp(passes[: len(turns)], dim=0) - math.log(len(turns))
        mixed = torch.where(self._turned_classes, averaged, unturned)
        return mixed - torch.logsumexp(mixed, dim=-1, keepdim=True)

    def _logits(self, x: torch.Tensor) -> torch.Tensor:
        features, _ = self.rnn(self.cnn(x))
        return self.head(features[:, -1])


class AssignmentEnsemble(nn.Module):
    """Trained assignment networks whose class probabilities are averaged with equal weights (our addition, not
    in Zimmermann et al. 2018). ``forward`` returns the log of the mean probability, as an averaged ``AssignmentNet``
    does.

    Each member keeps its own turn averages, so the passes are the sum of the members'. It is assembled from
    shipped members (``train.ensemble_of``, ``training.i2s.warmstart``), not trained as a whole: members that learnt
    different motions (the gait-only 1.6.0, the all-activity 1.8.0) err on different real windows (README "Method").
    """

    def __init__(self, members: Sequence[AssignmentNet]) -> None:
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs at least two members, got {len(members)}")
        self.members = nn.ModuleList(members)

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        log_p = torch.stack([torch.log_softmax(member(imu), -1) for member in self.members])
        return torch.logsumexp(log_p, dim=0) - math.log(len(self.members))  # log of the mean probability


def _quarter_turn(imu: torch.Tensor, k: int) -> torch.Tensor:
    """Readings of the same motion with the sensor turned by k · 90° about its z axis: v' = R_z(k · 90°)ᵀ v, an
    exact permutation and sign change of the x and y channels of both the accelerometer and the gyroscope."""
    if k == 0:
        return imu
    ax, ay, az, gx, gy, gz = imu.unbind(-1)
    turns = {1: (ay, -ax, az, gy, -gx, gz), 2: (-ax, -ay, az, -gx, -gy, gz), 3: (-ay, ax, az, -gy, gx, gz)}
    return torch.stack(turns[k], dim=-1)


def turned_about_gravity(imu: torch.Tensor, n: int) -> list[torch.Tensor]:
    """The window turned by j · 360°/n (j = 0 … n−1) about its mean specific force k (Rodrigues:
    R = cos φ · I + sin φ · [k]× + (1 − cos φ) · k kᵀ); j = 0 is the window itself. The turn leaves k fixed."""
    k = _unit(imu[..., :3].mean(1))  # (B, 3)
    k0, k1, k2 = k.unbind(-1)
    zero = torch.zeros_like(k0)
    K = torch.stack([zero, -k2, k1, k2, zero, -k0, -k1, k0, zero], -1).reshape(-1, 3, 3)
    kkT = k[:, :, None] * k[:, None, :]
    eye = torch.eye(3, dtype=imu.dtype, device=imu.device)
    views = [imu]
    for j in range(1, n):
        phi = 2.0 * math.pi * j / n
        R = math.cos(phi) * eye + math.sin(phi) * K + (1.0 - math.cos(phi)) * kkT
        views.append(rotate_imu(imu, R))
    return views


def _turn_about_z(cos2: torch.Tensor, sin2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The (w, z) components of the quaternion of R_z(ψ) (x and y are 0) from the doubled angle (cos 2ψ, sin 2ψ)
    with cos 2ψ ≥ 0 (|ψ| ≤ 45°), by the half-angle formulas twice (no atan2 in the graph)."""
    cos, sin = _half_angle(cos2, sin2)
    half_cos = torch.sqrt(((1 + cos) / 2).clamp(min=1e-12))
    return half_cos, sin / (2 * half_cos)


# k ⊗ q = q · _Z_LEFT for k = (0, 0, 0, 1): a turn about z applied on the left, (w, 0, 0, z) ⊗ q = w q + z (k ⊗ q)
_Z_LEFT = _HAMILTON[3]


def _lagged_matrix_at(x: torch.Tensor, lag: torch.Tensor) -> torch.Tensor:
    """Lagged products mean(x_i,t · x_j,t+L) over time at one lag per window: ``x`` ``(B, P, C, T)`` (P groups of
    C signals), ``lag`` ``(B,)`` samples → ``(B, P, C, C)``. ``_lagged`` of signals i and j at that lag is the
    symmetric part, ½ (S_ij + S_ji); one gather of ``x`` for all of them."""
    n = x.shape[-1]
    t = torch.arange(n, device=x.device)
    ahead = t[None, :] + lag[:, None]  # (B, T)
    weight = (ahead < n).to(x.dtype) / (n - lag[:, None]).to(x.dtype)
    index = ahead.clamp(max=n - 1)[:, None, None, :].expand_as(x)
    later = torch.gather(x, -1, index) * weight[:, None, None, :]
    return torch.einsum("bpit,bpjt->bpij", x, later)


@functools.cache
def _shift_kernel(lags: tuple[int, ...]) -> np.ndarray:
    """``(len(lags), 1, max(lags) + 1)``: one-hot convolution kernels that read a signal L samples ahead. In numpy,
    so an exported graph holds it as a constant, and a tensor is made per call (a cached tensor made under
    ``torch.inference_mode`` could not be used in training afterwards)."""
    kernel = np.zeros((len(lags), 1, max(lags) + 1), dtype=np.float32)
    kernel[np.arange(len(lags)), 0, list(lags)] = 1.0
    return kernel


def is_geometry_convolution(node_name: str) -> bool:
    """Whether a Conv node of an exported alignment graph is one of ``_lagged``'s shifting convolutions: arithmetic
    on the window, with no learnt weights (warm starts skip them, quantisation keeps them float32)."""
    return "/functional_axes/" in node_name


def _lagged(a: torch.Tensor, b: torch.Tensor, lags: Sequence[int]) -> torch.Tensor:
    """Symmetrised lagged products ½·mean(a_t b_t+L + b_t a_t+L) over time, ``(B, T)`` → ``(B, len(lags))``.

    All lags at once: a convolution with one-hot kernels shifts each signal by every lag (zeros past its end, where
    no product is taken), and the mean divides by the T − L products there are. One slice per lag exported as
    several graph nodes per lag (about 3 ms per onnxruntime call on its nodes alone); a gather of the signals
    shifted by every lag moved them one number at a time (a fifth of the functional axes' cost)."""
    n, kernel = a.shape[-1], torch.from_numpy(_shift_kernel(tuple(lags))).to(a)
    counts = n - torch.tensor(list(lags), dtype=a.dtype, device=a.device)

    def ahead(x: torch.Tensor) -> torch.Tensor:  # (B, T) → (B, lags, T): x_t+L, 0 past the end
        return nn.functional.conv1d(nn.functional.pad(x[:, None, :], (0, kernel.shape[-1] - 1)), kernel)

    a_later = ahead(a)
    if b is a:
        return (a[:, None, :] * a_later).sum(-1) / counts
    return 0.5 * (a[:, None, :] * ahead(b) + b[:, None, :] * a_later).sum(-1) / counts


class FunctionalAxes(nn.Module):
    """Turns predicted segment frames about their own z onto the axes that the window's motion defines.

    Our addition, not in Zimmermann et al. 2018 (README "Functional axes"). The functional segment frames
    (``service.core.skeleton.functional_correction``, the training labels) read y of the upper legs, lower legs
    and feet, and x of the pelvis, off the clip's motion; the same quantities are in the window itself, and
    measured there they do not depend on how a person's joints were fitted. The network's z (and with it the
    rotations about x and y) is kept; each named hypothesis is turned about its predicted z by the angle ψ
    (|ψ| < 45°) from its axis to the measured one:

    - legs and feet: y onto the dominant axis of the angular velocity in the predicted x-y plane (the flexion
      axis, as the labels define it): the principal direction of the 2 × 2 covariance. Only where the in-plane
      RMS rate is at least ``min_rate_rads`` and the eigenvalues are apart by ``min_anisotropy`` of their sum.
    - pelvis: x onto the direction of travel. In gait the pelvis accelerates forwards and backwards once per step
      and sways sideways once per stride, so at a lag of one step the forward acceleration is correlated with
      itself and the sideways one anti-correlated; the rotation rates do the opposite (tilt about the sideways
      axis once per step, obliquity about the forward axis once per stride). The step is the lag of 0.25-0.75 s
      with the largest autocorrelation of the vertical (predicted z) acceleration; the two lagged 2 × 2
      covariances, each divided by its signal's in-plane power, are combined (acceleration minus rate) and x is
      turned onto the principal direction. Only where the step autocorrelation reaches ``min_periodicity`` of
      the vertical variance and the combined contrast ``min_contrast``.
    - pelvis, with ``pelvis_half_turn`` τ: which way along that axis is forward. The step analysis above fixes the
      axis, not its sign, and on real people the network's pelvis x pointed backwards in about 40 % of a walk's
      windows (docs/models.md). Walking is an inverted pendulum: the body is slowest at mid-stance, where it is
      highest, so the forward acceleration leads the vertical one by a quarter step. The cross-correlation of the
      forward and vertical accelerations at +``REVERSAL_LAG`` samples minus that at −``REVERSAL_LAG`` (each
      normalised by both signals' deviations) is positive in 98 % of simulated level-walking windows in their true
      pelvis frame and changes sign with x; where the step rhythm is clear (``min_periodicity``) and it reads
      ≤ −τ, the hypothesis is turned by a further 180° about z.

    Input: q_segment_imu ``(B, 7, 4)`` (w ≥ 0) and the raw window ``(B, T, 6)`` (m/s², rad/s, 60 Hz).
    """

    STEP_LAGS = tuple(range(15, 46))  # samples at 60 Hz: steps of 0.25-0.75 s (cadence 80-240 steps/min)
    REVERSAL_LAG = 6  # samples at 60 Hz (0.1 s, about a fifth of a step): the lead of the forward acceleration

    def __init__(
        self,
        segments: Sequence[str],
        min_anisotropy: float = 0.5,
        min_rate_rads: float = 0.2,
        min_periodicity: float = 0.3,
        min_contrast: float = 0.8,
        pelvis_half_turn: float | None = None,
    ) -> None:
        super().__init__()
        unknown = sorted(set(segments) - set(SEGMENTS))
        if unknown or not segments:
            raise ValueError(f"functional axes segments must be some of {list(SEGMENTS)}; got {list(segments)}")
        self.segments = tuple(segments)
        flexion = [n in self.segments and n != "Pelvis" for n in SEGMENTS]
        self.register_buffer("flexion_mask", torch.tensor(flexion), persistent=False)
        self.pelvis = SEGMENTS.index("Pelvis") if "Pelvis" in self.segments else None
        self.min_anisotropy, self.min_rate_rads = min_anisotropy, min_rate_rads
        self.min_periodicity, self.min_contrast = min_periodicity, min_contrast
        if pelvis_half_turn is not None and (self.pelvis is None or pelvis_half_turn < 0):
            raise ValueError(f"pelvis_half_turn needs Pelvis among the segments and τ ≥ 0; got {pelvis_half_turn}")
        self.pelvis_half_turn = pelvis_half_turn

    def _flexion_turn(self, R: torch.Tensor, gyr: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The turn of each hypothesis ``R`` ``(B, 7, 3, 3)`` as (w, z) ``(B, 7)`` each; (1, 0) where none."""
        uv = torch.einsum("btk,bsjk->bsjt", gyr, R[:, :, :2])  # (B, 7, 2, T) rates about the predicted x and y
        moments = (uv[:, :, :, None] * uv[:, :, None]).mean(-1)  # (B, 7, 2, 2)
        sxx, syy, sxy = moments[..., 0, 0], moments[..., 1, 1], moments[..., 0, 1]
        r = torch.sqrt((syy - sxx) ** 2 + 4 * sxy * sxy + 1e-12)
        w, z = _turn_about_z((syy - sxx) / r, 2 * sxy / r)  # ψ from y towards the principal direction
        clear = (syy > sxx) & (r >= self.min_anisotropy * (sxx + syy)) & (sxx + syy >= self.min_rate_rads**2)
        clear = clear & self.flexion_mask
        return torch.where(clear, w, 1.0), torch.where(clear, z, 0.0)

    def _pelvis_turn(self, R: torch.Tensor, imu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The turn of the pelvis hypothesis ``R`` ``(B, 3, 3)`` as (w, z) ``(B,)`` each; (1, 0) where none."""
        acc = torch.einsum("btk,bjk->bjt", imu[..., :3], R)  # (B, 3, T): along the predicted x, y, z
        rate = torch.einsum("btk,bjk->bjt", imu[..., 3:], R[:, :2])  # (B, 2, T): about the predicted x, y
        acc, rate = acc - acc.mean(-1, keepdim=True), rate - rate.mean(-1, keepdim=True)
        az = acc[:, 2]
        vertical = _lagged(az, az, self.STEP_LAGS)  # (B, lags)
        periodic = vertical.max(-1).values >= self.min_periodicity * (az * az).mean(-1)
        step = vertical.argmax(-1) + self.STEP_LAGS[0]  # (B,) samples; the lags are consecutive
        # (Sxx − Syy, 2 Sxy) at the step lag over the in-plane power, the doubled principal direction, for the
        # acceleration and the rate at once: forward is acceleration in step, rate out of step.
        pairs = torch.stack([acc[:, :2], rate], 1)  # (B, 2, 2, T)
        S = _lagged_matrix_at(pairs, step)  # (B, 2, 2, 2)
        power = (pairs * pairs).sum(-2).mean(-1) + 1e-12  # (B, 2)
        contrast = torch.stack([S[..., 0, 0] - S[..., 1, 1], S[..., 0, 1] + S[..., 1, 0]], -1) / power[..., None]
        d = contrast[:, 0] - contrast[:, 1]
        norm = torch.sqrt((d * d).sum(-1) + 1e-12)
        w, z = _turn_about_z(d[:, 0] / norm, -d[:, 1] / norm)  # ψ = minus the principal direction's angle
        clear = periodic & (norm >= self.min_contrast) & (d[:, 0] > 0)
        w, z = torch.where(clear, w, 1.0), torch.where(clear, z, 0.0)
        if self.pelvis_half_turn is None:
            return w, z
        # The forward acceleration in the turned frame: R_z(ψ) · R puts x at cos ψ · x − sin ψ · y.
        cos, sin = 1 - 2 * z * z, 2 * w * z
        forward = cos[:, None] * acc[:, 0] - sin[:, None] * acc[:, 1]
        lag = self.REVERSAL_LAG
        lead = (forward[:, :-lag] * az[:, lag:]).mean(-1) - (forward[:, lag:] * az[:, :-lag]).mean(-1)
        spread = torch.sqrt((forward * forward).mean(-1) * (az * az).mean(-1) + 1e-12)
        backwards = periodic & (lead <= -self.pelvis_half_turn * spread)
        return torch.where(backwards, -z, w), torch.where(backwards, w, z)  # R_z(180°) ⊗ turn: (w, z) → (−z, w)

    def forward(self, q: torch.Tensor, imu: torch.Tensor) -> torch.Tensor:
        R = rotation_matrix(q)  # (B, 7, 3, 3): each hypothesis' predicted axes in sensor coordinates
        w, z = self._flexion_turn(R, imu[..., 3:])
        if self.pelvis is not None:
            pelvis_w, pelvis_z = self._pelvis_turn(R[:, self.pelvis], imu)
            is_pelvis = torch.arange(len(SEGMENTS), device=q.device)[None, :] == self.pelvis
            w, z = torch.where(is_pelvis, pelvis_w[:, None], w), torch.where(is_pelvis, pelvis_z[:, None], z)
        out = w[..., None] * q + z[..., None] * (q @ _Z_LEFT.to(q))  # R_new = R_z(ψ) · R: turned about its own z
        return out * torch.where(out[..., :1] < 0, -1.0, 1.0)


def rotate_imu(imu: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Readings ``(B, T, 6)`` expressed in another frame: acc' = R · acc, gyr' = R · gyr, with ``R`` ``(B, 3, 3)``."""
    Rt = R.transpose(1, 2)
    return torch.cat([imu[..., :3] @ Rt, imu[..., 3:] @ Rt], dim=-1)


class AlignmentNet(nn.Module):
    """CNN → 2-layer LSTM(128) → linear → stereographic projections → unit quaternions, one per segment.

    The alignment R_SI is only defined relative to a segment, so the head regresses 3 values for
    each of the 7 segments; training supervises the row of the true segment and the service picks the
    row of the assigned (or declared) segment. ``forward`` returns q_segment_imu ``(B, 7, 4)``, unit, w ≥ 0.

    With ``canonical=True`` the window is first rotated into its ``CanonicalFrame`` and the network predicts
    q_segment_canonical, so q_segment_imu = q_segment_canonical ⊗ q_canonical_imu (all inside the graph).
    With ``functional_axes`` those segments' frames are then turned about their z onto the axes that the
    window's motion defines (``FunctionalAxes``; no weights, so it can wrap trained weights as they are), and with
    ``pelvis_half_turn`` the pelvis is turned round where its walk says it faces backwards.
    With ``rnn_stride`` n > 1 the CNN's features are averaged over each run of n samples before the LSTM (not in
    the paper): the LSTM, most of the network's cost, takes 128 / n steps. The weights keep their shapes, so a
    network trained at one stride warm-starts another.
    """

    def __init__(
        self,
        hidden: int = 128,
        channels: int = 64,
        kernel: int = 16,
        keep_prob: float = 0.8,
        canonical: bool = False,
        functional_axes: Sequence[str] | None = None,
        rnn_stride: int = 1,
        pelvis_half_turn: float | None = None,
    ) -> None:
        super().__init__()
        if rnn_stride < 1:
            raise ValueError(f"rnn_stride must be a whole number of samples ≥ 1; got {rnn_stride}")
        self.scale = InputScale()
        self.rnn_stride = rnn_stride
        self.canonical = CanonicalFrame() if canonical else None
        if pelvis_half_turn is not None and functional_axes is None:
            raise ValueError("pelvis_half_turn is part of the functional axes: name Pelvis in functional_axes")
        self.functional_axes = (
            None if functional_axes is None else FunctionalAxes(functional_axes, pelvis_half_turn=pelvis_half_turn)
        )
        self.cnn = ConvFrontEnd(channels, kernel, 3, keep_prob)
        self.rnn = nn.LSTM(channels, hidden, num_layers=2, batch_first=True)
        self.head = nn.Linear(hidden, 3 * len(SEGMENTS))

    def stereographic(self, imu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The head's projections ``(B, 7, 3)`` and the canonical frame ``R_c`` (or None) they are relative to."""
        x = self.scale(imu)
        R_c = None
        if self.canonical is not None:
            R_c = self.canonical(x).detach()
            x = rotate_imu(x, R_c)
        features = self.cnn(x)
        if self.rnn_stride > 1:  # mean over each run of rnn_stride samples: 1 / rnn_stride of the LSTM's steps
            features = nn.functional.avg_pool1d(features.transpose(1, 2), self.rnn_stride).transpose(1, 2)
        features, _ = self.rnn(features)
        return self.head(features[:, -1]).reshape(-1, len(SEGMENTS), 3), R_c

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        p, R_c = self.stereographic(imu)
        q = stereographic_to_quat(p)
        if R_c is not None:
            q = quat_multiply(q, quat_from_matrix(R_c)[:, None, :])
        q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
        return q if self.functional_axes is None else self.functional_axes(q, imu)


def stereographic_to_quat(p: torch.Tensor) -> torch.Tensor:
    """q = (1 - |p|², 2p) / (1 + |p|²), then w ≥ 0 (ref. 56 of Zimmermann et al. 2018); ``(..., 3)`` → ``(..., 4)``."""
    n2 = (p * p).sum(-1, keepdim=True)
    q = torch.cat([1.0 - n2, 2.0 * p], dim=-1) / (1.0 + n2)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


class AssignmentExport(nn.Module):
    """Exported assignment graph: imu ``(B, 128, 6)`` → class probabilities ``(B, 7)`` (softmax inside)."""

    def __init__(self, net: AssignmentNet | AssignmentEnsemble) -> None:
        super().__init__()
        self.net = net

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.net(imu), dim=-1)
