"""``POST /v1/pose/imu``: whole-body pose from raw sensor readings, calibrated as declared, by a still pose or by
the walk (I2S)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response

from service.api.routes import _Route, _settings, assign_windows, file_answer, infer_windows
from service.api.schemas import (
    AssignResponse,
    PoseImuRequest,
    PoseImuResponse,
    SegmentTrack,
    error_responses,
    file_responses,
)
from service.core.assignment import is_moving
from service.core.body import BODY_SEGMENTS, Body, body_bvh, feet_of
from service.core.bvh import format_bvh
from service.core.calibration import (
    CalibrationError,
    is_still,
    pelvis_heading_from_legs,
    pose_features,
    segment_readings,
    still_pose_calibration,
)
from service.core.joint_angles import ANGLE_CONVENTION, JOINT_COMPONENTS, answered_joints, joint_angles_deg
from service.core.opensim import format_opensim_storage
from service.core.resample import resample_quats, resample_uniform
from service.core.rotations import UNIT_QUAT_TOLERANCE, canonical_quat, is_unit_quaternion
from service.core.segments import SEGMENTS
from service.core.translation import RootTracker
from service.core.units import ACC_UNITS, GRAVITY_MPS2, GYR_UNITS, unit_warnings_over
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, WINDOW_SAMPLES, sliding_windows
from service.inference.pose import (
    MAX_POSE_FRAMES,
    MAX_POSE_IMU_RATE_HZ,
    MIN_POSE_IMU_RATE_HZ,
    PoseModel,
    covered_segments,
    fitting_models,
    general_first,
    measured_segments,
    pose_answer,
    whole_body,
)
from service.inference.predict import InputError, mean_alignment
from service.inference.velocity import VelocityModel, learned_velocity_model, world_velocity
from service.settings import Settings

router = APIRouter(route_class=_Route)

STILL_ACC_NORM_TOLERANCE_MPS2 = 1.5


def pose_models(request: Request) -> dict[str, PoseModel]:
    return request.app.state.pose_models


def choose_model(
    models: dict[str, PoseModel], segments: list[str], name: str | None, streaming: bool, extra: bool = False
) -> PoseModel:
    """The named model, else the one (offline unless ``streaming``) whose sensors are exactly ``segments``, a general
    one before one trained for a scenario. With ``extra`` (REST), sensors beyond a model's are allowed: without an
    exact match, the model that reads the most of them (the rest are answered as measured)."""
    if not models:
        raise HTTPException(503, "no imu_pose model is loaded")
    if name is not None:
        if name not in models:
            raise HTTPException(422, f"model: no pose model {name!r}; loaded: {sorted(models)}")
        model = models[name]
        missing = [s for s in model.spec.sensors if s not in segments]
        unused = [s for s in segments if s not in model.spec.sensors]
        if missing or (unused and not extra):
            raise HTTPException(
                422,
                f"sensors: {name} takes sensors on {model.spec.sensors}; got {segments} "
                f"(missing {missing}, not used {unused})",
            )
        return model
    kind = [m for m in general_first(models) if m.spec.streaming == streaming]
    fitting = fitting_models(kind, segments)
    if fitting and (extra or sorted(fitting[0].spec.sensors) == sorted(segments)):
        return fitting[0]
    placements = sorted({", ".join(m.spec.sensors) for m in models.values()})
    raise HTTPException(
        422,
        f"sensors: no {'streaming' if streaming else 'offline'} pose model takes sensors on {segments}; "
        f"the loaded models take [{'] or ['.join(placements)}]",
    )


@dataclass(frozen=True)
class Readings:
    """Validated raw readings at the model's rate: q (T, N, 4), acc (T, N, 3) m/s², the model's sensors first in its
    order, then the sensors it does not read (answered as measured) in the request's order, on ``segments``."""

    q_world_sensor: np.ndarray
    acc_mps2: np.ndarray
    gyr_rads: np.ndarray | None
    sensor_ids: list[str]
    segments: list[str]


