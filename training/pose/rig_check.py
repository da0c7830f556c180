"""Do the rigs agree on how the limbs' segment frames are turned about their long axes?

A segment frame is its bone's frame times one offset per rig (``service.core.body``, fitted on the rig's walks): z
along the long axis, x anterior from the pelvis heading. About the long axis that leaves each rig's own notion of
neutral. An anatomical reference that every rig shares is the hinge of the joint below: the elbow flexes about an
axis that conventions.md's frames put along y (left) of the upper arm, the knee likewise in the thigh's frame. Where a
rig's hinge axis lies off y, turned about z by an azimuth, its upper arms (thighs) are turned by that azimuth
against an anatomical frame; two rigs whose azimuths differ score the same posture with that difference as error.
Where two rigs retargeted the same recording (li2018 and iClone), every segment can be compared directly
(``paired_trial_angles``).
"""

from __future__ import annotations

import collections
from pathlib import Path

import numpy as np

from service.core.body import BODY_SEGMENTS
from service.core.flex import azimuth_elevation_deg, hinge_in_proximal
from training.data.catalog import mocap_entries
from training.pose.data import HINGE_LIMBS, build_motions


def rig_hinge_table(
    data_dir: Path, cache_dir: Path, per_source: int = 12, seed: int = 0, workers: int = 2, limb_twist: str = "rig"
) -> str:
    """A markdown table: per source and limb, the median (and interquartile range) over ``per_source`` of its
    walking clips (drawn with ``seed``) of the hinge axis' azimuth and elevation in the proximal segment's frame,
    and the hinge's range of motion; the frames as ``limb_twist`` makes them (``training.pose.data``)."""
    by_source: dict[str, list] = collections.defaultdict(list)
    for entry in mocap_entries(data_dir, activities=["walk"]):
        by_source[entry.source].append(entry)
    rng = np.random.default_rng(seed)
    chosen = [
        entries[k]
        for entries in by_source.values()
        for k in sorted(rng.choice(len(entries), size=min(per_source, len(entries)), replace=False))
    ]
    rows: dict[tuple[str, str], list[tuple[float, float, float]]] = collections.defaultdict(list)
    for clip in build_motions(data_dir, chosen, cache_dir, workers, limb_twist=limb_twist):
        R = clip.motion.R_world_segment
        for side in ("Left", "Right"):
            for proximal, distal in HINGE_LIMBS:  # the elbow, the knee
                p, d = BODY_SEGMENTS.index(side + proximal), BODY_SEGMENTS.index(side + distal)
                axis, motion = hinge_in_proximal(R[:, p], R[:, d])
                rows[clip.source, side + proximal].append((*azimuth_elevation_deg(axis), motion))
    lines = [
        "| source | segment | clips | hinge azimuth from y (median, IQR) | elevation | hinge range |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for (source, segment), values in sorted(rows.items()):
        a = np.array(values)
        q1, med, q3 = np.percentile(a[:, 0], [25, 50, 75])
        lines.append(
            f"| {source} | {segment} | {len(a)} | {med:+.1f}° ({q1:+.0f}…{q3:+.0f}) | {np.median(a[:, 1]):+.1f}° | "
            f"{np.median(a[:, 2]):.0f}° |"
        )
    return "\n".join(lines)


def paired_trial_table(
    data_dir: Path, cache_dir: Path, workers: int = 2, limb_twist: str = "hinge", trunk_axes: str = "spine"
) -> str:
    """``paired_trial_angles`` as a markdown table."""
    apart = paired_trial_angles(data_dir, cache_dir, workers, limb_twist, trunk_axes)
    pairs = len(next(iter(apart.values())))
    lines = [f"| segment | li2018 against iClone, same trial ({pairs} pairs): median | range |", "| --- | --- | --- |"]
    for segment, a in apart.items():
        lines.append(f"| {segment} | {np.median(a):.1f}° | {a.min():.1f}…{a.max():.1f}° |")
    return "\n".join(lines)


def paired_trial_angles(
    data_dir: Path, cache_dir: Path, workers: int = 2, limb_twist: str = "hinge", trunk_axes: str = "spine"
) -> dict[str, np.ndarray]:
    """Per segment, how far apart (degrees, one per pair) li2018's and iClone's versions of the same CMU trial (the
    catalogue's "SAME CMU TRIAL" notes) hold it against the vertical and the pelvis's heading: the angle between
    the two clips' rotation means over the clip. The same person doing the same thing: what
    differs is how each retargeting placed the joints and how our per-rig frames read them, so this much of any
    held-out figure on one rig against a model that learned the other is convention, not error."""
    import re

    from scipy.spatial.transform import Rotation

    from training.data.catalog import read_catalog

    same = re.compile(r"SAME CMU TRIAL as (mocap/cmu_iclone/[0-9_]+\.bvh)")
    notes = {e.path: same.search(e.notes) for e in read_catalog(data_dir)}
    wanted = {p: m.group(1) for p, m in notes.items() if m}
    entries = [e for e in mocap_entries(data_dir) if e.path in wanted or e.path in wanted.values()]
    built = build_motions(data_dir, entries, cache_dir, workers, limb_twist=limb_twist, trunk_axes=trunk_axes)
    clips = {c.path: c for c in built}
    pelvis = BODY_SEGMENTS.index("Pelvis")

    def posture(path: str) -> Rotation:  # each segment's rotation mean over the clip, the pelvis's heading taken out
        R = clips[path].motion.R_world_segment
        x = R[:, pelvis, :, 0]
        heading = Rotation.from_rotvec(np.arctan2(x[:, 1], x[:, 0])[:, None] * [0.0, 0.0, 1.0]).as_matrix()
        rel = np.einsum("tji,tsjk->tsik", heading, R)
        return Rotation.concatenate([Rotation.from_matrix(rel[:, k]).mean() for k in range(len(BODY_SEGMENTS))])

    apart = np.degrees(
        [(posture(a).inv() * posture(b)).magnitude() for a, b in wanted.items() if a in clips and b in clips]
    )
    return {segment: apart[:, k] for k, segment in enumerate(BODY_SEGMENTS)}
