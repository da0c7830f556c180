"""The label-free real-data alignment checks, on a sensor simulated from real walking mocap with a known alignment."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.assignment import is_moving, turns_about_vertical
from service.core.recordings import RealRecording, RealSensor
from service.core.segments import SEGMENTS
from service.core.windowing import sliding_windows
from training.data.catalog import mocap_entries
from training.i2s.data.imu_sim import alignment, imu_readings
from training.i2s.data.mocap import build_kinematics
from training.i2s.evaluate import evaluate_real, evaluate_real_alignment

SEGMENT = SEGMENTS.index("LeftLowerLeg")


def _simulated_recording(data_dir: Path, cache: Path, segment: int) -> tuple[RealRecording, np.ndarray]:
    """A 'recording' of one sensor on ``segment`` at a known eq. 8 alignment over the cmu_07 walking clips."""
    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"]
    R_true = alignment(segment, np.radians(135.0), np.radians(45.0))
    readings = []
    for clip in build_kinematics(data_dir, entries, cache):
        parts = (clip.kin.lin_acc_mps2, clip.kin.up_mps2, clip.kin.gyr_rads, clip.kin.ang_acc_rads2)
        readings.append(imu_readings(*(a[None, :, segment] for a in parts), R_true)[0])
    sensor = RealSensor(SEGMENTS[segment], np.concatenate(readings).astype(np.float32), segment)
    return RealRecording(f"sim/{SEGMENTS[segment]}", "sim", "cmu_07", "walk", [sensor]), R_true[0]


@pytest.fixture(scope="module")
def recording(data_dir: Path, kinematics_cache: Path) -> tuple[RealRecording, np.ndarray]:
    """A 'recording' of one lower-leg sensor at a known eq. 8 alignment over the cmu_07 walking clips, end to end."""
    return _simulated_recording(data_dir, kinematics_cache, SEGMENT)


def _constant(R: np.ndarray):
    q = Rotation.from_matrix(R).as_quat(scalar_first=True).astype(np.float32)
    return lambda windows: np.broadcast_to(q, (len(windows), len(SEGMENTS), 4)).copy()


def test_window_joint_answers_fix_a_shared_favourite_at_each_moment(recording) -> None:
    """Two sensors both favour the shank; the one that favours it less is the thigh. Each window alone gets half
    right; one-to-one at each moment and over the recording get all right."""
    rec, _ = recording
    shank = rec.sensors[0]
    thigh = RealSensor("thigh", shank.imu * np.array([1, 1, 1, 0.5, 0.5, 0.5], dtype=np.float32), SEGMENT + 1)
    typical = np.linalg.norm(shank.imu[:, 3:], axis=1).mean()

    def predict(windows: np.ndarray) -> np.ndarray:  # the faster a window turns, the surer it is a shank
        x = np.linalg.norm(windows[..., 3:], axis=-1).mean(axis=1)
        probs = np.full((len(windows), len(SEGMENTS)), 0.01, dtype=np.float32)
        probs[:, SEGMENT] = 0.5 + 0.4 * x / (x + typical)
        probs[:, SEGMENT + 1] = 0.95 - probs[:, SEGMENT]
        return probs

    two = RealRecording("sim/two", "sim", "cmu_07", "walk", [shank, thigh])
    m, cm = evaluate_real(predict, [two])
    assert m["real_n_windows"] > 10
    assert m["real_accuracy"] == pytest.approx(0.5, abs=0.05)
    assert m["real_window_joint_accuracy"] == 1.0
    assert m["window_joint_accuracy/sim/two"] == m["real_window_joint_accuracy"]
    assert m["real_joint_assignment_correct_fraction"] == 1.0
    assert cm[SEGMENT + 1, SEGMENT] > 0  # the confusion matrix keeps the windows' own answers


def test_sensors_that_swing_together_find_the_feet_sides(data_dir: Path, kinematics_cache: Path) -> None:
    """Both feet and the left shank of one simulated walk (cmu_07, held out of the swing fit). Each foot's windows
    cannot tell left from right (equal probabilities), the shank is sure of itself: per moment alone the feet are
    a coin toss; weighing how the sensors swing (``real_window_joint_swing_*``) puts the foot that swings with the
    shank on its side."""
    names = ("LeftFoot", "LeftLowerLeg", "RightFoot")
    sensors = [_simulated_recording(data_dir, kinematics_cache, SEGMENTS.index(n))[0].sensors[0] for n in names]
    feet = [SEGMENTS.index("LeftFoot"), SEGMENTS.index("RightFoot")]

    kinds = iter(["foot", "shank", "foot"])  # evaluate_real predicts each sensor's moving windows in one call

    def predict(windows: np.ndarray) -> np.ndarray:
        probs = np.full((len(windows), len(SEGMENTS)), 0.01, dtype=np.float32)
        if next(kinds) == "shank":
            probs[:, SEGMENT] = 0.9
        else:
            probs[:, feet] = 0.45  # a foot, either side
        return probs

    m, _ = evaluate_real(predict, [RealRecording("sim/three", "sim", "cmu_07", "walk", sensors)])
    assert m["window_joint_accuracy/sim/three"] < 0.9  # the feet by chance
    assert m["real_window_joint_swing_accuracy"] > 0.97
    assert m["window_joint_swing_accuracy/sim/three"] == m["real_window_joint_swing_accuracy"]
    # Over the whole recording the same: without the swing the feet's sides are a coin toss, with it both right.
    assert m["real_joint_assignment_swing_correct_fraction"] == 1.0


def test_declared_worn_segments_keep_a_favourite_that_no_sensor_wears_out(recording) -> None:
    """Both sensors favour the thigh of the other leg, which neither wears. Per moment over seven segments one of
    them takes it; declared (the recording's own segments, ``real_window_joint_worn_*``) both are right."""
    rec, _ = recording
    shank = rec.sensors[0]
    thigh = RealSensor("thigh", shank.imu * np.array([1, 1, 1, 0.5, 0.5, 0.5], dtype=np.float32), SEGMENT + 1)
    typical = np.linalg.norm(shank.imu[:, 3:], axis=1).mean()
    elsewhere = SEGMENTS.index("RightUpperLeg")

    def predict(windows: np.ndarray) -> np.ndarray:
        x = np.linalg.norm(windows[..., 3:], axis=-1).mean(axis=1)
        probs = np.full((len(windows), len(SEGMENTS)), 0.01, dtype=np.float32)
        probs[:, elsewhere] = 0.5
        probs[:, SEGMENT] = 0.2 + 0.2 * x / (x + typical)
        probs[:, SEGMENT + 1] = 0.45 - probs[:, SEGMENT]
        return probs

    m, _ = evaluate_real(predict, [RealRecording("sim/two", "sim", "cmu_07", "walk", [shank, thigh])])
    assert m["real_window_joint_accuracy"] == pytest.approx(0.5, abs=0.05)
    assert m["real_window_joint_worn_accuracy"] == 1.0
    assert m["window_joint_worn_accuracy/sim/two"] == 1.0
    assert m["real_window_joint_worn_accuracy_ignoring_side"] == 1.0
    # Body parts declared, sides not (``real_window_joint_part_*``): the thigh may be either thigh and takes the
    # favourite; the shank has no such pull. So exactly the shank's moving windows are right.
    n_moving = [int(is_moving(sliding_windows(s.imu)).sum()) for s in (shank, thigh)]
    assert m["real_window_joint_part_accuracy"] == pytest.approx(n_moving[0] / sum(n_moving))
    assert m["window_joint_part_accuracy/sim/two"] == m["real_window_joint_part_accuracy"]


def test_body_joint_assignment_resolves_each_body_and_skips_a_cut_one() -> None:
    from training.i2s.evaluate import body_joint_assignment

    eye = np.eye(len(SEGMENTS))
    favourite = np.log(np.clip(0.5 * eye + 0.5 / len(SEGMENTS), 1e-12, 1))  # row k favours class k
    body_a = favourite.copy()
    body_a[1] = np.log(np.full(len(SEGMENTS), 0.1) + 0.3 * eye[0])  # favours class 0, which row 0 favours more
    log_probs = np.concatenate([body_a, favourite[:3]])
    body = np.array([5] * 7 + [9] * 3)
    out = body_joint_assignment(body, log_probs)
    assert out[:7].tolist() == list(range(7)) and out[7:].tolist() == [-2] * 3


def test_simulated_window_joint_accuracy_gets_no_help_from_row_order(data_dir: Path, kinematics_cache) -> None:
    """A model that answers the same for every window gives one-to-one answers decided by ties: a body's rows are
    shuffled before they are assigned, so about one in seven is right, as for a guess."""
    from training.i2s.data.windows import Augmentation
    from training.i2s.evaluate import evaluate_simulated

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:1]
    clips = build_kinematics(data_dir, entries, kinematics_cache)

    def always_left_shank(imu: np.ndarray) -> np.ndarray:
        return np.eye(len(SEGMENTS), dtype=np.float32)[np.full(len(imu), SEGMENT)]

    result = evaluate_simulated(always_left_shank, "assignment", clips, Augmentation(), max_windows=7 * 64 * 20 + 5)
    assert result.metrics["accuracy"] == pytest.approx(1 / 7, abs=1e-3)
    assert result.metrics["window_joint_accuracy"] == pytest.approx(1 / 7, abs=0.03)


