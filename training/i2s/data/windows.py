"""Windows of simulated IMU data drawn from cached segment kinematics.

Training draws fresh windows every step (``WindowSampler``): a random clip, start, segment and
eq. 8 alignment, plus the augmentations of ``Augmentation`` (playback speed, sensor offset, gain,
bias, noise, mirror image). Evaluation enumerates every window (hop 16) × segment × eq. 8 grid alignment
(``grid_batches``), deterministically, with the paper's noise and quantisation only.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from service.core.assignment import is_moving
from service.core.recordings import RealRecording
from service.core.rotations import quat_from_matrix
from service.core.segments import MIRROR
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, WINDOW_SAMPLES, sliding_windows
from training.i2s.data.imu_sim import (
    SOFT_TISSUE_SHARE,
    SensorSpec,
    SoftTissue,
    alignment,
    alignment_grid,
    imu_readings,
    mirrored,
    mirrored_readings,
    quantise,
    soft_tissue_motion,
    with_soft_tissue,
)
from training.i2s.data.mocap import Clip

if TYPE_CHECKING:  # training.i2s.config imports this module (Augmentation)
    from training.i2s.config import ExperimentConfig

N_SEGMENTS = 7
_MAX_MOVING_ROUNDS = 20  # moving_only: batches drawn before giving up on a nearly still clip set


class Augmentation(BaseModel):
    """Per-window randomisation of the simulation; zeros and ones reproduce Zimmermann et al. 2018 exactly."""

    model_config = ConfigDict(extra="forbid")
    alignment: str = "continuous"  # "grid": eq. 8's 64 variations; "continuous": θ₁, θ₂ uniform
    tilt_deg: float = 0.0  # extra random tilt of the sensor off the surface tangent
    speed_min: float = 1.0  # playback-speed scaling range (docs/conventions.md)
    speed_max: float = 1.0
    offset_std_m: float = 0.0  # sensor position offset from the segment midpoint
    gain_std: float = 0.0  # per-axis scale-factor error
    acc_bias_std_mps2: float = 0.0
    gyr_bias_std_rads: float = 0.0
    acc_noise_std_mps2: float = 1.0  # Zimmermann et al. 2018 §2.4.2: variance 1 m²/s⁴
    gyr_noise_std_rads: float = 0.0
    mirror: bool = False  # also draw from every clip's mirror image, left and right swapped (``mirrored``)
    # Share of windows drawn from the walking clips' stiff-knee variants (``stiffened_knee``; 0: none built),
    # and the most knee flexion such a variant keeps.
    stiff_knee_share: float = Field(0.0, ge=0.0, lt=1.0)
    stiff_knee_keep_max: float = Field(0.4, ge=0.0, le=1.0)
    # Soft-tissue artefact (``soft_tissue_motion``; our addition, not in Zimmermann et al. 2018): per window the sensor
    # turns and moves on its segment with the segment's own accelerations through a resonance of 4–12 Hz; the RMS
    # rotation and displacement are uniform up to these values for the thigh, scaled down for the other segments
    # (``SOFT_TISSUE_SHARE``). 0: off.
    soft_tissue_rot_deg: float = Field(0.0, ge=0.0)
    soft_tissue_disp_mm: float = Field(0.0, ge=0.0)
    # Draw only windows the service answers (``is_moving``: the sensor's mean gyroscope norm above the still
    # threshold); still windows carry no cue to a segment but gravity's direction, which the alignment hides.
    # Matters for clips with long still spells (basketball signals, directing traffic); gait is nearly all moving.
    moving_only: bool = False


@dataclass(frozen=True)
class Batch:
    imu: np.ndarray  # (B, 128, 6) float32
    segment: np.ndarray  # (B,) int64
    q_segment_imu: np.ndarray  # (B, 4) float32, w >= 0
    # (B,) bool: the windows a teacher speaks for in distillation (``train.distill_activities``); None: all
    taught: np.ndarray | None = None


_BATCH_FIELDS = [f.name for f in fields(Batch)]


class _Stacked:
    """All clips' kinematics concatenated along time, ``(N, 7, 3)`` each, with clip offsets."""

    def __init__(self, clips: list[Clip], variant_share: float = 0.0) -> None:
        if not clips:
            raise ValueError("no clips to draw windows from")
        self.draw_p = _draw_probabilities(clips, variant_share)
        self.lin_acc = np.concatenate([c.kin.lin_acc_mps2 for c in clips])
        self.up = np.concatenate([c.kin.up_mps2 for c in clips])
        self.gyr = np.concatenate([c.kin.gyr_rads for c in clips])
        self.ang_acc = np.concatenate([c.kin.ang_acc_rads2 for c in clips])
        self.lengths = np.array([c.n_samples for c in clips])
        self.offsets = np.r_[0, np.cumsum(self.lengths)[:-1]]

    def gather(self, t: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, ...]:
        """Linear interpolation at fractional global sample times ``t`` (B, T) for segments ``seg`` (B,)."""
        i0 = np.floor(t).astype(np.int64)
        i1 = np.minimum(i0 + 1, self.lin_acc.shape[0] - 1)
        w = (t - i0)[..., None]
        s = seg[:, None]
        return tuple((1 - w) * a[i0, s] + w * a[i1, s] for a in (self.lin_acc, self.up, self.gyr, self.ang_acc))


