"""Which clips a configuration uses, its leave-one-subject-out split, and the clip pack for training elsewhere.

A pack holds the segment kinematics of a configuration's clips with their catalogue entries and digests, and the
real recordings it trains on (``data.real_train_recordings``, Zimmermann et al. 2018 §4.3), so a machine without the
data directory (a GPU box, say) can run ``training.cli fit`` on exactly the clips, the split and the real windows that
the tracked run will record.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from service.core.recordings import RealRecording, RealSensor
from training.data.catalog import CatalogEntry, mocap_entries
from training.i2s.config import ExperimentConfig
from training.i2s.data.imu_sim import SegmentKinematics
from training.i2s.data.mocap import Clip, KinematicsParams, as_recorded, build_kinematics, stiff_knee_variants

_KIN_FIELDS = [f.name for f in dataclasses.fields(SegmentKinematics) if f.name != "sample_rate_hz"]


def load_clips(cfg: ExperimentConfig, data_dir: Path, cache_dir: Path) -> list[Clip]:
    """The config's clips, followed by their stiff-knee variants when ``augmentation.stiff_knee_share`` > 0."""
    params = KinematicsParams(cfg.data.sample_rate_hz, cfg.data.cutoff_hz, cfg.data.filter_order)
    entries = mocap_entries(data_dir, cfg.data.activities, cfg.data.sources)
    clips = build_kinematics(data_dir, entries, cache_dir, params)
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


def save_pack(clips: list[Clip], path: Path, recordings: list[RealRecording] | None = None) -> Path:
    """Write clips (kinematics as float32, entries and digests) and real recordings (readings as float32, the
    precision ``RealWindowSampler`` windows them at) to one ``.npz``."""
    arrays: dict[str, np.ndarray] = {}
    for i, c in enumerate(clips):
        for name in _KIN_FIELDS:
            arrays[f"{i}/{name}"] = getattr(c.kin, name).astype(np.float32)
        arrays[f"{i}/sample_rate_hz"] = np.float64(c.kin.sample_rate_hz)
    meta = [{"entry": dataclasses.asdict(c.entry), "digest": c.digest, "variant": c.variant} for c in clips]
    arrays["meta"] = np.array(json.dumps(meta))
    real = []
    for j, rec in enumerate(recordings or []):
        for k, sensor in enumerate(rec.sensors):
            arrays[f"real/{j}/{k}"] = sensor.imu.astype(np.float32)
        real.append(
            {
                "name": rec.name,
                "source": rec.source,
                "subject": rec.subject,
                "activity": rec.activity,
                "sensors": [{"sensor_id": s.sensor_id, "segment": s.segment} for s in rec.sensors],
            }
        )
    arrays["real_meta"] = np.array(json.dumps(real))
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


def load_pack_recordings(path: Path) -> list[RealRecording]:
    """The real recordings of ``save_pack`` (readings float32), in the same order; none in an older pack."""
    with np.load(path) as z:
        if "real_meta" not in z.files:
            return []
        return [
            RealRecording(
                m["name"],
                m["source"],
                m["subject"],
                m["activity"],
                [RealSensor(s["sensor_id"], z[f"real/{j}/{k}"], s["segment"]) for k, s in enumerate(m["sensors"])],
            )
            for j, m in enumerate(json.loads(str(z["real_meta"])))
        ]


def recordings_digest(recordings: list[RealRecording]) -> str:
    """Digest of real training recordings as the training windows them (names, labels, float32 readings);
    order-independent. The empty list has a digest too."""
    parts = []
    for rec in recordings:
        h = hashlib.sha256(rec.name.encode())
        for sensor in rec.sensors:
            h.update(f"|{sensor.sensor_id}|{sensor.segment}|".encode())
            h.update(np.ascontiguousarray(sensor.imu, dtype=np.float32).tobytes())
        parts.append(h.hexdigest())
    return hashlib.sha256("|".join(sorted(parts)).encode()).hexdigest()[:20]