def test_the_true_alignment_is_stable_and_upright(recording) -> None:
    rec, R_true = recording
    m = evaluate_real_alignment(_constant(R_true), [rec])
    assert m["real_alignment_n_windows"] > 10
    assert m["real_alignment_spread_median_deg"] < 1e-3
    assert m["real_leg_up_axis_angle_median_deg"] < 25.0, m  # the shank leans in gait: 19° here


def test_a_sensor_whose_answers_flip_by_a_half_turn_reads_its_share_of_flipped_windows(recording) -> None:
    """Every third window answered a half turn about the segment's z away, the first among them: the larger mode is
    the mean, and a third of the windows read as half turns, for the sensor's body part and over all; a stream's
    settled answer faces the other way only over the first windows."""
    rec, R_true = recording
    q = Rotation.from_matrix(R_true).as_quat(scalar_first=True)
    q_turned = (Rotation.from_euler("z", 180, degrees=True) * Rotation.from_matrix(R_true)).as_quat(scalar_first=True)

    def flipping(windows: np.ndarray) -> np.ndarray:
        out = np.broadcast_to(q, (len(windows), len(SEGMENTS), 4)).copy()
        out[::3] = q_turned
        return out.astype(np.float32)

    steady = evaluate_real_alignment(_constant(R_true), [rec])
    assert steady["real_half_turn_share"] == 0.0 and steady["real_half_turn_share/lower_leg"] == 0.0
    m = evaluate_real_alignment(flipping, [rec])
    n = m["real_alignment_n_windows"]
    assert m["real_half_turn_share/lower_leg"] == pytest.approx(np.ceil(n / 3) / n)
    assert m["real_half_turn_share"] == m["real_half_turn_share/lower_leg"]
    # Live, the settled answer faces the other way only while the first (turned) window leads: a few windows.
    assert steady["real_live_half_turn_share"] == 0.0
    assert 0.0 < m["real_live_half_turn_share/lower_leg"] * n <= 3


