"""Do the rigs agree on how the limbs' segment frames are turned about their long axes?

A segment frame is its bone's frame times one offset per rig (``service.core.body``, fitted on the rig's walks): z
along the long axis, x anterior from the pelvis heading. About the long axis that leaves each rig's own notion of
neutral. An anatomical reference that every rig shares is the hinge of the joint below: the elbow flexes about an
axis that DESIGN.md §2's frames put along y (left) of the upper arm, the knee likewise in the thigh's frame. Where a
rig's hinge axis lies off y, turned about z by an azimuth, its upper arms (thighs) are turned by that azimuth
against an anatomical frame; two rigs whose azimuths differ score the same posture with that difference as error.
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
