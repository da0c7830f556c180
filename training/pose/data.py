"""Mocap clips on the canonical body, at the model rate, cached on disk; the held-out-subject split.

Every BVH of the data directory (CMU li2018, iClone, raw, and both Bandai-Namco sets) is read through
``service.core.body`` with its family's mapping table, T-pose frames dropped, resampled to 60 Hz (slerp and cubic
spline: Bandai-Namco is 30 fps) and stored as float32 quaternions and positions, keyed by a digest of the file's
bytes, the rate, ``MOTION_VERSION`` (or its source's entry in ``SOURCE_MOTION_VERSIONS``) and its rig's segment
offsets (which the frame rules, ``limb_twist`` and ``trunk_axes``, decide)."""

from __future__ import annotations

import collections
import hashlib
import logging
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from service.core.body import (
    BODY_SEGMENTS,
    BodyMotion,
    SkeletonMapping,
    body_motion,
    check_trunk_axes,
    other_side,
    read_body_motion,
    read_clip_offsets,
    read_rig,
    resample_motion,
    rig_offsets,
)
from service.core.flex import azimuth_elevation_deg, hinge_in_proximal
from service.core.rotations import matrix_from_quat, quat_from_matrix
from training.data.catalog import CatalogEntry, is_bandai_namco, mocap_entries

log = logging.getLogger(__name__)

MOTION_VERSION = "5"  # 2: upright trunk frames for L5 and T8; 3: one set of segment offsets per rig; 4: from walks;
# 5: feet level in flat stance
# A source whose mapping changed since: only its clips are read again (the others keep their digests, and with them
# their simulated sessions). cmu_li2018 6: the hand is the palm, driven by the hand joint (it was the wrist joint,
# whose zero-length bone only twists, so li2018's hands had no wrist flexion).
SOURCE_MOTION_VERSIONS = {"cmu_li2018": "6"}
# A source's entry replaces MOTION_VERSION in its digest, so each entry must stay above it: bumping MOTION_VERSION to
# or past an entry drops that entry (every source is read again anyway), or its clips would keep stale caches.
if any(int(v) <= int(MOTION_VERSION) for v in SOURCE_MOTION_VERSIONS.values()):
    raise RuntimeError(
        f"SOURCE_MOTION_VERSIONS {SOURCE_MOTION_VERSIONS} must stay above MOTION_VERSION {MOTION_VERSION}"
    )
MODEL_RATE_HZ = 60.0
OWN_SOURCE = "own"  # a user's own motion capture (``data.own``)


@dataclass(frozen=True)
class MotionClip:
    """One clip on the canonical body at 60 Hz with where it comes from."""

    path: str
    source: str
    subject: str  # "" when the source names none (Bandai-Namco, most li2018 clips)
    activity: str
    motion: BodyMotion
    digest: str

    @property
    def group(self) -> str:
        return self.subject or f"{self.source}_unlabelled"


def _digest(path: Path, offsets: np.ndarray | None = None, source: str = "") -> str:
    h = hashlib.sha256(path.read_bytes())
    h.update(f"|{MODEL_RATE_HZ}|v{SOURCE_MOTION_VERSIONS.get(source, MOTION_VERSION)}".encode())
    if offsets is not None:
        # to 1e-5 (0.0006°) and without the sign of a zero: the offsets' noise-level entries (1e-17 to 1e-6, a third
        # of them negative zeros at 8 decimals) differ between numpy / scipy builds, and the digest names the clip
        # in the motion cache and in the registry's evaluation digest, which must not change with the build
        h.update((np.round(offsets, 5) + 0.0).tobytes())
    return h.hexdigest()[:20]


def rig_key(entry: CatalogEntry) -> str:
    """Clips that share one skeleton rig: a whole source, except cmu_raw, whose files are different people's
    ASF skeletons (``../shared/data/README.md``)."""
    return entry.path if entry.source == "cmu_raw" else entry.source


def load_motion(
    path: Path,
    source: str,
    skip_frames: int = 0,
    mapping: SkeletonMapping | None = None,
    offsets: np.ndarray | None = None,
) -> BodyMotion:
    """A BVH on the canonical body at the model rate, the first ``skip_frames`` (T-pose) dropped; ``offsets``:
    its rig's segment offsets (``service.core.body.rig_offsets``), else the clip's own."""
    motion = read_body_motion(path, mapping, source, offsets)
    return resample_motion(motion.crop(skip_frames), MODEL_RATE_HZ)


