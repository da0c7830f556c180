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
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS
from training.data.catalog import mocap_entries
from training.pose.data import build_motions

HINGES = (("UpperArm", "ForeArm"), ("UpperLeg", "LowerLeg"))  # (proximal, distal): elbow, knee


def hinge_in_proximal(R_proximal: np.ndarray, R_distal: np.ndarray) -> tuple[np.ndarray, float]:
    """The hinge axis of a joint, in the proximal segment's frame, from both segments' world orientations ``(T, 3,
    3)``: the first principal axis of the relative rotation's rotation vectors about its mean (as
    ``service.core.flex.fit_hinge``, here composed on the left so that the axis is the proximal frame's), signed so
    that the larger excursion is positive (flexion); and that excursion's range (degrees, 1st to 99th percentile)."""
    rel = Rotation.from_matrix(np.einsum("tji,tjk->tik", R_proximal, R_distal))
    v = (rel * rel.mean().inv()).as_rotvec()
    axis = np.linalg.svd(v - v.mean(axis=0), full_matrices=False)[2][0]
    angle = v @ axis
    if np.percentile(angle, 99) - np.median(angle) < np.median(angle) - np.percentile(angle, 1):
        axis, angle = -axis, -angle
    return axis, float(np.degrees(np.percentile(angle, 99) - np.percentile(angle, 1)))


def azimuth_elevation_deg(axis: np.ndarray) -> tuple[float, float]:
    """How far a hinge axis lies from the frame's y: its turn about z from ±y (positive anticlockwise seen from
    above, the sign of y taken so that the axis points left) and its elevation out of the x-y plane."""
    a = axis if axis[1] >= 0 else -axis
    return float(np.degrees(np.arctan2(-a[0], a[1]))), float(np.degrees(np.arcsin(np.clip(a[2], -1.0, 1.0))))


def rig_hinge_table(data_dir: Path, cache_dir: Path, per_source: int = 12, seed: int = 0, workers: int = 2) -> str:
    """A markdown table: per source and limb, the median (and interquartile range) over ``per_source`` of its
    walking clips (drawn with ``seed``) of the hinge axis' azimuth and elevation in the proximal segment's frame,
    and the hinge's range of motion."""
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
    for clip in build_motions(data_dir, chosen, cache_dir, workers):
        R = clip.motion.R_world_segment
        for side in ("Left", "Right"):
            for proximal, distal in HINGES:
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
