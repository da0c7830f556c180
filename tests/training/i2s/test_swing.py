"""How sensors worn together swing together: the table the per-moment answer weighs is what its fit gives."""

from __future__ import annotations

import pytest

from service.core.assignment import SWING, SWING_PAIR_TYPES


def test_the_served_swing_table_is_the_fit_on_the_training_clips(data_dir, kinematics_cache) -> None:
    from training.i2s.config import load_config
    from training.i2s.data.split import load_clips, split_clips
    from training.i2s.swing import fit_swing

    cfg = load_config("training/configs/i2s_assignment.yaml")
    train, _, _ = split_clips(
        load_clips(cfg, data_dir, kinematics_cache), cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed
    )
    fitted = fit_swing([c for c in train if not c.variant])
    assert set(fitted) == set(SWING_PAIR_TYPES)
    for name, (mean, std, n) in fitted.items():
        assert n >= 300, name
        assert SWING[name] == pytest.approx((mean, std), abs=6e-4), name
    # What the table says: one leg's foot swings with its shank and thigh, the two legs' feet take turns.
    assert SWING["same_leg-foot-lower_leg"][0] > 0.5 > -0.5 > SWING["both_legs-foot-foot"][0]
    assert SWING["same_leg-foot-upper_leg"][0] - SWING["both_legs-foot-upper_leg"][0] > 0.5


def test_on_real_people_a_left_leg_sensor_follows_the_pelvis_sway_and_a_right_one_the_other_way(data_dir) -> None:
    """``sway-fit``'s table over real recordings with a pelvis sensor (its frame as a stream knows it): every left leg
    class reads a positive mean z, every right one a negative one, each over at least 800 windows. The recordings:
    of the ten people who wear a pelvis sensor, every recording with thigh sensors and each other person's first
    (all 21 with a pelvis read alike, at twice the cost: ``python -m training.cli sway-fit``)."""
    from pathlib import Path

    from service.core.recordings import read_all_real
    from service.core.segments import SEGMENTS
    from service.inference.registry import load_models
    from training.i2s.swing import fit_sway, recording_laterals, sway_samples

    align = load_models(Path("onnx_models"), 1)["i2s_alignment"]
    pelvis, thighs = SEGMENTS.index("Pelvis"), {SEGMENTS.index("LeftUpperLeg"), SEGMENTS.index("RightUpperLeg")}
    recordings, people = [], set()
    for rec in read_all_real(data_dir):
        if all(s.segment != pelvis for s in rec.sensors):
            continue
        if rec.subject not in people or any(s.segment in thighs for s in rec.sensors):
            recordings.append(rec)
            people.add(rec.subject)
    fitted = fit_sway([sway_samples(rec, recording_laterals(rec, align.run)) for rec in recordings])
    assert set(fitted) == {f"{side}{part}" for side in ("Left", "Right") for part in ("Foot", "LowerLeg", "UpperLeg")}
    for name, (mean, std, n) in fitted.items():
        assert n >= 800 and std > 0, name
        assert (mean > 0.1) if name.startswith("Left") else (mean < -0.1), (name, mean)
