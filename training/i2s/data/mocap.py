"""Mocap clips → segment kinematics, cached on disk by a content digest.

The digest covers the BVH bytes, the simulation parameters and ``KINEMATICS_VERSION``; changing any
of them recomputes. ``build_kinematics`` shows a progress bar and uses a process pool.
"""

from __future__ import annotations

import hashlib
import logging
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from service.core.bvh import read_bvh
from service.core.kinematics import forward_kinematics
from service.core.skeleton import SegmentTrajectories, functional_frames, segment_trajectories, skeleton_map_for
from training.data.catalog import METRES_PER_UNIT, CatalogEntry
from training.i2s.data.imu_sim import LEG_CHAIN, ClipTooShort, SegmentKinematics, segment_kinematics, stiffened_knee

log = logging.getLogger(__name__)

KINEMATICS_VERSION = "2"  # 2: functional segment frames


@dataclass(frozen=True)
class KinematicsParams:
    sample_rate_hz: float = 60.0
    cutoff_hz: float = 10.0
    filter_order: int = 8


@dataclass(frozen=True)
class Clip:
    """One mocap clip's segment kinematics with its catalogue entry and content digest."""

    entry: CatalogEntry
    kin: SegmentKinematics
    digest: str
    variant: str = ""  # "" for the clip as recorded; else how it was altered (``stiff_knee_variants``)

    @property
    def n_samples(self) -> int:
        return self.kin.gyr_rads.shape[0]

    @property
    def source_digest(self) -> str:
        """The digest of the recorded clip this one comes from (its own digest if it is not a variant)."""
        return self.digest.removesuffix(f"-{self.variant}") if self.variant else self.digest


def as_recorded(clips: list[Clip]) -> list[Clip]:
    """The clips as recorded, without their variants."""
    return [c for c in clips if not c.variant]


def clip_digest(bvh_path: Path, params: KinematicsParams) -> str:
    h = hashlib.sha256(bvh_path.read_bytes())
    h.update(f"{params}|v{KINEMATICS_VERSION}".encode())
    return h.hexdigest()[:20]


def geometric_trajectories(bvh_path: Path, entry: CatalogEntry) -> SegmentTrajectories:
    """The clip's seven segment trajectories in the geometric frames, T-pose frames dropped."""
    poses = forward_kinematics(read_bvh(bvh_path), METRES_PER_UNIT[entry.source])
    traj = segment_trajectories(poses, skeleton_map_for(entry.source, poses.names))
    skip = entry.tpose_frames
    return SegmentTrajectories(
        traj.R_world_segment[skip:], traj.origin_m[skip:], traj.midpoint_m[skip:], traj.sample_rate_hz
    )


def compute_kinematics(bvh_path: Path, entry: CatalogEntry, params: KinematicsParams) -> SegmentKinematics:
    traj, _ = functional_frames(geometric_trajectories(bvh_path, entry), foot_flat=entry.activity != "run")
    return segment_kinematics(traj, params.sample_rate_hz, params.cutoff_hz, params.filter_order)


def compute_variant_kinematics(
    bvh_path: Path, entry: CatalogEntry, params: KinematicsParams, side: str, keep: float
) -> SegmentKinematics:
    """``compute_kinematics`` of the clip with one knee braced (``stiffened_knee``)."""
    traj, _ = functional_frames(geometric_trajectories(bvh_path, entry), foot_flat=entry.activity != "run")
    traj = stiffened_knee(traj, side, keep)
    return segment_kinematics(traj, params.sample_rate_hz, params.cutoff_hz, params.filter_order)


def _cached(path: Path, compute) -> SegmentKinematics:
    if path.exists():
        with np.load(path) as z:
            return SegmentKinematics(
                **{k: z[k] for k in z.files if k != "sample_rate_hz"}, sample_rate_hz=float(z["sample_rate_hz"])
            )
    kin = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: v for k, v in kin.__dict__.items()})
    tmp.rename(path)
    return kin


def _load_or_compute(args: tuple[Path, CatalogEntry, KinematicsParams, Path]) -> Clip | None:
    data_dir, entry, params, cache_dir = args
    bvh_path = data_dir / entry.path
    digest = clip_digest(bvh_path, params)
    try:
        kin = _cached(cache_dir / f"{digest}.npz", lambda: compute_kinematics(bvh_path, entry, params))
    except ClipTooShort:
        return None
    return Clip(entry, kin, digest)


_STIFF_KNEE = "stiffknee"


def braced_side(clip: Clip) -> str:
    """The leg ("left" or "right") whose knee a ``stiff_knee_variants`` clip braces."""
    kind, side, _ = clip.variant.split("-")
    if kind != _STIFF_KNEE:
        raise ValueError(f"{clip.entry.path} is not a stiff-knee variant: {clip.variant!r}")
    return side


def _load_or_compute_variant(args: tuple[Path, Clip, KinematicsParams, Path, str, float]) -> Clip:
    data_dir, clip, params, cache_dir, side, keep = args
    variant = f"{_STIFF_KNEE}-{side}-{keep:.3f}"
    digest = f"{clip.digest}-{variant}"
    kin = _cached(
        cache_dir / f"{digest}.npz",
        lambda: compute_variant_kinematics(data_dir / clip.entry.path, clip.entry, params, side, keep),
    )
    return Clip(clip.entry, kin, digest, variant)


def stiff_knee_variants(
    data_dir: Path,
    clips: list[Clip],
    cache_dir: Path,
    keep_max: float,
    seed: int,
    params: KinematicsParams = KinematicsParams(),
    workers: int = 2,
) -> list[Clip]:
    """Each walking clip twice more, once with the left and once with the right knee braced, cached.

    The share of flexion kept is uniform in [0, ``keep_max``], drawn per clip and side from ``seed`` and the
    clip's digest, so the same config always builds the same variants.
    """
    jobs = []
    for clip in clips:
        if clip.entry.activity != "walk" or clip.variant:
            continue
        rng = np.random.default_rng([seed, int(clip.digest[:12], 16)])
        for side in LEG_CHAIN:
            jobs.append((data_dir, clip, params, cache_dir, side, round(float(rng.uniform(0.0, keep_max)), 3)))
    with ProcessPoolExecutor(max_workers=workers) as pool:
        variants = list(
            tqdm(pool.map(_load_or_compute_variant, jobs), total=len(jobs), desc="stiff-knee variants", unit="clip")
        )
    log.info("%d stiff-knee variants of %d walking clips", len(variants), len(jobs) // 2)
    return variants


def build_kinematics(
    data_dir: Path,
    entries: list[CatalogEntry],
    cache_dir: Path,
    params: KinematicsParams = KinematicsParams(),
    workers: int = 2,
) -> list[Clip]:
    """Segment kinematics of every entry, from the cache where possible, with a progress bar."""
    jobs = [(data_dir, e, params, cache_dir) for e in entries]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        loaded = list(
            tqdm(pool.map(_load_or_compute, jobs, chunksize=2), total=len(jobs), desc="kinematics", unit="clip")
        )
    clips = [c for c in loaded if c is not None]
    log.info(
        "kinematics of %d clips (cache %s); %d too short for the filter left out",
        len(clips),
        cache_dir,
        len(loaded) - len(clips),
    )
    return clips


def dataset_digest(clips: list[Clip]) -> str:
    """Digest of a set of clips (order-independent)."""
    return hashlib.sha256("|".join(sorted(c.digest for c in clips)).encode()).hexdigest()[:20]