def _clip_offsets_job(args: tuple[Path, CatalogEntry, Path, str]) -> np.ndarray | None:
    data_dir, e, cache_dir, trunk_axes = args
    path = data_dir / e.path
    rule = "" if trunk_axes == "spine" else "-" + trunk_axes
    cached = cache_dir / "clip_offsets" / f"{_digest(path, source=e.source)}{rule}.npy"
    if cached.exists():
        return np.load(cached)
    try:
        off = read_clip_offsets(path, None, e.source, trunk_axes=trunk_axes)
    except Exception as exc:  # logged and left out of its rig's mean, as the clip itself is left out below
        log.warning("no offsets for %s: %s", e.path, exc)
        return None
    cached.parent.mkdir(parents=True, exist_ok=True)
    np.save(cached, off)
    return off


def build_rig_offsets(
    data_dir: Path,
    entries: list[CatalogEntry],
    cache_dir: Path,
    workers: int = 2,
    limb_twist: str = "rig",
    trunk_axes: str = "spine",
) -> dict:
    """Per rig (``rig_key``), the segment offsets of ``rig_offsets`` over the rig's walking clips in the catalogue
    (all its clips where fewer than three of its walks give offsets; never only ``entries``: the rig's frames must
    not depend on which clips a run selects). ``limb_twist`` "hinge": each arm and leg segment then turned about its
    long axis so that the elbow's (knee's) hinge lies along its y (``hinge_twisted``). ``trunk_axes``: the upper
    trunk's rule (``service.core.body.clip_offsets``); each clip's offsets are cached per rule."""
    check_trunk_axes(trunk_axes)
    everything = mocap_entries(data_dir)
    wanted = {rig_key(e) for e in entries}
    rig_entries = [e for e in everything if rig_key(e) in wanted]
    walk_count = collections.Counter(rig_key(e) for e in rig_entries if e.activity == "walk")

    def fitted(chosen: list[CatalogEntry]) -> list[tuple[CatalogEntry, np.ndarray]]:
        if not chosen:
            return []
        jobs = [(data_dir, e, cache_dir, trunk_axes) for e in chosen]
        with ProcessPoolExecutor(max_workers=workers) as pool:
            offs = pool.map(_clip_offsets_job, jobs, chunksize=8)
            offs = list(tqdm(offs, total=len(jobs), desc="rig frames", unit="clip"))
        return [(e, off) for e, off in zip(chosen, offs, strict=True) if off is not None]

    # Neutral stance defines the frames (docs/conventions.md); walking is the nearest to it that every rig has: a rig's
    # dances and raised arms would turn its arms' frames (iClone forearms by about 60° about their long axis). A
    # rig's other clips are read only where fewer than three of its walks give offsets.
    done = fitted([e for e in rig_entries if e.activity == "walk" or walk_count[rig_key(e)] < 3])
    walks = collections.Counter(rig_key(e) for e, _ in done if e.activity == "walk")
    # a rig with three walks of which fewer than three give offsets: its other clips too
    rest = [e for e in rig_entries if e.activity != "walk" and walk_count[rig_key(e)] >= 3 and walks[rig_key(e)] < 3]
    done += fitted(rest)
    per_rig: dict[str, list[np.ndarray]] = {}
    for e, off in done:
        if e.activity == "walk" or walks[rig_key(e)] < 3:
            per_rig.setdefault(rig_key(e), []).append(off)
    out = {rig: rig_offsets(v) for rig, v in per_rig.items()}
    if limb_twist == "hinge":
        walking = {}
        for e in rig_entries:
            if e.activity == "walk":
                walking.setdefault(rig_key(e), []).append(e)
        for rig in out:
            clips = walking.get(rig) or [e for e in rig_entries if rig_key(e) == rig]
            spread = clips[:: max(1, len(clips) // HINGE_CLIPS)][:HINGE_CLIPS]  # across the rig's styles and people
            out[rig] = hinge_twisted(out[rig], [data_dir / e.path for e in spread], clips[0].source)
    return out


HINGE_CLIPS = 24  # walking clips per rig that place its hinges
HINGE_LIMBS = {  # hinge (proximal, distal) → the segments turned with each side of it
    ("UpperArm", "ForeArm"): (("UpperArm",), ("ForeArm", "Hand")),
    ("UpperLeg", "LowerLeg"): (("UpperLeg",), ("LowerLeg",)),
}


def hinge_twisted(
    offsets: np.ndarray, paths: list[Path], source: str, mapping: SkeletonMapping | None = None
) -> np.ndarray:
    """A rig's offsets ``(S, 3, 3)`` with each limb segment turned about its own z (long axis) so that the hinge of
    the joint it forms lies along its y: the upper arm and forearm (and the hand with it) by the elbow's, the thigh
    and shank by the knee's, each the median azimuth over the rig's walking ``paths``
    (``service.core.flex.hinge_in_proximal``). The rigs' own frames differ about these axes by up to 42°
    (docs/pose.md)."""
    azimuths: dict[str, list[float]] = {}
    for path in paths:
        poses, rig_mapping, ends = read_rig(path, mapping, source)
        R = body_motion(poses, rig_mapping, ends, offsets).R_world_segment
        for side in ("Left", "Right"):
            for (proximal, distal), (near, far) in HINGE_LIMBS.items():
                p, d = BODY_SEGMENTS.index(side + proximal), BODY_SEGMENTS.index(side + distal)
                for segments, a, b in ((near, p, d), (far, d, p)):  # the axis in each side's own frame
                    axis, _ = hinge_in_proximal(R[:, a], R[:, b])
                    for segment in segments:
                        azimuths.setdefault(side + segment, []).append(azimuth_elevation_deg(axis)[0])
    out = offsets.copy()
    for segment, values in azimuths.items():
        k = BODY_SEGMENTS.index(segment)
        out[k] = offsets[k] @ Rotation.from_euler("z", float(np.median(values)), degrees=True).as_matrix()
    return out


def _save(path: Path, m: BodyMotion) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(
        tmp,
        q=quat_from_matrix(m.R_world_segment).astype(np.float32),
        origin=m.origin_m.astype(np.float32),
        mid=m.midpoint_m.astype(np.float32),
    )
    tmp.rename(path)


def _load(path: Path) -> BodyMotion:
    with np.load(path) as z:
        R = matrix_from_quat(z["q"].astype(np.float64))
        return BodyMotion(R, z["origin"].astype(np.float64), z["mid"].astype(np.float64), MODEL_RATE_HZ)


def _load_or_compute(args: tuple[Path, CatalogEntry, Path, np.ndarray | None]) -> MotionClip | None:
    data_dir, e, cache_dir, offsets = args
    path = data_dir / e.path
    digest = _digest(path, offsets, e.source)
    cached = cache_dir / f"{digest}.npz"
    if cached.exists():
        motion = _load(cached)
    else:
        try:
            motion = load_motion(path, e.source, e.tpose_frames, offsets=offsets)
        except Exception as exc:  # one unreadable clip must not stop a build of thousands; it is logged
            log.warning("skipping %s: %s", e.path, exc)
            return None
        _save(cached, motion)
        motion = _load(cached)  # the float32 round trip, so a fresh build and a cached one are identical
    return MotionClip(e.path, e.source, e.subject, e.activity, motion, digest)


def build_motions(
    data_dir: Path,
    entries: list[CatalogEntry],
    cache_dir: Path,
    workers: int = 2,
    min_frames: int = 32,
    limb_twist: str = "rig",
    trunk_axes: str = "spine",
) -> list[MotionClip]:
    """Every entry on the canonical body, from the cache where possible, with a progress bar; each rig's clips
    share one set of segment frames (``build_rig_offsets``)."""
    rigs = build_rig_offsets(data_dir, entries, cache_dir, workers, limb_twist, trunk_axes)
    jobs = [(data_dir, e, cache_dir, rigs.get(rig_key(e))) for e in entries]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        clips = list(tqdm(pool.map(_load_or_compute, jobs, chunksize=8), total=len(jobs), desc="mocap", unit="clip"))
    kept = [c for c in clips if c is not None and c.motion.n_frames >= min_frames]
    log.info("%d of %d clips on the canonical body (cache %s)", len(kept), len(jobs), cache_dir)
    return kept


def shipped_split_and_frames(training_data: dict) -> dict:
    """From a shipped model's ``training_data``, the data-config fields that rebuild the clips its run scored: the
    sources it trained on, its split and the segment frames it answers in ("rig" and "spine" where not named)."""
    td = training_data
    return {
        "sources": td.get("sources"),
        "test_subjects": td["test_subjects"],
        "val_subjects": td["validation_subjects"],
        "test_activities_of_unlabelled": td["test_unlabelled_clips"],
        "limb_twist": td.get("limb_twist", "rig"),
        "trunk_axes": td.get("trunk_axes", "spine"),
    }


def split_by_subject(
    clips: list[MotionClip], test_groups: list[str], val_groups: list[str], test_clips: list[str]
) -> tuple[list[MotionClip], list[MotionClip], list[MotionClip]]:
    """Train / validation / test by subject group, never by clip (``test_clips`` adds whole clips of unlabelled
    pools: the li2018 runs, whose performer is not named). Bandai-Namco (no actor ids) stays on the train side."""
    test = [c for c in clips if c.group in test_groups or c.path in test_clips]
    val = [c for c in clips if c.group in val_groups and c not in test]
    train = [c for c in clips if c not in test and c not in val]
    overlap = {c.group for c in train} & set(test_groups + val_groups)
    if overlap:
        raise ValueError(f"subject groups {sorted(overlap)} on both sides of the split")
    return train, val, test


def held_out_split(
    clips: list[MotionClip],
    test_subjects: list[str],
    val_subjects: list[str],
    test_activities_of_unlabelled: dict[str, list[str]],
) -> tuple[list[MotionClip], list[MotionClip], list[MotionClip]]:
    """``split_by_subject`` with whole clips of unlabelled pools held out by activity (the li2018 runs)."""
    held = [c.path for c in clips if not c.subject and c.activity in test_activities_of_unlabelled.get(c.source, [])]
    return split_by_subject(clips, test_subjects, val_subjects, held)


# Each segment's counterpart on the other side (itself on the midline), and the reflection y -> -y.
_OTHER_SIDE = np.array([BODY_SEGMENTS.index(other_side(s)) for s in BODY_SEGMENTS])
_LATERAL = np.array([1.0, -1.0, 1.0])
_FLIP = np.outer(_LATERAL, _LATERAL)  # (M R M)_ij = s_i R_ij s_j


def mirrored(clip: MotionClip) -> MotionClip:
    """The clip performed by the mirror-image body, left and right swapped (our addition to Zheng et al. 2021, as the
    I2S simulation's ``mirrored``).

    Reflecting the scene through a vertical plane, M = diag(1, -1, 1), is a valid motion under gravity. A left
    segment's frame (x anterior, y left, z up) becomes its right counterpart's, R' = M R M (a proper rotation), and
    every joint position p' = M p. Bandai-Namco's three actors are 97 % of the frames: their mirror images halve
    whatever side-to-side habit they have (a right knee held in abduction) before the network learns it as the body's.
    """
    m = clip.motion
    motion = BodyMotion(
        m.R_world_segment[:, _OTHER_SIDE] * _FLIP,
        m.origin_m[:, _OTHER_SIDE] * _LATERAL,
        m.midpoint_m[:, _OTHER_SIDE] * _LATERAL,
        m.sample_rate_hz,
    )
    return MotionClip(f"{clip.path}#mirror", clip.source, clip.subject, clip.activity, motion, f"{clip.digest}-mirror")


def seen_split(clips: list[MotionClip], share: float) -> tuple[list[MotionClip], list[MotionClip]]:
    """Training clips → (those trained on, those held back as "seen people"): other takes of the people and
    activities trained on, about ``share`` of the clips, chosen by each clip's digest (the same on every machine)."""
    held = [int(c.digest[:8], 16) / 16**8 < share for c in clips]
    return [c for c, h in zip(clips, held, strict=True) if not h], [c for c, h in zip(clips, held, strict=True) if h]


def dataset_digest(clips: list[MotionClip]) -> str:
    return hashlib.sha256("|".join(sorted(c.digest for c in clips)).encode()).hexdigest()[:20]


# How a pose run's validation figure is computed, part of the registry's evaluation digest: "served chunks" since
# runs evaluate an offline model as the service runs it (training.pose.config.served_chunks); versions tagged before
# were scored on whole clips, and ``evaluate-pose --validation --tag`` scores a shipped one again this way; with
# ``service.inference.pose.assembly``'s "+knee-hinges" where the answer's knees are hinges (since 2026-12-06, models
# in the hinge frames), "+elbow-planes" and "+neutral-wrists" where its elbows are also put in plane and its hands
# follow their forearms (since 2026-12-07).
POSE_EVALUATION = "served-chunks"


def pose_evaluation_digest(val_clips: list[MotionClip], assembled: str) -> str:
    """The registry's ``eval_digest`` of a pose validation figure: the clips and how they were scored (``assembled``:
    how the answer was put together, ``service.inference.pose.assembly``). A user's own
    clip (``data.own``) is named by its file, which says nothing of the segment frames it was read in (a mapping
    file, the motion version): its first frame's segment rotations stand for them."""
    own = [c for c in val_clips if c.source == OWN_SOURCE]
    frames = hashlib.sha256(b"".join(np.round(c.motion.R_world_segment[0], 4).tobytes() for c in own)).hexdigest()[:8]
    scoring = POSE_EVALUATION + assembled
    return f"{dataset_digest(val_clips)}|{scoring}" + (f"|own {frames}" if own else "")


def trains_on_bandai(clips: list[MotionClip]) -> bool:
    return any(is_bandai_namco(c.source) for c in clips)