def _draw_probabilities(clips: list[Clip], variant_share: float) -> np.ndarray:
    """Per-clip draw probabilities: by length, with the variants together taking ``variant_share`` of draws."""
    lengths = np.array([c.n_samples for c in clips], dtype=np.float64)
    is_variant = np.array([bool(c.variant) for c in clips])
    if not is_variant.any():
        return lengths / lengths.sum()
    if is_variant.all() or variant_share <= 0.0:
        raise ValueError(
            f"clip variants need recorded clips beside them and a share in (0, 1); got {int(is_variant.sum())} "
            f"variants of {len(clips)} clips and share {variant_share}"
        )
    share = np.where(is_variant, variant_share, 1.0 - variant_share)
    group_total = np.where(is_variant, lengths[is_variant].sum(), lengths[~is_variant].sum())
    return lengths / group_total * share


def _random_tilt(rng: np.random.Generator, n: int, tilt_deg: float) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(rng.normal(0.0, tilt_deg, size=(n, 1)))
    return Rotation.from_rotvec(axis * angle).as_matrix()


class WindowSampler:
    """Random simulated windows from a set of clips (training and validation)."""

    def __init__(
        self,
        clips: list[Clip],
        aug: Augmentation,
        spec: SensorSpec = SensorSpec(),
        taught_activities: list[str] | None = None,
    ) -> None:
        """``taught_activities``: the windows of these activities' clips are marked ``Batch.taught`` (None: no
        mark, a teacher speaks for every window)."""
        self.clips = [c for c in clips if c.n_samples >= WINDOW_SAMPLES + 1]
        if aug.mirror:
            self.clips += [Clip(c.entry, mirrored(c.kin), f"{c.digest}-mirror", c.variant) for c in self.clips]
        self.stack = _Stacked(self.clips, aug.stiff_knee_share)
        self.aug, self.spec = aug, spec
        self.taught_clip = (
            None if taught_activities is None else np.array([c.entry.activity in taught_activities for c in self.clips])
        )

    def _alignments(self, rng: np.random.Generator, seg: np.ndarray) -> np.ndarray:
        n = len(seg)
        if self.aug.alignment == "grid":
            t1, t2 = (rng.integers(0, 8, n) * np.pi / 4 for _ in range(2))
        elif self.aug.alignment == "continuous":
            t1, t2 = (rng.uniform(0, 2 * np.pi, n) for _ in range(2))
        else:
            raise ValueError(f"alignment must be 'grid' or 'continuous', got {self.aug.alignment!r}")
        R = np.stack([alignment(int(s), a, b)[0] for s, a, b in zip(seg, t1, t2, strict=True)])
        return R @ _random_tilt(rng, n, self.aug.tilt_deg) if self.aug.tilt_deg > 0 else R

    def sample(self, rng: np.random.Generator, batch_size: int) -> Batch:
        if not self.aug.moving_only:
            return self._draw(rng, batch_size)
        parts, n = [], 0
        for _ in range(_MAX_MOVING_ROUNDS):
            b = self._draw(rng, batch_size)
            keep = is_moving(b.imu)
            parts.append(Batch(*(None if getattr(b, f) is None else getattr(b, f)[keep] for f in _BATCH_FIELDS)))
            n += int(keep.sum())
            if n >= batch_size:
                return concat_batches(*parts, limit=batch_size)
        raise ValueError(
            f"augmentation.moving_only: {n} moving windows in {_MAX_MOVING_ROUNDS} draws of {batch_size}; "
            "the clips are nearly all still"
        )

    def _draw(self, rng: np.random.Generator, batch_size: int) -> Batch:
        aug, st = self.aug, self.stack
        clip = rng.choice(len(st.lengths), size=batch_size, p=st.draw_p)
        speed = rng.uniform(aug.speed_min, aug.speed_max, batch_size)
        speed = np.minimum(speed, (st.lengths[clip] - 1) / (WINDOW_SAMPLES - 1))  # short clips: slower only
        span = (WINDOW_SAMPLES - 1) * speed
        room = np.maximum(st.lengths[clip] - 1 - span, 0.0)
        start = st.offsets[clip] + rng.uniform(0.0, 1.0, batch_size) * room
        t = start[:, None] + speed[:, None] * np.arange(WINDOW_SAMPLES)[None, :]
        seg = rng.integers(0, N_SEGMENTS, batch_size)
        lin_acc, up, gyr, ang_acc = st.gather(t, seg)
        s = speed[:, None, None]  # time scaling: velocities × s, accelerations × s²
        R = self._alignments(rng, seg)
        offset = rng.normal(0.0, aug.offset_std_m, (batch_size, 3)) if aug.offset_std_m > 0 else None
        lin_acc, gyr, ang_acc = lin_acc * s**2, gyr * s, ang_acc * s**2
        if aug.soft_tissue_rot_deg > 0 or aug.soft_tissue_disp_mm > 0:
            seg_frame = imu_readings(lin_acc, up, gyr, ang_acc, np.broadcast_to(np.eye(3), R.shape), offset)
            acc_s, gyr_s = with_soft_tissue(
                seg_frame[..., :3],
                seg_frame[..., 3:],
                *soft_tissue_motion(lin_acc, ang_acc, self._soft_tissue(rng, seg), MODEL_RATE_HZ),
            )
            imu = np.concatenate([np.einsum("bji,btj->bti", R, acc_s), np.einsum("bji,btj->bti", R, gyr_s)], axis=-1)
        else:
            imu = imu_readings(lin_acc, up, gyr, ang_acc, R, offset)
        imu = self._sensor_errors(rng, imu)
        taught = None if self.taught_clip is None else self.taught_clip[clip]
        return Batch(imu.astype(np.float32), seg.astype(np.int64), quat_from_matrix(R).astype(np.float32), taught)

    def _soft_tissue(self, rng: np.random.Generator, seg: np.ndarray) -> SoftTissue:
        b, share = len(seg), SOFT_TISSUE_SHARE[seg]
        return SoftTissue(
            freq_hz=rng.uniform(4.0, 12.0, b),
            damping=rng.uniform(0.2, 0.5, b),
            mix=rng.normal(size=(b, 6, 6)),
            rot_rms_rad=np.radians(self.aug.soft_tissue_rot_deg) * rng.uniform(0.0, 1.0, b) * share,
            disp_rms_m=1e-3 * self.aug.soft_tissue_disp_mm * rng.uniform(0.0, 1.0, b) * share,
        )

    def _sensor_errors(self, rng: np.random.Generator, imu: np.ndarray) -> np.ndarray:
        aug, b = self.aug, imu.shape[0]
        if aug.gain_std > 0:
            imu = imu * rng.normal(1.0, aug.gain_std, (b, 1, 6))
        bias_std = np.array([aug.acc_bias_std_mps2] * 3 + [aug.gyr_bias_std_rads] * 3)
        noise_std = np.array([aug.acc_noise_std_mps2] * 3 + [aug.gyr_noise_std_rads] * 3)
        imu = imu + rng.normal(size=(b, 1, 6)) * bias_std + rng.normal(size=imu.shape) * noise_std
        return quantise(imu, self.spec)