def test_the_true_foot_alignment_is_flat_and_a_tilted_one_is_not(data_dir: Path, kinematics_cache: Path) -> None:
    """The functional foot frame's z is up while the foot is flat, so the true alignment of a simulated foot
    sensor maps the sensor's slowest-quarter specific force close to +z (3.3° here: the flat foot's roll is what is
    left); 20° wrong about the segment's y (pitch) reads 18.4°."""
    rec, R_true = _simulated_recording(data_dir, kinematics_cache, SEGMENTS.index("RightFoot"))
    true = evaluate_real_alignment(_constant(R_true), [rec])
    assert true["real_foot_flat_up_angle_median_deg"] < 6.0, true
    assert "real_leg_up_axis_angle_median_deg" not in true  # no leg sensor: no leg figure
    pitched = Rotation.from_euler("y", 20, degrees=True).as_matrix() @ R_true
    off = evaluate_real_alignment(_constant(pitched), [rec])["real_foot_flat_up_angle_median_deg"]
    assert off > 15.0, off


def test_the_nominal_frame_check_reads_the_difference_and_its_heading(data_dir: Path, kinematics_cache: Path) -> None:
    """A foot sensor whose dataset gives a nominal frame: a model that predicts exactly that frame reads 0°, one that
    predicts it turned by 15° about z reads 15° with a heading of +15°, and a half turn about z reads 180°."""
    rec, R_true = _simulated_recording(data_dir, kinematics_cache, SEGMENTS.index("LeftFoot"))
    sensor = dataclasses.replace(rec.sensors[0], nominal_frame=R_true)
    rec = dataclasses.replace(rec, sensors=[sensor])
    key = f"nominal_frame_heading_deg/{rec.name}/LeftFoot"
    exact = evaluate_real_alignment(_constant(R_true), [rec])
    assert exact["real_nominal_frame_angle_median_deg"] < 1e-3 and abs(exact[key]) < 1e-3
    for turn, angle in ((15.0, 15.0), (180.0, 180.0)):
        turned = Rotation.from_euler("z", turn, degrees=True).as_matrix() @ R_true
        m = evaluate_real_alignment(_constant(turned), [rec])
        assert m["real_nominal_frame_angle_median_deg"] == pytest.approx(angle, abs=1e-3)
        assert abs(m[key]) == pytest.approx(turn, abs=1e-3)
    plain = dataclasses.replace(rec, sensors=[dataclasses.replace(sensor, nominal_frame=None)])
    assert "real_nominal_frame_angle_median_deg" not in evaluate_real_alignment(_constant(R_true), [plain])