def _array(rows: list[list[float]], width: int, where: str) -> np.ndarray:
    bad = next((len(r) for r in rows if len(r) != width), None)
    if bad is not None:
        raise InputError(f"{where}: every row needs {width} values, got a row of {bad}")
    x = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(x).all():
        row = int(np.argmin(np.isfinite(x).all(axis=1)))
        raise InputError(f"{where}[{row}]: values must be finite numbers, got NaN or Inf")
    return x


def read_sensors(body: PoseImuRequest, model: PoseModel) -> Readings:
    """The request's readings, validated, at 60 Hz, in ``model``'s order (``in_model_order``); every sensor's
    segment declared."""
    return in_model_order(read_request(body), model)


def in_model_order(r: Readings, model: PoseModel) -> Readings:
    """Readings in request order (every segment known) → the model's sensors first in its order, then the others
    in the request's."""
    order = [*model.spec.sensors, *(seg for seg in r.segments if seg not in model.spec.sensors)]
    idx = [r.segments.index(seg) for seg in order]
    gyr = None if r.gyr_rads is None else r.gyr_rads[:, idx]
    return Readings(r.q_world_sensor[:, idx], r.acc_mps2[:, idx], gyr, [r.sensor_ids[k] for k in idx], order)


def read_request(body: PoseImuRequest) -> Readings:
    """Every sensor's readings, validated, in contract units at 60 Hz, in the request's order; ``segments`` as
    declared (None where a sensor's is to be found from the walk)."""
    rate = body.sample_rate_hz
    if not MIN_POSE_IMU_RATE_HZ <= rate <= MAX_POSE_IMU_RATE_HZ:
        raise InputError(
            f"sample_rate_hz must be in [{MIN_POSE_IMU_RATE_HZ:g}, {MAX_POSE_IMU_RATE_HZ:g}], got {rate:g}"
        )
    declared = [s.segment for s in body.sensors if s.segment is not None]
    if len(set(declared)) != len(declared):
        raise InputError(f"sensors: one sensor per segment, got segments {[s.segment for s in body.sensors]}")
    ids = [s.sensor_id for s in body.sensors]
    if len(set(ids)) != len(ids):  # the answer's calibration is keyed by sensor_id
        raise InputError(f"sensors: sensor_id values must be unique, got {ids}")
    lengths = {len(s.q_world_sensor) for s in body.sensors} | {len(s.acc) for s in body.sensors}
    if len(lengths) != 1:
        raise InputError(
            f"sensors: every sensor needs the same number of q_world_sensor and acc rows, got {sorted(lengths)}"
        )
    n = lengths.pop()
    if n * 60.0 / rate > MAX_POSE_FRAMES:
        raise InputError(f"at most {MAX_POSE_FRAMES} frames at 60 Hz per request, got {n} samples at {rate:g} Hz")
    qs, accs, gyrs, ids = [], [], [], []
    for k, s in enumerate(body.sensors):
        where = f"sensors[{k}]"
        q = _array(s.q_world_sensor, 4, f"{where}.q_world_sensor")
        norm = np.linalg.norm(q, axis=1)
        off = np.abs(norm - 1.0) > UNIT_QUAT_TOLERANCE
        if off.any():
            i = int(np.argmax(off))
            raise InputError(
                f"{where}.q_world_sensor[{i}]: expected a unit quaternion (w, x, y, z), got norm {norm[i]:.3f}"
            )
        qs.append(canonical_quat(q))
        accs.append(_array(s.acc, 3, f"{where}.acc") * ACC_UNITS[body.acc_unit])
        if s.gyr is not None:
            if len(s.gyr) != n:
                raise InputError(f"{where}.gyr: {n} rows expected (as q_world_sensor), got {len(s.gyr)}")
            gyrs.append(_array(s.gyr, 3, f"{where}.gyr") * GYR_UNITS[body.gyr_unit])
        ids.append(s.sensor_id)
    q = np.stack(qs, axis=1)
    acc = np.stack(accs, axis=1)
    gyr = np.stack(gyrs, axis=1) if len(gyrs) == len(qs) else None
    if not np.isclose(rate, 60.0):
        q = np.stack([resample_quats(q[:, k], rate, 60.0) for k in range(q.shape[1])], axis=1)
        acc = resample_uniform(acc, rate, 60.0)[: len(q)]
        gyr = None if gyr is None else resample_uniform(gyr, rate, 60.0)[: len(q)]
        q = q[: len(acc)]
    return Readings(q, acc, gyr, ids, [s.segment for s in body.sensors])