def grid_batches(
    clips: list[Clip],
    aug: Augmentation,
    seed: int,
    batch_size: int = 2048,
    n_angles: int = 8,
    spec: SensorSpec = SensorSpec(),
    segments: list[tuple[int, ...]] | None = None,
) -> Iterator[tuple[Batch, np.ndarray]]:
    """Every window (hop 16) × segment × eq. 8 alignment of ``clips``; yields (batch, body per row).

    Only the paper's accelerometer noise (``aug.acc_noise_std_mps2``) and quantisation are applied.
    ``segments`` (one tuple per clip) scores only those segments of each clip. The rows of one body are the
    windows of a clip's segments at the same moment with the same alignment index: a set of sensors worn
    together (for ``window_joint_assignment``).
    """
    rng = np.random.default_rng(seed)
    grids = [alignment_grid(s, n_angles) for s in range(N_SEGMENTS)]
    quats = [quat_from_matrix(g).astype(np.float32) for g in grids]
    rows: list[tuple[int, int, int, int, int]] = []  # (clip, start, segment, alignment, body)
    n_bodies = 0
    for ci, clip in enumerate(clips):
        scored = range(N_SEGMENTS) if segments is None else segments[ci]
        for start in range(0, clip.n_samples - WINDOW_SAMPLES + 1, HOP_SAMPLES):
            rows += [(ci, start, s, a, n_bodies + a) for s in scored for a in range(n_angles**2)]
            n_bodies += n_angles**2
    table = np.array(rows, dtype=np.int64).reshape(-1, 5)
    for lo in range(0, len(table), batch_size):
        part = table[lo : lo + batch_size]
        idx = part[:, 1:2] + np.arange(WINDOW_SAMPLES)
        seg = part[:, 2]
        arrays = [
            np.stack([getattr(clips[c].kin, name)[i, s] for c, i, s in zip(part[:, 0], idx, seg, strict=True)])
            for name in ("lin_acc_mps2", "up_mps2", "gyr_rads", "ang_acc_rads2")
        ]
        R = np.stack([grids[s][a] for s, a in zip(seg, part[:, 3], strict=True)])
        imu = imu_readings(*arrays, R_segment_imu=R)
        imu = imu + rng.normal(size=imu.shape) * np.array([aug.acc_noise_std_mps2] * 3 + [0.0] * 3)
        imu = quantise(imu, spec)
        q = np.stack([quats[s][a] for s, a in zip(seg, part[:, 3], strict=True)])
        yield Batch(imu.astype(np.float32), seg, q), part[:, 4]