def test_a_tilted_alignment_fails_the_up_axis_check(recording) -> None:
    rec, R_true = recording
    tilted = Rotation.from_euler("x", 90, degrees=True).as_matrix() @ R_true  # 90° wrong about segment x
    assert evaluate_real_alignment(_constant(tilted), [rec])["real_leg_up_axis_angle_median_deg"] > 60.0


def test_unstable_predictions_fail_the_spread_check(recording) -> None:
    rec, _ = recording
    rng = np.random.default_rng(0)

    def random_rotations(windows: np.ndarray) -> np.ndarray:
        q = Rotation.random(len(windows) * len(SEGMENTS), random_state=rng).as_quat(scalar_first=True)
        return q.reshape(len(windows), len(SEGMENTS), 4).astype(np.float32)

    assert evaluate_real_alignment(random_rotations, [rec])["real_alignment_spread_median_deg"] > 60.0


def test_walking_legs_swing_and_a_leg_turned_about_the_vertical_does_not(recording) -> None:
    """Simulated walking (any mounting) swings about a horizontal axis; the same window with a turn rate about
    the mean specific force added dominates that axis and is flagged."""
    from service.core.windowing import sliding_windows

    windows = sliding_windows(recording[0].sensors[0].imu)
    assert turns_about_vertical(windows).mean() < 0.05
    up = windows[..., :3].mean(axis=1)
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    twisting = windows.copy()
    twisting[..., 3:] += 8.0 * np.sin(np.linspace(0.0, 12.0, windows.shape[1]))[None, :, None] * up[:, None, :]
    assert turns_about_vertical(twisting).mean() > 0.95
    assert turns_about_vertical(windows[:0]).shape == (0,)


