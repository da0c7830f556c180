"""A user's own motion capture on the canonical body: BVH files or folders of them, any skeleton family through a
mapping file, each skeleton in the segment frames of the training rig it is, or fitted on its own walks as the
catalogue fits a rig's. ``evaluate-pose``, ``evaluate-flex`` and pose training on one's own mocap (``data.own``)
read them here."""

from __future__ import annotations

import functools
import hashlib
import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from service.core.body import (
    MappingError,
    NoStanceError,
    check_trunk_axes,
    load_mapping,
    read_clip_offsets,
    rig_offsets,
)
from service.core.bvh import BvhFormatError, read_bvh_header
from training.data.catalog import mocap_entries
from training.pose.data import HINGE_CLIPS, MotionClip, build_rig_offsets, hinge_twisted, load_motion, rig_key

log = logging.getLogger(__name__)


def user_clips(
    paths: list[Path],
    mapping_file: Path | None,
    limb_twist: str = "rig",
    data_dir: Path | None = None,
    cache_dir: Path | None = None,
    skipped: list[dict[str, str]] | None = None,
    trunk_axes: str = "spine",
) -> list[MotionClip]:
    """BVH files (plain or .gz), or folders of them, on the canonical body at 60 Hz; the activity is the folder's
    name. Without a mapping file the skeleton must be one of the known families. The files of one skeleton
    (``_skeleton``: one rig, or one person of a family that fits a skeleton per person) share their segment frames:
    the training clips' where it is a rig of the data directory (``data_dir``, ``catalogue_rig``), else fitted on
    these files as the catalogue fits a rig's (``fitted_rig``); with ``limb_twist`` "hinge" the limbs turned so that
    the elbows' and knees' hinges lie along y (``training.pose.data.hinge_twisted``), with ``trunk_axes`` "thorax"
    the upper trunk read from the hip and shoulder joint centres (``service.core.body``). A file that cannot be scored
    (not BVH, shorter than ``MIN_USER_SECONDS``, a skeleton the mapping does not fit) is left out with the reason,
    appended to ``skipped`` and logged, unless no file can be: then its error is raised (a skeleton's that no
    mapping fits before a file's that cannot be read)."""
    check_trunk_axes(trunk_axes)
    mapping = load_mapping(mapping_file) if mapping_file else None
    files, walks = [], []
    for p in paths:
        found = bvh_files(p) if p.is_dir() else [p]
        files += found
        # a walk: a folder (below the one given) or file name that says so
        walks += [q for q in found if "walk" in (str(q.relative_to(p)) if p.is_dir() else q.name).lower()]
    if not files:
        raise ValueError(f"no .bvh or .bvh.gz files in {[str(p) for p in paths]}")
    errors: list[Exception] = []

    def leave_out(group: list[Path], exc: Exception) -> None:
        errors.append(exc)
        for f in group:
            log.warning("left out %s: %s", f, exc)
            if skipped is not None:
                skipped.append({"clip": str(f), "reason": str(exc)})

    rigs: dict[str, list[Path]] = {}
    bad: set[Path] = set()  # files left out while a skeleton's frames were fitted

    def unreadable(f: Path, exc: Exception) -> None:
        bad.add(f)
        leave_out([f], exc)

    for f in files:
        try:
            bvh, frames = read_bvh_header(f)
            seconds = frames * bvh.frame_time_s
            if seconds < MIN_USER_SECONDS:
                raise ValueError(f"{frames} frames, {seconds:.2f} s: shorter than {MIN_USER_SECONDS} s")
            rigs.setdefault(_skeleton(f), []).append(f)
        except (BvhFormatError, ValueError, OSError) as exc:
            leave_out([f], exc)
    if len(rigs) > 1:
        log.info("%d skeletons among the %d files: each has its own segment frames", len(rigs), len(files))
    offsets: dict[Path, np.ndarray] = {}
    for group in rigs.values():
        try:
            rig = None
            if mapping is None and data_dir is not None:
                rig = catalogue_rig(group, data_dir, cache_dir or Path(".cache/pose_motion"), limb_twist, trunk_axes)
            if rig is None:
                walked = [w for w in walks if w in group]
                rig = fitted_rig(group, walked, mapping, limb_twist, trunk_axes, unreadable)
            offsets |= dict.fromkeys(group, rig)
        except (MappingError, ValueError) as exc:  # a skeleton the mapping does not fit, no clip it can read
            leave_out([f for f in group if f not in bad], exc)
    clips = []
    for f in files:
        if f not in offsets or f in bad:
            continue
        try:
            motion = load_motion(f, "", 0, mapping, offsets[f])
        except (MappingError, ValueError, OSError) as exc:
            leave_out([f], exc)
            continue
        digest = hashlib.sha256(f.read_bytes()).hexdigest()[:20]
        clips.append(MotionClip(str(f), "user", f.parent.name, f.parent.name, motion, digest))
    if not clips:  # a skeleton no mapping fits says more than a broken file beside it
        raise next((e for e in errors if isinstance(e, MappingError)), errors[0])
    return clips


MIN_USER_SECONDS = 0.5  # a user's clip shorter than this is left out: too short to simulate sensors on


def bvh_files(folder: Path) -> list[Path]:
    """The BVH files (plain or .gz) in ``folder`` and below it, through linked folders too (``Path.rglob`` does
    not follow them before Python 3.13)."""
    found = []
    for root, _, names in os.walk(folder, followlinks=True):
        found += [Path(root) / n for n in names if n.endswith((".bvh", ".bvh.gz"))]
    return sorted(found)