class RealWindowSampler:
    """Moving windows (hop 4) of labelled real recordings, for mixing into assignment training.

    ``part`` splits every sensor's recording in time: ``"train"`` takes the first ``1 - val_fraction`` of its
    samples, ``"validation"`` the rest, so no validation window shares a sample with a training window;
    ``"all"`` takes everything. ``mirror`` is the share of drawn windows read as the mirror-image body's
    (``mirrored_readings``, label ↔ the other side's segment); a draw of none leaves the random stream as it was.
    ``rotate`` turns each drawn window by a uniformly random rotation (``turned_readings``). ``balance`` says how
    windows are drawn: ``"window"`` uniformly over all of them (a source with many long recordings then fills most
    draws), ``"source"`` each source equally often, within it each person equally often, within a person uniformly;
    with ``"source"``, ``balance_share`` of the draws follow that rule and the rest are drawn by window.
    """

    def __init__(
        self,
        recordings: list[RealRecording],
        part: Literal["all", "train", "validation"] = "all",
        val_fraction: float = 0.2,
        mirror: float = 0.0,
        rotate: bool = False,
        balance: Literal["window", "source"] = "window",
        balance_share: float = 1.0,
    ) -> None:
        self.mirror, self.rotate = mirror, rotate
        imu, seg, owner = [], [], []
        for rec in recordings:
            for sensor in rec.sensors:
                if sensor.segment is None:
                    continue
                cut = int(round(len(sensor.imu) * (1.0 - val_fraction)))
                samples = {"all": sensor.imu, "train": sensor.imu[:cut], "validation": sensor.imu[cut:]}[part]
                if len(samples) < WINDOW_SAMPLES:
                    continue
                w = sliding_windows(samples.astype(np.float32), hop=4)
                w = w[is_moving(w)]
                imu.append(w)
                seg.append(np.full(len(w), sensor.segment))
                owner += [(rec.source, rec.subject)] * len(w)
        if not sum(len(w) for w in imu):
            raise ValueError(f"no labelled moving windows in the {part} part of the real training recordings")
        self.imu, self.segment = np.concatenate(imu), np.concatenate(seg)
        self.p = None
        if balance == "source":
            self.p = balance_share * source_balanced_weights(owner) + (1.0 - balance_share) / len(owner)

    def sample(self, rng: np.random.Generator, batch_size: int) -> Batch:
        if self.p is None:
            idx = rng.integers(0, len(self.imu), batch_size)
        else:
            idx = rng.choice(len(self.imu), batch_size, p=self.p)
        nan_q = np.full((batch_size, 4), np.nan, dtype=np.float32)  # alignment unknown on real data
        imu, segment = self.imu[idx], self.segment[idx].astype(np.int64)
        if self.mirror > 0:
            flip = rng.random(batch_size) < self.mirror
            imu = np.where(flip[:, None, None], mirrored_readings(imu), imu).astype(np.float32)
            segment = np.where(flip, np.asarray(MIRROR)[segment], segment)
        if self.rotate:
            imu = turned_readings(imu, Rotation.random(batch_size, rng).as_matrix().astype(np.float32))
        return Batch(np.ascontiguousarray(imu), segment, nan_q)


