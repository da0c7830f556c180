"""Which clips a configuration uses, its leave-one-subject-out split, and the clip pack for training elsewhere.

A pack holds the segment kinematics of a configuration's clips with their catalogue entries and digests, so a
machine without the data directory (a GPU box, say) can run ``training.cli fit`` on exactly the clips, and the
split, that the tracked run will record.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from training.config import ExperimentConfig
from training.data.catalog import CatalogEntry, mocap_entries
from training.data.imu_sim import SegmentKinematics
from training.data.mocap import Clip, KinematicsParams, as_recorded, build_kinematics, stiff_knee_variants

_KIN_FIELDS = [f.name for f in dataclasses.fields(SegmentKinematics) if f.name != "sample_rate_hz"]


def load_clips(cfg: ExperimentConfig, data_dir: Path, cache_dir: Path) -> list[Clip]:
    """The config's clips, followed by their stiff-knee variants when ``augmentation.stiff_knee_share`` > 0."""
    params = KinematicsParams(cfg.data.sample_rate_hz, cfg.data.cutoff_hz, cfg.data.filter_order)
    clips = build_kinematics(data_dir, mocap_entries(data_dir, cfg.data.activities), cache_dir, params)
    aug = cfg.augmentation
    if aug.stiff_knee_share > 0:
        clips += stiff_knee_variants(data_dir, clips, cache_dir, aug.stiff_knee_keep_max, cfg.seed, params)
    return clips


def split_clips(
    clips: list[Clip], test_subjects: list[str], val_fraction: float, seed: int
) -> tuple[list[Clip], list[Clip], list[Clip]]:
    """LOSO split by subject group; the validation clips are a seeded fraction of the rest.

    Variants (``Clip.variant``) follow the clip they come from into training or validation and are left out of
    the test set, which is scored on the clips as recorded.
    """
    variants = [c for c in clips if c.variant]
    train, val, test = _split_recorded(as_recorded(clips), test_subjects, val_fraction, seed)
    val_sources = {c.digest for c in val}
    test_sources = {c.digest for c in test}
    train += [v for v in variants if v.source_digest not in val_sources | test_sources]
    val += [v for v in variants if v.source_digest in val_sources]
    return train, val, test


def _split_recorded(
    clips: list[Clip], test_subjects: list[str], val_fraction: float, seed: int
) -> tuple[list[Clip], list[Clip], list[Clip]]:
    test = [c for c in clips if c.entry.group in test_subjects]
    rest = [c for c in clips if c.entry.group not in test_subjects]
    missing = set(test_subjects) - {c.entry.group for c in test}
    if missing:
        raise ValueError(
            f"test subjects {sorted(missing)} have no clips; groups are {sorted({c.entry.group for c in clips})}"
        )
    order = np.random.default_rng(seed).permutation(len(rest))
    n_val = max(1, int(round(val_fraction * len(rest))))
    val = [rest[i] for i in order[:n_val]]
    return [rest[i] for i in order[n_val:]], val, test


def save_pack(clips: list[Clip], path: Path) -> Path:
    """Write clips (kinematics as float32, entries and digests) to one ``.npz``."""
    arrays: dict[str, np.ndarray] = {}
    for i, c in enumerate(clips):
        for name in _KIN_FIELDS:
            arrays[f"{i}/{name}"] = getattr(c.kin, name).astype(np.float32)
        arrays[f"{i}/sample_rate_hz"] = np.float64(c.kin.sample_rate_hz)
    meta = [{"entry": dataclasses.asdict(c.entry), "digest": c.digest, "variant": c.variant} for c in clips]
    arrays["meta"] = np.array(json.dumps(meta))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def load_pack(path: Path) -> list[Clip]:
    """The clips of ``save_pack``, in the same order (kinematics back in float64)."""
    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        return [
            Clip(
                CatalogEntry(**m["entry"]),
                SegmentKinematics(
                    **{name: z[f"{i}/{name}"].astype(np.float64) for name in _KIN_FIELDS},
                    sample_rate_hz=float(z[f"{i}/sample_rate_hz"]),
                ),
                m["digest"],
                m.get("variant", ""),
            )
            for i, m in enumerate(meta)
        ]