def calibrate(body: PoseImuRequest, model: PoseModel, r: Readings, found: np.ndarray | None = None) -> np.ndarray:
    """``q_segment_sensor`` (N, 4) in the model's sensor order, by the request's method (``assignment``: ``found``,
    from ``walk_alignments``), the pelvis's turned to the legs' heading where asked (``calibration.pelvis_heading``,
    by default with ``assignment``)."""
    cal = body.calibration
    q = found if cal.method == "assignment" else _calibrate_by_method(body, model, r)
    if q is None:
        raise ValueError("calibration 'assignment' needs the alignments found from the walk (walk_alignments)")
    if (cal.pelvis_heading or ("legs" if cal.method == "assignment" else "alignment")) == "legs":
        try:
            n = len(model.spec.sensors)
            q = q.copy()
            q[:n], _ = pelvis_heading_from_legs(r.q_world_sensor[:, :n], q[:n], model.spec.sensors)
        except CalibrationError as exc:
            raise InputError(f"calibration.pelvis_heading: {exc}") from None
    return q


WALK = "calibration 'assignment'"


def walk_windows(request: Request, r: Readings) -> list[np.ndarray]:
    """Each sensor's I2S windows ``(n, 128, 6)`` of the request's walk. Every window of a long request would be more
    than the I2S routes take in one (and than a settled mean needs): they are spread over the request, at most an
    equal share of that limit per sensor."""
    others = [s for s in r.segments if s is not None and s not in SEGMENTS]
    if others:
        raise InputError(f"{WALK} aligns sensors on {list(SEGMENTS)} from their walk; sensors are also on {others}")
    if r.gyr_rads is None:
        raise InputError(f"{WALK}: every sensor's gyr is needed (the alignment reads acc and gyr)")
    if len(r.acc_mps2) < WINDOW_SAMPLES:
        raise InputError(
            f"{WALK}: at least {WINDOW_SAMPLES} samples at 60 Hz ({WINDOW_SAMPLES / 60.0:.2f} s) of walking are "
            f"needed, got {len(r.acc_mps2)}"
        )
    if "i2s_alignment" not in request.app.state.models:
        raise HTTPException(503, f"{WALK}: no I2S alignment model is loaded")
    per_sensor = max(1, request.app.state.settings.max_windows_per_request // len(r.sensor_ids))
    hop = max(HOP_SAMPLES, -(-(len(r.acc_mps2) - WINDOW_SAMPLES + 1) // per_sensor))
    return [
        sliding_windows(np.concatenate([r.acc_mps2[:, k], r.gyr_rads[:, k]], axis=1).astype(np.float32), hop=hop)
        for k in range(len(r.sensor_ids))
    ]


async def place_by_walk(request: Request, r: Readings) -> tuple[Readings, np.ndarray, AssignResponse]:
    """Calibration ``assignment`` with sensors whose segment is not declared: ``/v1/imu/assign``'s answer for the
    request's walk (a declared segment is that sensor's only candidate) places them; the readings of the placed
    sensors with their segments, their alignments ``(N, 4)`` in request order, and that answer."""
    windows = walk_windows(request, r)
    candidates = [None if s is None else [SEGMENTS.index(s)] for s in r.segments]
    placed = await assign_windows(request, r.sensor_ids, windows, False, None, candidates)
    if any(s.segment is not None and s.alignment is None for s in placed.sensors):
        raise HTTPException(503, f"{WALK}: no I2S alignment model is loaded")
    still = [s.sensor_id for s in placed.sensors if s.segment is not None and not s.moving_windows]
    if still:
        raise InputError(
            f"{WALK}: sensors {still} move in none of their windows; a sensor's place and alignment are found from "
            "a walk"
        )
    keep = [k for k, s in enumerate(placed.sensors) if s.segment is not None]
    segments = [placed.sensors[k].segment for k in keep]
    gyr = None if r.gyr_rads is None else r.gyr_rads[:, keep]
    readings = Readings(r.q_world_sensor[:, keep], r.acc_mps2[:, keep], gyr, [r.sensor_ids[k] for k in keep], segments)
    q = np.array([placed.sensors[k].alignment.q_segment_imu for k in keep])
    return readings, q, placed


async def walk_alignments(request: Request, model: PoseModel, r: Readings) -> np.ndarray:
    """Calibration ``assignment``: each sensor's ``q_segment_sensor`` (N, 4) as ``/v1/imu/assign`` finds it for
    the sensor's segment, the served I2S alignment model's robust mean over the sensor's moving windows."""
    windows = walk_windows(request, r)
    _, quats, _ = await infer_windows(request, np.concatenate(windows))
    if quats is None:
        raise HTTPException(503, f"{WALK}: no I2S alignment model is loaded")
    out, start = [], 0
    for k, (segment, w) in enumerate(zip(r.segments, windows, strict=True)):
        moving = is_moving(w)
        if not moving.any():
            raise InputError(
                f"{WALK}: sensor {r.sensor_ids[k]} ({segment}) moves in none of its {len(w)} windows; its alignment "
                "is found from a walk"
            )
        out.append(mean_alignment(quats[start : start + len(w), SEGMENTS.index(segment)][moving])[0])
        start += len(w)
    return np.stack(out)


def _calibrate_by_method(body: PoseImuRequest, model: PoseModel, r: Readings) -> np.ndarray:
    cal = body.calibration
    order = {s.segment: (k, s) for k, s in enumerate(body.sensors)}
    if cal.method == "declared":
        out = []
        for seg in r.segments:
            k, s = order[seg]
            if s.q_segment_sensor is None:
                raise InputError(
                    f"sensors[{k}].q_segment_sensor: calibration 'declared' needs every sensor's alignment; "
                    "give it, or use calibration method 'still_pose' with a still span, or 'assignment' (lower-body "
                    "sensors: found from their walk)"
                )
            q = np.asarray(s.q_segment_sensor, dtype=np.float64)
            if not is_unit_quaternion(q):
                got = [round(float(v), 6) for v in q]
                raise InputError(f"sensors[{k}].q_segment_sensor: expected a finite unit quaternion, got {got}")
            out.append(canonical_quat(q))
        return np.stack(out)
    scale = 60.0 / body.sample_rate_hz
    start, stop = int(round(cal.start * scale)), int(round((cal.stop if cal.stop is not None else 0) * scale))
    n = len(r.q_world_sensor)
    if cal.stop is None or not 0 <= start < stop <= n:
        raise InputError(
            f"calibration: a still span needs 0 <= start < stop <= {round(n / scale)} samples, "
            f"got start {cal.start}, stop {cal.stop}"
        )
    if stop - start < 30:
        raise InputError(f"calibration: the still span must last at least 0.5 s, got {(stop - start) / 60.0:.2f} s")
    span = slice(start, stop)
    still, why = is_still(None if r.gyr_rads is None else r.gyr_rads[span], r.acc_mps2[span], r.segments)
    if not still:
        raise InputError(f"calibration: samples {cal.start}-{cal.stop} are not still: {why}")
    acc_norm = float(np.median(np.linalg.norm(r.acc_mps2[span], axis=-1)))
    if abs(acc_norm - GRAVITY_MPS2) > STILL_ACC_NORM_TOLERANCE_MPS2:
        raise InputError(
            f"calibration: the still sensors read |acc| {acc_norm:.2f} m/s^2 where gravity reads 9.81: "
            f"is acc_unit ({body.acc_unit}) right?"
        )
    try:
        return still_pose_calibration(r.q_world_sensor[span], r.segments, cal.pose, 0, cal.pelvis_back_axis)
    except CalibrationError as exc:
        raise InputError(f"calibration: {exc}") from None


def unit_check(body: PoseImuRequest, r: Readings) -> list[str]:
    """Each sensor's readings against its declared units (``service.core.units.unit_warnings_over``), as the I2S
    routes and the streams check theirs; the acceleration is what the sensor measured, in its own frame."""
    out = []
    for k, sensor_id in enumerate(r.sensor_ids):
        gyr = np.zeros_like(r.acc_mps2[:, k]) if r.gyr_rads is None else r.gyr_rads[:, k]
        readings = np.concatenate([r.acc_mps2[:, k], gyr], axis=-1)
        out += [f"{sensor_id}: {text}" for text in unit_warnings_over(readings, 60.0, body.acc_unit, body.gyr_unit)]
    return out


@dataclass(frozen=True)
class BodyPose:
    R_world: np.ndarray  # (T, 21, 3, 3) every segment's orientation in the sensors' world frame
    body: Body  # the body it is drawn on
    root_m: np.ndarray | None  # (T, 3) the pelvis positions, with translation


@dataclass(frozen=True)
class PoseJob:
    """What a request's pose is made of: the model, the readings, each sensor's alignment, the body's height (None:
    the model's default body), the translation (``none``, ``feet``, ``learned``) and, for ``learned``, the velocity
    model."""

    model: PoseModel
    readings: Readings
    q_seg_sensor: np.ndarray
    height_m: float | None
    translation: str
    velocity: VelocityModel | None = None

    def __post_init__(self) -> None:
        if (self.translation == "learned") != (self.velocity is not None):
            raise ValueError("translation 'learned', and it alone, runs a velocity model")


def body_pose(job: PoseJob) -> BodyPose:
    """The model's pose on the default body (or one of ``height_m``), with the body's translation when asked
    (``service.core.translation``, from the pelvis sensor's free acceleration, and with ``translation`` learned
    from ``velocity``'s pelvis velocity)."""
    model, r = job.model, job.readings
    R_all, a_all = segment_readings(r.q_world_sensor, r.acc_mps2, job.q_seg_sensor)
    n = len(model.spec.sensors)
    R_w_seg, a_w = R_all[:, :n], a_all[:, :n]
    features = pose_features(R_w_seg, a_w)
    R_world = whole_body(
        R_w_seg,
        model.predict(features),
        model.sensor_index,
        model.output_index,
        measured_segments(r.segments[n:], R_all[:, n:]),
        hinges=model.hinge_joints,
    )
    body = model.body.scaled(job.height_m) if job.height_m else model.body
    if job.translation == "none":
        return BodyPose(R_world, body, None)
    tracker, learned = RootTracker(feet_of(body), MODEL_RATE_HZ), None
    if job.velocity is not None:
        tracker.learned_share = job.velocity.spec.learned_share
        learned = world_velocity(R_w_seg[:, 0], job.velocity.predict(features))
    return BodyPose(R_world, body, tracker.advance(body.forward(R_world), a_w[:, 0], learned)[0])


def velocity_for(request: Request, model: PoseModel, translation: str) -> VelocityModel | None:
    """The velocity model ``translation`` learned needs (``learned_velocity_model``), else 422."""
    try:
        return learned_velocity_model(request.app.state.velocity_models, model.spec, model.name, translation)
    except LookupError as exc:
        raise HTTPException(422, f"translation: {exc}") from None


def pose_bvh(job: PoseJob) -> str:
    """The pose as the text of a BVH file (``service.core.body.body_bvh``)."""
    pose = body_pose(job)
    return format_bvh(body_bvh(pose.R_world, pose.body, MODEL_RATE_HZ, pose.root_m))


def segment_sources(job: PoseJob) -> dict[str, str]:
    """Per segment what answers it: ``sensor`` (a calibrated sensor), ``model`` or ``parent`` (neither: its
    parent's orientation)."""
    covered, sensed = set(covered_segments(job.model)), set(job.readings.segments)
    return {s: "sensor" if s in sensed else "model" if s in covered else "parent" for s in BODY_SEGMENTS}


def pose_joint_angles(sources: dict[str, str], R_world: np.ndarray) -> tuple[list[str], np.ndarray]:
    """The joints whose two segments a sensor or the model answers (``segment_sources``), and their angles
    ``(T, J, 3)`` in degrees (``service.core.joint_angles``)."""
    joints = answered_joints({s for s, src in sources.items() if src != "parent"})
    return joints, joint_angles_deg(R_world, joints)


def pose_storage(job: PoseJob) -> str:
    """The pose's joint angles as an OpenSim storage file (``.mot``): time in seconds from the first frame at 60
    Hz, one column per joint and component (``LeftKnee_flexion``), in degrees."""
    pose = body_pose(replace(job, translation="none", velocity=None))  # angles need no translation
    joints, angles = pose_joint_angles(segment_sources(job), pose.R_world)
    columns = {f"{j}_{c}": angles[:, i, k] for i, j in enumerate(joints) for k, c in enumerate(JOINT_COMPONENTS)}
    m = job.model.loaded.manifest
    time_s = np.arange(len(pose.R_world)) / MODEL_RATE_HZ
    return format_opensim_storage(f"{m.name} {m.version}", time_s, columns, in_degrees=True)


def pose_response(job: PoseJob, warnings: list[str], joint_angles: bool = False) -> PoseImuResponse:
    pose = body_pose(job)
    model, R_world = job.model, pose.R_world
    answer = pose_answer(R_world, pose.body)
    sources = segment_sources(job)
    rnd = lambda a, d: np.round(a, d).tolist()  # noqa: E731
    return PoseImuResponse(
        model={"name": model.name, "version": model.loaded.manifest.version},
        sample_rate_hz=60.0,
        frames=len(R_world),
        look_ahead_frames=model.spec.look_ahead_frames,
        body_height_m=round(pose.body.height_m, 3),
        q_segment_sensor={i: rnd(q, 6) for i, q in zip(job.readings.sensor_ids, job.q_seg_sensor, strict=True)},
        segments={
            s: SegmentTrack(
                source=sources[s],
                q_world_segment=rnd(answer["q_world_segment"][:, k], 5),
                q_parent_segment=rnd(answer["q_parent_segment"][:, k], 5),
                joint_position_m=rnd(answer["joint_positions_m"][:, k], 4),
            )
            for k, s in enumerate(BODY_SEGMENTS)
        },
        root_position_m=None if pose.root_m is None else rnd(pose.root_m, 4),
        warnings=warnings,
        **(_angles_answer(sources, R_world) if joint_angles else {}),
    )


def _angles_answer(sources: dict[str, str], R_world: np.ndarray) -> dict:
    joints, angles = pose_joint_angles(sources, R_world)
    per_joint = np.round(angles, 2)
    return {
        "joint_angles_deg": {
            j: {c: per_joint[:, i, k].tolist() for k, c in enumerate(JOINT_COMPONENTS)} for i, j in enumerate(joints)
        },
        "angle_convention": ANGLE_CONVENTION,
    }


@router.post(
    "/v1/pose/imu",
    response_model=PoseImuResponse,
    tags=["pose"],
    summary="Whole-body pose from raw IMU readings",
    description=(
        "Raw readings per sensor (its fusion's q_world_sensor in its own z-up world frame and its accelerometer), "
        "the segment each sensor is on, and a calibration: `declared` alignments (no pose needed, e.g. from "
        "/v1/imu/assign), the frame span of a still N-pose/T-pose in this request, or `assignment` (lower-body "
        "sensors with gyr: each alignment, and the segment of a sensor that declares none, found from the walk in "
        "this request, the placement in the answer's `assignment`). Returns per frame (60 Hz) and "
        "segment the global and parent-relative quaternions and joint positions of the default body (or of "
        "`body_height_m`); with `translation` `feet` or `learned` also where the pelvis is per frame "
        "(`root_position_m`). The model is the offline one whose sensors match, else the one that reads the most "
        "of them (the others answered as measured, and a warning says so), or the one `model` names. With "
        "`format=bvh` the same pose comes as a BVH file (one joint per segment, centimetres, Y up) for Blender, "
        "MotionBuilder or OpenSim, with `format=mot` its joint angles as an OpenSim storage file; the model and "
        "the warnings in the headers `X-Pose-Model` and `X-Pose-Warnings`. With `joint_angles` the JSON answer "
        "also has each joint's flexion, abduction and rotation per frame."
    ),
    responses=file_responses(
        "Pose",
        "HIERARCHY\nROOT Pelvis\n{\n\tOFFSET 0.0000 0.0000 0.0000\n...",
        "`bvh` the text of a BVH file; `mot` an OpenSim storage file of the joint angles",
    )
    | error_responses(
        400,
        401,
        413,
        415,
        422,
        503,
        details={
            422: {"a rule": "sensors: no offline pose model takes sensors on ['Pelvis', 'Head']; ..."},
            503: {"no model": "no imu_pose model is loaded"},
        },
    ),
)
async def pose_from_imu(
    body: PoseImuRequest,
    request: Request,
    settings: Settings = Depends(_settings),
    format: Literal["json", "bvh", "mot"] = Query(  # noqa: A002 (the query parameter's name)
        "json",
        description="`json` (default): quaternions and joint positions; `bvh`: a BVH file of the pose; `mot`: its "
        "joint angles as an OpenSim storage file (degrees, a column per joint and component)",
    ),
) -> Response:
    if body.joint_angles and format == "bvh":
        raise InputError("joint_angles: the angles come in the JSON answer or as format=mot; format 'bvh' has none")
    everything, placed, found = read_request(body), None, None
    unplaced = [k for k, s in enumerate(everything.segments) if s is None]
    if unplaced and body.calibration.method != "assignment":
        raise InputError(
            f"sensors[{unplaced[0]}].segment: calibration {body.calibration.method!r} needs each sensor's segment; "
            "calibration 'assignment' finds the lower-body sensors' segments from their walk"
        )
    if unplaced:
        everything, q_found, placed = await place_by_walk(request, everything)
    try:
        model = choose_model(pose_models(request), everything.segments, body.model, False, extra=True)
    except HTTPException as exc:
        if placed is None or exc.status_code != 422:
            raise
        where = {s.sensor_id: s.segment for s in placed.sensors}
        raise HTTPException(422, f"{exc.detail} (as the walk placed them: {where})") from None
    readings = in_model_order(everything, model)
    if placed is not None:
        found = q_found[[everything.sensor_ids.index(i) for i in readings.sensor_ids]]
    elif body.calibration.method == "assignment":
        found = await walk_alignments(request, model, readings)
    q_seg_sensor = calibrate(body, model, readings, found)
    warnings = unit_check(body, readings)
    if placed is not None:
        if placed.status != "assigned":
            warnings.append(
                f"the walk's assignment is {placed.status!r}: the sensors' places are a guess (see assignment)"
            )
        left_out = [s.sensor_id for s in placed.sensors if s.segment is None]
        if left_out:
            warnings.append(f"sensors {left_out} were placed on no segment by the walk's assignment and are left out")
    measured = readings.segments[len(model.spec.sensors) :]
    if measured:  # a misnamed segment would otherwise pass unnoticed
        warnings.append(f"sensors on {measured} are not read by {model.name}: their segments are answered as measured")
    velocity = velocity_for(request, model, body.translation)
    job = PoseJob(model, readings, q_seg_sensor, body.body_height_m, body.translation, velocity)
    runner = request.app.state.runner
    if format != "json":
        text = await runner.run_call(pose_bvh if format == "bvh" else pose_storage, job)
        version = model.loaded.manifest.version
        return file_answer(text, f"{model.name}.{format}", "Pose", model.name, version, warnings)
    answer = await runner.run_call(pose_response, job, warnings, body.joint_angles)
    answer.assignment = placed
    return Response(answer.model_dump_json(), media_type="application/json")