def source_balanced_weights(owner: list[tuple[str, str]]) -> np.ndarray:
    """Draw probabilities of windows owned by ``(source, person)``: every source the same total, shared equally by
    its people, and by each person's windows."""
    persons = Counter(owner)
    per_source = Counter(source for source, _ in persons)
    w = np.array([1.0 / (len(per_source) * per_source[src] * persons[(src, who)]) for src, who in owner])
    return w / w.sum()


def turned_readings(imu: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Windows ``(B, T, 6)`` read by sensors turned by ``R`` ``(B, 3, 3)`` (new sensor ← old sensor): each window's
    accelerometer and gyroscope vectors rotated alike, ``R @ v`` at every sample."""
    acc = np.einsum("bij,btj->bti", R, imu[..., :3])
    gyr = np.einsum("bij,btj->bti", R, imu[..., 3:])
    return np.concatenate([acc, gyr], axis=-1).astype(np.float32)


def real_window_samplers(
    cfg: ExperimentConfig, recordings: list[RealRecording]
) -> tuple[RealWindowSampler | None, RealWindowSampler | None]:
    """Training and validation windows of the real training recordings (those ``data.real_train_recordings``
    names, Zimmermann et al. 2018 §4.3 fine-tuning), split in time by ``data.real_val_fraction``; (None, None) without
    recordings or when ``data.real_fraction`` is 0."""
    if not recordings or cfg.data.real_fraction == 0:
        return None, None
    fraction = cfg.data.real_val_fraction
    mirror = cfg.data.real_mirror  # training windows only: validation reads the recordings as they are
    rotate = cfg.data.real_rotation
    drawn = {"balance": cfg.data.real_balance, "balance_share": cfg.data.real_balance_share}
    if fraction == 0:
        return RealWindowSampler(recordings, mirror=mirror, rotate=rotate, **drawn), None
    train = RealWindowSampler(recordings, "train", fraction, mirror=mirror, rotate=rotate, **drawn)
    return train, RealWindowSampler(recordings, "validation", fraction, **drawn)


def concat_batches(*batches: Batch, limit: int | None = None) -> Batch:
    """The batches one after the other (the first ``limit`` windows). Where some carry ``taught`` and others do not,
    the others' windows count as taught (real windows: gait, which a teacher speaks for)."""
    if all(b.taught is None for b in batches):
        taught = None
    else:
        taught = np.concatenate([np.ones(len(b.segment), bool) if b.taught is None else b.taught for b in batches])
    joined = [np.concatenate([getattr(b, f) for b in batches]) for f in _BATCH_FIELDS if f != "taught"]
    return Batch(*(a[:limit] for a in joined), None if taught is None else taught[:limit])
