"""A skeleton family the jobs do not know, for the tests of a user's own mocap: the iClone CMU rig with its joints
renamed, and the mapping file a user would write for it."""

from __future__ import annotations

from pathlib import Path

from service.core.body import SKELETON_MAPPINGS


def lab_mapping() -> dict:
    """The iClone rig's mapping with its joints renamed: a skeleton family the job does not know."""
    built_in = SKELETON_MAPPINGS["cmu_iclone"]
    rename = lambda j: None if j is None else j.replace("CC_Base_", "Lab_")  # noqa: E731
    return {
        "name": "a_lab_rig",
        "metres_per_unit": built_in.metres_per_unit,
        "hips": [rename(j) for j in built_in.hips],
        "segments": {s: {"joint": rename(j), "distal": rename(d)} for s, (j, d) in built_in.segments.items()},
    }


def lab_clips(data_dir: Path, folder: Path, names: list[str]) -> None:
    """The named iClone clips, renamed into the lab rig, written to ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        text = (data_dir / "mocap/cmu_iclone" / f"{name}.bvh").read_text().replace("CC_Base_", "Lab_")
        (folder / f"{name}.bvh").write_text(text)