def test_population_offset_baseline_is_small_on_its_own_subject_and_across_subjects_with_functional_frames(
    data_dir: Path, kinematics_cache: Path
) -> None:
    """Fitted and scored on the same subject's walking, the untrained reference (canonical frame ⊗ mean offset)
    reads under 2° (measured 0.6°). Fitted on another subject it reads 2.5° with the functional segment frames
    (``service.core.skeleton.functional_correction``); with the geometric frames alone it read 6.6°, the offset
    between a subject's skeleton-fitted frames and its motion being the subject's own."""
    from training.i2s.data.windows import Augmentation
    from training.i2s.evaluate import population_offset_baseline

    walks = mocap_entries(data_dir, ["walk"])
    own = build_kinematics(data_dir, [e for e in walks if e.group == "cmu_07"][:2], kinematics_cache)
    other = build_kinematics(data_dir, [e for e in walks if e.group == "cmu_05"][:2], kinematics_cache)
    same = population_offset_baseline(own, own, Augmentation(alignment="grid"), n_fit_windows=7_000)
    assert same["mean_angle_error_deg"] < 2.0, same["mean_angle_error_deg"]
    for leg in ("LeftUpperLeg", "LeftLowerLeg", "RightUpperLeg", "RightLowerLeg"):
        assert max(same[f"{leg}_ax{ax}_mean_deg"] for ax in range(3)) < 3.0, leg
    across = population_offset_baseline(other, own, Augmentation(alignment="grid"), n_fit_windows=7_000)
    assert same["mean_angle_error_deg"] < across["mean_angle_error_deg"] < 3.5, across["mean_angle_error_deg"]