def _skeleton(path: Path) -> str:
    """A BVH file's skeleton from its header: joint names, parents, channels and the bone offsets (to 1e-3 of its
    unit) of the joints without position channels (the root's OFFSET is where a take starts, and Bandai-Namco's
    position channels replace its joints' offsets)."""
    bvh, _ = read_bvh_header(path)
    h = hashlib.sha256()
    for j in bvh.joints:
        h.update(f"{j.name}|{j.parent}|{','.join(j.channels)}|".encode())
        if not any(c.endswith("position") for c in j.channels):
            h.update((np.round(j.offset, 3) + 0.0).tobytes())
    for j, end in sorted(bvh.end_sites.items()):
        h.update(f"end {j}|".encode() + (np.round(end, 3) + 0.0).tobytes())
    return h.hexdigest()


def catalogue_rig(
    files: list[Path], data_dir: Path, cache_dir: Path, limb_twist: str, trunk_axes: str = "spine"
) -> np.ndarray | None:
    """The segment offsets the training clips of the same rig got (``build_rig_offsets``: fitted on the rig's
    walks), where every file has a skeleton of exactly one whole-source rig of the data directory; else None. A
    user's clips of a rig the models trained on are then scored in exactly the frames they learned, whatever the
    clips do (fitted on a folder of sprints, the pelvis's and trunk's frames would take the sprint's lean)."""
    wanted = {_skeleton(f) for f in files}
    if len(wanted) != 1:
        return None
    rigs = _catalogue_skeletons(data_dir)
    matches = [rig for rig, (skeletons, _) in rigs.items() if wanted <= skeletons]
    if len(matches) != 1:
        if matches:
            log.info("the skeleton is that of %s alike: frames fitted on the clips", " and ".join(matches))
        return None
    [rig] = matches
    log.info("segment frames: the %s rig's, as its training clips had them", rig)
    return build_rig_offsets(data_dir, rigs[rig][1], cache_dir, limb_twist=limb_twist, trunk_axes=trunk_axes)[rig]


@functools.lru_cache(maxsize=4)
def _catalogue_skeletons(data_dir: Path) -> dict[str, tuple[set[str], list]]:
    """Per whole-source rig of the data directory (each cmu_raw file is its own person's skeleton, so not one),
    the skeletons of its files and its catalogue entries; read once per data directory (about 2 s)."""
    out: dict[str, tuple[set[str], list]] = {}
    for e in mocap_entries(data_dir):
        if rig_key(e) == e.source:
            skeletons, entries = out.setdefault(e.source, (set(), []))
            skeletons.add(_skeleton(data_dir / e.path))
            entries.append(e)
    return out


def fitted_rig(
    files: list[Path],
    walks: list[Path],
    mapping,
    limb_twist: str,
    trunk_axes: str = "spine",
    unreadable: Callable[[Path, Exception], None] | None = None,
) -> np.ndarray:
    """A rig's segment offsets fitted on ``files`` with ``build_rig_offsets``' rules (a rig's walks are the nearest
    to the neutral stance that defines the frames), on its ``walks`` where there are any (a training rig needs
    three, else all its clips; a user's folder has fewer, and one walk is nearer to neutral than any sprint), the
    clips whose feet stand flat somewhere (the foot frames are level there); where none does, the feet taken
    level where they move slowest. A file that cannot be read is handed to ``unreadable`` with its error and the
    rest fit the frames (without it, the error is raised); a ``MappingError`` always is: it holds for every file."""
    # the walks first; should none of them be readable, the other clips fit the frames
    chosen = walks + [f for f in files if f not in walks]
    if not walks:
        log.warning(
            "no clip is a walk (no folder or file name says so): the segment frames are fitted on all %d clips, so "
            "the pelvis's and trunk's frames take their mean lean; add walks of the same rig for neutral frames",
            len(files),
        )
    per_clip, no_stance, readable = [], [], []
    for f in chosen:
        if readable and walks and f not in walks:
            break  # a readable walk fitted them: the other clips are not for the frames
        try:
            per_clip.append(read_clip_offsets(f, mapping, trunk_axes=trunk_axes))
        except NoStanceError as exc:
            no_stance.append(exc)
        except MappingError:
            raise
        except (ValueError, OSError, np.linalg.LinAlgError) as exc:
            if unreadable is None:
                raise
            unreadable(f, exc)
            continue
        readable.append(f)
    chosen = readable
    if not chosen:
        raise ValueError(f"none of the {len(walks or files)} clips that would fit this skeleton's frames can be read")
    if not per_clip:  # no clip stands flat long enough (sprints, jumps): the feet level where they move slowest
        log.warning(
            "%s; so in none of these %d clips: each foot's frame is taken level where it moves slowest (its "
            "contact), an approximation: add a clip with walking or standing of the same rig for level feet",
            no_stance[0],
            len(chosen),
        )
        per_clip = [read_clip_offsets(f, mapping, feet_at_slowest=True, trunk_axes=trunk_axes) for f in chosen]
    offsets = rig_offsets(per_clip)
    if limb_twist == "hinge":
        offsets = hinge_twisted(offsets, chosen[:: max(1, len(chosen) // HINGE_CLIPS)][:HINGE_CLIPS], "", mapping)
    return offsets