def test_the_braced_knee_evaluation_scores_the_braced_shank_and_foot_only(data_dir: Path, kinematics_cache) -> None:
    """A model that answers LeftLowerLeg for everything is right on exactly the left-braced shanks: a quarter of
    the scored windows (shank and foot of each braced leg, both legs braced once per clip)."""
    from service.core.windowing import HOP_SAMPLES, WINDOW_SAMPLES
    from training.i2s.data.mocap import stiff_knee_variants
    from training.i2s.data.windows import Augmentation
    from training.i2s.evaluate import evaluate_braced_knees

    entries = [e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07"][:1]
    variants = stiff_knee_variants(
        data_dir, build_kinematics(data_dir, entries, kinematics_cache), kinematics_cache, 0.4, 0
    )
    left_shank = SEGMENTS.index("LeftLowerLeg")

    def always_left_shank(imu: np.ndarray) -> np.ndarray:
        return np.eye(len(SEGMENTS), dtype=np.float32)[np.full(len(imu), left_shank)]

    result = evaluate_braced_knees(always_left_shank, variants, Augmentation())
    n_windows = len(range(0, variants[0].n_samples - WINDOW_SAMPLES + 1, HOP_SAMPLES))
    assert result.metrics["n_windows"] == 2 * 2 * 64 * n_windows
    assert result.metrics["accuracy"] == pytest.approx(0.25)
    assert result.metrics["recall_LeftLowerLeg"] == 1.0 and result.metrics["recall_LeftFoot"] == 0.0
    assert set(np.unique(result.segment)) == {
        SEGMENTS.index(n) for n in ("LeftFoot", "LeftLowerLeg", "RightLowerLeg", "RightFoot")
    }


def _write_csv(path: Path, imu: np.ndarray) -> None:
    """``imu`` (contract units, 60 Hz) as a user's file: a time column, acc in g, gyr in deg/s."""
    t = np.arange(len(imu)) / 60.0
    rows = np.column_stack([t, imu[:, :3] / 9.80665, np.degrees(imu[:, 3:])])
    np.savetxt(path, rows, delimiter=",", header="time,ax,ay,az,gx,gy,gz", comments="")


def test_evaluate_csv_scores_ones_own_files_as_the_reader_does(data_dir: Path, tmp_path: Path) -> None:
    """`evaluate-csv` on gaitmap's 4 × 10 m walk written out as two CSV files in g and deg/s with a time column
    prints what `evaluate_real` gives on the recording read from the data directory; bad arguments are refused
    with a message naming what was expected."""
    from typer.testing import CliRunner

    from service.core.recordings import read_recording
    from training.cli import app
    from training.i2s.evaluate import onnx_predictor

    models = Path(__file__).resolve().parents[3] / "mlflow_snapshot" / "models"  # 1.8.0 is archived, not served
    rec = read_recording(data_dir, "gaitmap_foot/imu_sample_ic_stride")
    args = ["evaluate-csv", "--rate", "60", "--acc-unit", "g", "--gyr-unit", "deg/s", "--skip-columns", "1"]
    args += ["--models", str(models), "--assignment", "1.8.0"]
    for s in rec.sensors:
        _write_csv(tmp_path / f"{s.sensor_id}.csv", s.imu)
        args += ["--sensor", f"{SEGMENTS[s.segment]}={tmp_path / s.sensor_id}.csv"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    want, _ = evaluate_real(onnx_predictor(models / "i2s_assignment/1.8.0/model.onnx"), [rec])
    for key in ("real_accuracy", "real_window_joint_accuracy", "real_window_joint_worn_accuracy"):
        line = f"{key}: {want[key]:.4f} (ignoring left/right {want[key + '_ignoring_side']:.4f})"
        assert line in result.output, (line, result.output)
    assert f"(body parts declared): {want['real_window_joint_part_accuracy']:.4f}" in result.output
    assert "real_foot_flat_up_angle_median_deg" in result.output

    short = tmp_path / "short.csv"
    _write_csv(short, rec.sensors[0].imu[:100])
    (tmp_path / "five.csv").write_text("a,b,c,d,e\n1,2,3,4,5\n")
    for bad, fragment in (
        (["--sensor", f"Head={short}"], "SEGMENT=PATH with SEGMENT one of"),
        (["--sensor", f"LeftFoot={short}", "--sensor", f"LeftFoot={short}"], "one sensor per segment"),
        (["--sensor", f"LeftFoot={tmp_path / 'five.csv'}"], "got 5 column(s)"),
        (["--sensor", f"LeftFoot={short}"], "moving 128-sample window"),
    ):
        # a wide terminal, so that rich does not wrap the message inside its box
        out = CliRunner().invoke(
            app, ["evaluate-csv", "--rate", "60", "--skip-columns", "1", *bad], env={"COLUMNS": "400"}
        )
        assert out.exit_code == 2 and fragment in out.output, out.output


def test_int8_calibration_windows_come_from_the_named_recordings_only(data_dir: Path) -> None:
    """`quantize --calibrate-on real` draws its windows from a model's real training recordings: for a fold, never
    the person it is scored on."""
    from service.core.recordings import read_recording
    from training.i2s.quantize import real_calibration_windows

    name = "gaitmap_foot/imu_sample_ic_stride"
    every = np.concatenate(
        [
            sliding_windows(s.imu.astype(np.float32))
            for s in read_recording(data_dir, name).sensors
            if s.segment is not None
        ]
    )
    drawn = real_calibration_windows([name], data_dir, 10**6)  # more than there are: all of them, in order
    np.testing.assert_array_equal(drawn, every)
    some = real_calibration_windows([name], data_dir, 16)
    assert len(some) == 16 and all((every == w).all(axis=(1, 2)).any() for w in some)
    with pytest.raises(ValueError, match="trained on no real recording"):
        real_calibration_windows([], data_dir, 16)


def test_quantize_says_what_it_needs(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from training.cli import app

    served = Path(__file__).resolve().parents[3] / "onnx_models" / "i2s_assignment"
    newest = sorted(served.iterdir(), key=lambda p: tuple(int(x) for x in p.name.split(".")))[-1]
    for args, fragment in (
        ([str(newest)], "name the --version to write (or --loso-run"),
        ([str(newest), "--version", "9.9.9", "--calibrate-on", "mocap"], "one of simulated, real; got 'mocap'"),
        ([str(tmp_path), "--version", "9.9.9"], "is not a shipped model folder"),
    ):
        out = CliRunner().invoke(app, ["quantize", *args], env={"COLUMNS": "400"})
        assert out.exit_code == 2 and fragment in out.output, out.output
    assert not (served / "9.9.9").exists()
