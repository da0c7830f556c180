"""Request and response bodies of the REST API (pydantic v2).

The request models publish the rules the service enforces: ranges, lengths and uniqueness as JSON Schema keywords;
rules across fields (rows against rate, rows against a loaded model) in the field's description. Request models are
strict: a number is a JSON number, a boolean ``true`` or ``false``; ``"60"`` and ``0`` are refused, not coerced.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, StrictBool, StrictFloat, model_validator

from service.core.body import BODY_SEGMENTS
from service.core.rotations import UNIT_QUAT_TOLERANCE
from service.core.segments import SEGMENTS
from service.core.windowing import MODEL_RATE_HZ, WINDOW_SAMPLES
from service.inference.flex import MAX_FLEX_RATE_HZ, MAX_FLEX_SAMPLES, MIN_FLEX_RATE_HZ
from service.inference.pose import MAX_POSE_FRAMES, MAX_POSE_IMU_RATE_HZ, MIN_POSE_IMU_RATE_HZ
from service.inference.predict import MAX_ABS_READING, MAX_RATE_HZ, MIN_RATE_HZ, MIN_WINDOW_ROWS
from service.settings import Settings

SegmentName = Literal[SEGMENTS]  # type: ignore[valid-type]
AccUnit = Literal["m/s^2", "g"]
GyrUnit = Literal["rad/s", "deg/s"]
# One sample's values: numbers only (JSON integers too); true, false and "1.5" are refused, not coerced.
Sample = list[StrictFloat]
# An IMU reading in its unit; larger magnitudes are no sensor's and would overflow float32 in the models.
Reading = Annotated[StrictFloat, Field(ge=-MAX_ABS_READING, le=MAX_ABS_READING, allow_inf_nan=False)]
ImuSample = Annotated[
    list[Reading], Field(min_length=6, max_length=6, description="acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z")
]
Quaternion = Annotated[list[Reading], Field(min_length=4, max_length=4, description="w, x, y, z")]
Vector3 = Annotated[list[Reading], Field(min_length=3, max_length=3, description="x, y, z")]


def _non_zero(v: list[float]) -> list[float]:
    if float(np.linalg.norm(v)) < 1e-6:
        raise ValueError(f"a direction needs a non-zero vector, got {v}")
    return v


# A direction in a sensor's frame (its length does not matter; zero has no direction).
Direction3 = Annotated[Vector3, AfterValidator(_non_zero)]
MAX_WINDOWS_PER_REQUEST = Settings.model_fields["max_windows_per_request"].default
# Request bodies: extra fields refused, no coercion between JSON types.
REQUEST = ConfigDict(extra="forbid", strict=True)


def _each_once(names: list[str]) -> list[str]:
    if len(set(names)) != len(names):
        raise ValueError(f"name each segment once, got {names}")
    return names


SegmentSet = Annotated[
    list[SegmentName],
    Field(min_length=1, max_length=len(SEGMENTS), json_schema_extra={"uniqueItems": True}),
    AfterValidator(_each_once),
]
WORN_SEGMENTS_DESCRIPTION = (
    "the segments the sensors are known to be on, when the user knows that but not which sensor is where (e.g. "
    '["LeftFoot", "RightFoot"]): the joint and per-moment answers are then drawn from these segments only. '
    "Each segment once. Default: any of the seven"
)

CANDIDATE_SEGMENTS_DESCRIPTION = (
    "the segments this sensor may be on, when the user knows that much of it (e.g. "
    '["LeftFoot", "RightFoot"] for a foot sensor whose side is not known, ["Pelvis"] for the pelvis sensor): its '
    "joint and per-moment answers are drawn from these only, and from `worn_segments` where both are given "
    "(then the two must have a segment in common). Each segment once. Default: any"
)
WINDOW_ROWS_RULE = (
    f"How many depends on `sample_rate_hz` r: at {MODEL_RATE_HZ:g} Hz exactly {WINDOW_SAMPLES}; at another rate "
    f"enough for {WINDOW_SAMPLES} after resampling to {MODEL_RATE_HZ:g} Hz (polyphase by {MODEL_RATE_HZ:g}/r "
    f"written as a fraction p/q with q <= 1000: ceil(rows * p / q) >= {WINDOW_SAMPLES}, about "
    f"{WINDOW_SAMPLES} * r / {MODEL_RATE_HZ:g} rows, {MIN_WINDOW_ROWS} at {MIN_RATE_HZ:g} Hz); the last "
    f"{WINDOW_SAMPLES} resampled samples are used"
)
# The part of that rule JSON Schema can state: at the model's rate (also the default; within np.isclose's
# tolerance, as fit_window compares) a window has exactly 128 rows.
AT_MODEL_RATE_ROWS = {
    "if": {
        "properties": {
            "sample_rate_hz": {
                "minimum": MODEL_RATE_HZ * (1 - 1e-5) - 1e-8,
                "maximum": MODEL_RATE_HZ * (1 + 1e-5) + 1e-8,
            }
        }
    },
    "then": {"properties": {"samples": {"minItems": WINDOW_SAMPLES, "maxItems": WINDOW_SAMPLES}}},
}
WINDOWS_LIMIT_RULE = (
    f"at most WEARMOCAP_MAX_WINDOWS_PER_REQUEST windows per request (default {MAX_WINDOWS_PER_REQUEST}; more: 413)"
)


def finite_or_none(value: float) -> float | None:
    """JSON has no infinity: a margin over no other segment is null."""
    return float(value) if np.isfinite(value) else None


def check_declarations(candidates: list[list[str] | None], worn: list[str] | None, field: str) -> None:
    """``ValueError`` naming the first sensor whose candidate segments and the worn ones have none in common."""
    if worn is None:
        return
    for k, own in enumerate(candidates):
        if own is not None and not set(own) & set(worn):
            raise ValueError(f"{field}[{k}].candidate_segments: none of {own} is among worn_segments {worn}")


EXAMPLE_WINDOW = {
    "samples": [[0.0, 0.0, 9.81, 0.0, 0.0, 0.0]] * 128,
    "sample_rate_hz": 60.0,
    "acc_unit": "m/s^2",
    "gyr_unit": "rad/s",
}


class ImuWindow(BaseModel):
    """One window of one sensor: rows of acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z in the sensor frame.

    At 60 Hz exactly 128 rows; at another rate enough rows for 128 after resampling to 60 Hz
    (the last 128 resampled samples are used).
    """

    model_config = REQUEST | ConfigDict(json_schema_extra={"examples": [EXAMPLE_WINDOW], **AT_MODEL_RATE_ROWS})
    samples: list[ImuSample] = Field(
        min_length=MIN_WINDOW_ROWS, description=f"rows of 6 finite numbers, oldest first. {WINDOW_ROWS_RULE}"
    )
    sample_rate_hz: float = Field(MODEL_RATE_HZ, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, allow_inf_nan=False)
    acc_unit: AccUnit = "m/s^2"
    gyr_unit: GyrUnit = "rad/s"
    segment: SegmentName | None = Field(None, description="known segment: the alignment is given for it")


class WindowsRequest(BaseModel):
    model_config = REQUEST | ConfigDict(json_schema_extra={"examples": [{"windows": [EXAMPLE_WINDOW]}]})
    windows: list[ImuWindow] = Field(
        min_length=1, json_schema_extra={"maxItems": MAX_WINDOWS_PER_REQUEST}, description=WINDOWS_LIMIT_RULE
    )


_EXAMPLE_PROBS = dict(zip(SEGMENTS, [0.001, 0.002, 0.004, 0.985, 0.004, 0.002, 0.002], strict=True))
EXAMPLE_ALIGNMENT = {
    "segment": "Pelvis",
    "q_segment_imu": [0.9238795, 0.0, 0.3826834, 0.0],
    "R_segment_imu": [[0.7071068, 0.0, 0.7071068], [0.0, 1.0, 0.0], [-0.7071068, 0.0, 0.7071068]],
}
EXAMPLE_RESULT = {
    "segment": "Pelvis",
    "confidence": 0.985,
    "probabilities": _EXAMPLE_PROBS,
    "moving": True,
    "turns_about_vertical": False,
    "alignment": EXAMPLE_ALIGNMENT,
}
EXAMPLE_VERSIONS = {"i2s_assignment": "1.9.0", "i2s_alignment": "3.3.0"}


class Alignment(BaseModel):
    segment: SegmentName
    q_segment_imu: list[float] = Field(
        min_length=4, max_length=4, description="unit quaternion w, x, y, z (w >= 0): v_segment = R(q) v_imu"
    )
    R_segment_imu: list[Annotated[list[float], Field(min_length=3, max_length=3)]] = Field(min_length=3, max_length=3)


class WindowResult(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [EXAMPLE_RESULT]})
    segment: SegmentName
    confidence: float
    probabilities: dict[str, float]
    moving: bool = Field(description="false: the gyroscope was still, the class is a guess")
    turns_about_vertical: bool = Field(
        description="true: a moving window whose dominant rotation axis lies within 45° of gravity. Legs and feet "
        "swing about a horizontal axis in gait, the motion the models were trained on; for a leg or foot sensor such "
        "a window (twisting, turning on the spot) is outside it, so treat its class and alignment with caution. "
        "The pelvis turns about the vertical in gait too."
    )
    alignment: Alignment | None = None


class WindowsResponse(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"results": [EXAMPLE_RESULT], "model_versions": EXAMPLE_VERSIONS}]}
    )
    results: list[WindowResult]
    model_versions: dict[str, str]
    warnings: list[str] = Field(
        default_factory=list,
        description="the input looks implausible for its declared units (gravity far from 9.81 m/s² over the "
        "windows, a gyroscope faster than a human segment turns): the answer is given, but check the units",
    )


class SensorWindows(BaseModel):
    model_config = REQUEST
    sensor_id: str = Field(min_length=1, max_length=128, description="unique within the request")
    windows: list[ImuWindow] = Field(
        min_length=1,
        json_schema_extra={"maxItems": MAX_WINDOWS_PER_REQUEST},
        description=f"in time order; window k of each sensor is the same moment. The request's sensors together "
        f"have {WINDOWS_LIMIT_RULE}",
    )
    candidate_segments: SegmentSet | None = Field(None, description=CANDIDATE_SEGMENTS_DESCRIPTION)


class AssignRequest(BaseModel):
    """Sensors recorded at the same time; each is assigned one segment.

    One-to-one by default (more sensors than segments: the weakest stay unassigned; fewer: some
    segments stay empty). ``allow_shared`` lets several sensors share a segment. ``worn_segments`` narrows the
    segments to choose from for all sensors, a sensor's ``candidate_segments`` for that sensor.
    """

    model_config = REQUEST | ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "sensors": [
                        {"sensor_id": "thigh_left", "windows": [EXAMPLE_WINDOW]},
                        {"sensor_id": "pelvis", "windows": [EXAMPLE_WINDOW]},
                    ],
                    "allow_shared": False,
                }
            ]
        },
    )
    sensors: list[SensorWindows] = Field(min_length=1, max_length=64, description="each sensor_id once")
    allow_shared: StrictBool = False
    worn_segments: SegmentSet | None = Field(None, description=WORN_SEGMENTS_DESCRIPTION)

    @model_validator(mode="after")
    def _declarations_agree(self) -> AssignRequest:
        check_declarations([s.candidate_segments for s in self.sensors], self.worn_segments, "sensors")
        return self


class SensorAssignment(BaseModel):
    sensor_id: str
    segment: SegmentName | None
    confidence: float = Field(
        description="softmax of the summed window log-probabilities at the assigned segment: near 1 after a few "
        "windows whatever the truth (windows overlap and agree with each other); see `p_correct`"
    )
    p_correct: float | None = Field(
        None,
        description="calibrated probability that `segment` is right, from the share of moving windows that "
        "favour it, the margin per window and the number of moving windows, fitted on sessions of people the "
        "model never trained on (the model's manifest, `confidence`); null for a model without calibration",
    )
    committed: bool | None = Field(
        None,
        description="`p_correct` reaches the model's threshold (`confidence.threshold`) on at least "
        "`confidence.min_moving_windows` moving windows: this sensor's segment is as sure as the calibration's "
        "selective accuracy (models.md), whether or not the session's other sensors are; null without calibration",
    )
    margin: float | None = Field(
        description="summed log-probability lead of the assigned segment over the sensor's best other segment "
        "(among those declared for it); negative when the one-to-one constraint overrode the sensor's own "
        "preference; null when the declarations leave the sensor one segment only. With a model calibrated on "
        "answers that weigh how the sensors swing together (`confidence.swing_weight` > 0): how much more the "
        "whole answer scores, swing included, than the best one that puts this sensor elsewhere"
    )
    windows: int
    moving_windows: int
    moving_windows_turning_about_vertical: int = Field(
        description="of the moving windows, those that turn about the vertical (see the per-window field)"
    )
    alignment: Alignment | None = Field(
        None, description="robust mean over the sensor's moving windows (all windows if none moves)"
    )
    alignment_spread_deg: float | None = Field(
        None, description="median angle of those windows' alignments from the mean; large: they disagree"
    )
    window_segments: list[SegmentName | None] = Field(
        description="per window, in order: the one-to-one answer of the windows that the request's sensors took at "
        "that moment (window k of every sensor that has one), weighing also how those windows swing together (the "
        "sensors of one leg swing together, the two legs take turns); null for a still window or one left over when "
        "more than seven windows move; with `allow_shared`, each moving window's own answer. `segment` above is the "
        "answer from all windows together"
    )


class AssignResponse(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "sensors": [
                        {
                            "sensor_id": "pelvis",
                            "segment": "Pelvis",
                            "confidence": 0.999,
                            "p_correct": 0.998,
                            "committed": True,
                            "margin": 41.2,
                            "windows": 12,
                            "moving_windows": 11,
                            "moving_windows_turning_about_vertical": 0,
                            "alignment": EXAMPLE_ALIGNMENT,
                            "alignment_spread_deg": 3.1,
                            "window_segments": ["Pelvis"] * 11 + [None],
                        }
                    ],
                    "p_all_correct": None,
                    "status": "assigned",
                    "model_versions": EXAMPLE_VERSIONS,
                }
            ]
        }
    )
    sensors: list[SensorAssignment]
    p_all_correct: float | None = Field(
        None,
        description="calibrated probability that the whole joint assignment is right (every assigned sensor on its "
        "segment), from the sensors' `p_correct`, fitted on sessions of people the model never trained on (the "
        "model's manifest, `confidence.session`); null for a model without that calibration",
    )
    status: Literal["assigned", "not_enough_walking", "uncalibrated"] = Field(
        description="`assigned`: on enough moving windows per sensor, every assigned sensor's `p_correct` reaches "
        "the model's threshold (its manifest, `confidence.threshold`), or, for a model that also calibrates the whole "
        "answer, `p_all_correct` reaches `confidence.session.threshold`; `not_enough_walking`: not yet, walk on (or "
        "the motion is not gait); `uncalibrated`: the model carries no calibration"
    )
    model_versions: dict[str, str]
    warnings: list[str] = Field(
        default_factory=list,
        description="the input looks implausible for its declared units (gravity far from 9.81 m/s² over the "
        "windows, a gyroscope faster than a human segment turns): the answer is given, but check the units",
    )


EXAMPLE_FLEX_SAMPLES = [[1850.0, 1790.0, 2210.0, 2105.0]] * 100


class FlexRequest(BaseModel):
    """A block of flex or capacitive readings, oldest first: one row per sample of the model's ``channels`` in
    order (``GET /v1/models``), raw (``units``, ``value_range``). The block must cover the model's calibration
    window (``window_samples`` at ``sample_rate_hz``); every sample from then on gets its joint angles."""

    model_config = REQUEST | ConfigDict(
        json_schema_extra={"examples": [{"model": "flex_bilstm_cm", "samples": EXAMPLE_FLEX_SAMPLES}]}
    )
    model: str | None = Field(
        None,
        max_length=128,
        description="a loaded flex_pose model's name (GET /v1/models); default: the one model whose channel count "
        "is the rows' length (when none or several fit: 422)",
    )
    channels: list[str] | None = Field(
        None,
        max_length=64,
        description="optional check: the channel names in the order of each row; must equal the model's channels",
    )
    sample_rate_hz: float | None = Field(
        None,
        allow_inf_nan=False,
        ge=MIN_FLEX_RATE_HZ,
        le=MAX_FLEX_RATE_HZ,
        description="default: the model's rate; others are resampled to it",
    )
    samples: list[Annotated[Sample, Field(min_length=1)]] = Field(
        min_length=1,
        description="rows of finite numbers, oldest first, all as long as the model has channels, each value in the "
        "model's value_range (GET /v1/models). At the model's rate (its sample_rate_hz, after resampling from "
        "this request's) the block holds at least the model's window_samples (the calibration window: about "
        f"window_samples * sample_rate_hz / model rate rows) and at most {MAX_FLEX_SAMPLES} samples "
        "(round(rows * model rate / sample_rate_hz)); send longer recordings in blocks or over /v1/stream/flex",
    )


class FlexResponse(BaseModel):
    """Joint angles per sample: ``angles_deg[joint][component]`` lists one value per answered sample, the first
    for sample ``first_sample`` (at the model's rate; the samples before it fill the calibration window)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "model": {"name": "flex_bilstm_cm", "version": "1.0.0"},
                    "sample_rate_hz": 20.0,
                    "window_samples": 100,
                    "latency_samples": 1,
                    "first_sample": 98,
                    "frames": 1,
                    "angles_deg": {"LeftKnee": {"flexion": [12.5], "abduction": [0.4], "rotation": [-1.2]}},
                    "angle_convention": "service.core.joint_angles: ...",
                }
            ]
        }
    )
    model: dict[str, str]
    sample_rate_hz: float
    window_samples: int
    latency_samples: int = Field(description="each answer is for the sample this many before the newest it saw")
    first_sample: int
    frames: int
    angles_deg: dict[str, dict[str, list[float]]]
    angle_convention: str
    warnings: list[str] = Field(
        default_factory=list,
        description="the readings look like a mistake the value range lets through (every value at most 5 where "
        "the model takes counts in the thousands: volts or 0–1 values; a channel that reads one value over the whole "
        "block: a disconnected, shorted or saturated sensor): the angles are given, but check",
    )


BodySegmentName = Literal[BODY_SEGMENTS]  # type: ignore[valid-type]
_IDENTITY = [1.0, 0.0, 0.0, 0.0]


class PoseSensor(BaseModel):
    """One sensor's raw readings, oldest first, one row per sample: its fusion's orientation in its own world
    frame (any frame with z up: ENU, NWU, …; the pose does not depend on its heading) and its accelerometer."""

    model_config = REQUEST
    sensor_id: str = Field(min_length=1, max_length=64)
    segment: BodySegmentName | None = Field(
        None,
        description="the body segment the sensor is on (GET /v1/models: pose.sensors); one sensor per segment. "
        "Required, except with calibration `assignment`, which finds a lower-body sensor's segment from the walk",
    )
    q_world_sensor: list[Quaternion] = Field(
        min_length=2,
        description=f"unit quaternions w, x, y, z per sample (norm within 1 ± {UNIT_QUAT_TOLERANCE:g}); as many rows "
        "as `acc` and as every other sensor's",
    )
    acc: list[Vector3] = Field(
        min_length=2,
        description="specific force x, y, z in the sensor frame per sample (`acc_unit`); as many rows as "
        "`q_world_sensor`",
    )
    gyr: list[Vector3] | None = Field(
        None,
        description="angular rate x, y, z (`gyr_unit`): checks stillness, and calibration `assignment` needs it; as "
        "many rows as `q_world_sensor`",
    )
    q_segment_sensor: Quaternion | None = Field(
        None,
        description="declared alignment (calibration method 'declared', which needs it on every sensor): "
        f"v_segment = R(q) v_sensor, w, x, y, z, a unit quaternion (norm within 1 ± {UNIT_QUAT_TOLERANCE:g}); "
        "e.g. /v1/imu/assign's alignment of a lower-body sensor",
    )


PELVIS_HEADING_DESCRIPTION = (
    "`legs`: the pelvis's alignment turned about the vertical so that it faces where the leg sensors' segments face "
    "on average (over the request; on a stream over the frames so far), for alignments found from a walk "
    "(`/v1/imu/assign`), whose pelvis heading can be tens of degrees off on real people; needs the pose model to "
    "read a thigh, shank or foot sensor and assumes the legs point where the pelvis does (walking, standing). "
    "`alignment`: the pelvis's "
    "alignment as calibrated. Default: `legs` with calibration `assignment`, else `alignment`"
)


class PoseCalibration(BaseModel):
    """How sensor readings become segment readings. ``declared``: each sensor's ``q_segment_sensor``, no pose
    needed. ``still_pose``: frames [start, stop) of this request are a still N-pose (arms hanging) or T-pose (arms
    sideways) of 2-3 s; each sensor's alignment and the body's heading are computed from it (the pelvis sensor's
    ``pelvis_back_axis``, in its own frame, must point out of the lower back). ``assignment``: neither; each
    sensor's alignment is found from its own walk in this request by the served I2S alignment model, as
    ``/v1/imu/assign`` gives it for the sensor's segment (lower-body sensors, with ``gyr``, and at least one moving
    window of 128 samples at 60 Hz each), and the pelvis's heading from the legs."""

    model_config = REQUEST
    method: Literal["declared", "still_pose", "assignment"] = "declared"
    pose: Literal["npose", "tpose"] = "npose"
    start: int = Field(0, ge=0, description="still_pose: the span's first sample")
    stop: int | None = Field(
        None,
        ge=1,
        description="still_pose (required there): the sample after the span; start < stop <= the number of rows, "
        "and the span lasts at least 0.5 s with every sensor still and reading gravity",
    )
    pelvis_back_axis: Direction3 = Field(default_factory=lambda: [0.0, 0.0, 1.0])
    pelvis_heading: Literal["alignment", "legs"] | None = Field(None, description=PELVIS_HEADING_DESCRIPTION)


EXAMPLE_POSE_IMU = {
    "sample_rate_hz": 60.0,
    "acc_unit": "m/s^2",
    "sensors": [
        {
            "sensor_id": name.lower(),
            "segment": name,
            "q_world_sensor": [_IDENTITY] * 3,
            "acc": [[0.0, 0.0, 9.81]] * 3,
            "q_segment_sensor": _IDENTITY,
        }
        for name in ("Pelvis", "LeftLowerLeg", "RightLowerLeg")
    ],
    "calibration": {"method": "declared"},
}


TRANSLATION_DESCRIPTION = (
    "`feet`: also where the pelvis is (`root_position_m`): the foot on the ground holds still and the pelvis "
    "accelerometer tells flight from stance (TransPose 2021's supporting-foot rule; a level floor assumed); "
    "`learned`: the same rule with a learned pelvis velocity (TransPose 2021's fallback branch) in the "
    "accelerometer's place along the floor, where a velocity model for the pose model's sensors is loaded (GET "
    "/v1/models: task imu_pose_velocity); `none` (default): the pose about a pelvis kept in place"
)


class PoseImuRequest(BaseModel):
    model_config = REQUEST | ConfigDict(json_schema_extra={"examples": [EXAMPLE_POSE_IMU]})
    sample_rate_hz: float = Field(
        MODEL_RATE_HZ,
        allow_inf_nan=False,
        ge=MIN_POSE_IMU_RATE_HZ,
        le=MAX_POSE_IMU_RATE_HZ,
        description=f"resampled to the model's 60 Hz; at most {MAX_POSE_FRAMES} frames at 60 Hz per request "
        "(rows * 60 / sample_rate_hz)",
    )
    acc_unit: AccUnit = "m/s^2"
    gyr_unit: GyrUnit = "rad/s"
    sensors: list[PoseSensor] = Field(
        min_length=1,
        max_length=len(BODY_SEGMENTS),
        description="one per segment; their segments are a loaded offline pose model's sensors (GET /v1/models: "
        "pose.sensors), or those of `model`, and any others, answered as measured (`source` `sensor`)",
    )
    calibration: PoseCalibration = Field(default_factory=PoseCalibration)
    model: str | None = Field(
        None, description="a loaded pose model's name; default: the offline model for these sensors"
    )
    body_height_m: float | None = Field(
        None, ge=0.5, le=2.5, allow_inf_nan=False, description="scale the default body to this height"
    )
    translation: Literal["none", "feet", "learned"] = Field("none", description=TRANSLATION_DESCRIPTION)
    joint_angles: StrictBool = Field(
        False,
        description="also answer `joint_angles_deg`: each joint's flexion, abduction and rotation per frame "
        "(degrees, the convention in `angle_convention`) for the joints whose two segments the sensors or the "
        "model answer (pelvis and shanks: hips, knees and ankles)",
    )


class SegmentTrack(BaseModel):
    source: Literal["sensor", "model", "parent"] = Field(
        description="sensor: the calibrated sensor; model: the network (a thigh beside a sensed shank: that shank "
        "turned about the knee's hinge by the network's flexion); parent: neither covers it, the parent's"
    )
    q_world_segment: list[list[float]]
    q_parent_segment: list[list[float]]
    joint_position_m: list[list[float]] = Field(description="the segment's origin, pelvis at (0, 0, 0)")


_EXAMPLE_TRACK = {
    "source": "sensor",
    "q_world_segment": [[1.0, 0.0, 0.0, 0.0]],
    "q_parent_segment": [[1.0, 0.0, 0.0, 0.0]],
    "joint_position_m": [[0.0, 0.0, 0.0]],
}
EXAMPLE_POSE_IMU_RESPONSE = {
    "model": {"name": "pose_lower3", "version": "2.0.0"},
    "sample_rate_hz": 60.0,
    "frames": 1,
    "look_ahead_frames": 75,
    "body_height_m": 1.7,
    "q_segment_sensor": {"pelvis": [1.0, 0.0, 0.0, 0.0]},
    "segments": {"Pelvis": _EXAMPLE_TRACK},
    "root_position_m": None,
}


class PoseImuResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [EXAMPLE_POSE_IMU_RESPONSE]})
    model: dict[str, str]
    sample_rate_hz: float
    frames: int
    look_ahead_frames: int = Field(description="future frames each answer has seen (streaming models)")
    body_height_m: float
    q_segment_sensor: dict[str, list[float]] = Field(description="the calibration used, per sensor_id")
    segments: dict[str, SegmentTrack]
    root_position_m: list[list[float]] | None = Field(
        None,
        description="with `translation` `feet` or `learned`: the pelvis origin per frame in the sensors' world (z up, "
        "metres): x, y from where it stood at the first frame, z its height above the floor (the level of the first "
        "frame's lowest foot point); a joint's position in the world is this plus its `joint_position_m`",
    )
    warnings: list[str] = Field(
        default_factory=list,
        description="a sensor whose readings look implausible for the declared units (over 2 s windows: gravity far "
        "from 9.81 m/s², a gyroscope faster than a human segment turns): the pose is given, but check the units",
    )
    assignment: AssignResponse | None = Field(
        None,
        description="calibration `assignment` with sensors whose segment was not declared: how the walk placed "
        "them, as /v1/imu/assign answers (its `status` and each sensor's `p_correct` say how sure)",
    )
    joint_angles_deg: dict[str, dict[str, list[float]]] | None = Field(
        None,
        description="with `joint_angles`: per joint (LeftHip, LeftKnee, LeftAnkle, …) its `flexion`, `abduction` and "
        "`rotation` per frame in degrees",
    )
    angle_convention: str | None = Field(None, description="with `joint_angles`: how the angles are defined")


class FieldError(BaseModel):
    loc: list[str | int]
    msg: str
    type: str
    input: str | None = Field(None, description="at most 200 characters of what arrived")


class ErrorBody(BaseModel):
    detail: str = Field(description="what was expected and what arrived")
    errors: list[FieldError] | None = Field(None, description="field errors of a 422 (at most 20)")
    errors_total: int | None = None


class RefusedModel(BaseModel):
    name: str
    version: str
    path: str
    reason: str


class Readiness(BaseModel):
    ready: bool = Field(
        description="false (503): no i2s_assignment model is loaded, or a version pinned with "
        "WEARMOCAP_MODEL_VERSIONS cannot be served"
    )
    status: Literal["ok", "degraded", "unavailable"] = Field(
        description="degraded (still 200): a newer version than the one served was refused (see `refused`)"
    )
    models: dict[str, str] = Field(description="the loaded models' versions by name")
    refused: list[RefusedModel] = Field(
        default_factory=list, description="model files that are not served (bad sha256, unreadable, no manifest)"
    )
    failed_pins: dict[str, str] = Field(default_factory=dict, description="pinned models that cannot be served")


_FIELD_ERROR = {"loc": ["body"], "msg": "Field required", "type": "missing", "input": None}
_ERROR_EXAMPLES: dict[int, dict[str, dict]] = {
    400: {"not UTF-8": {"detail": "There was an error parsing the body"}},
    401: {"no key": {"detail": "missing or wrong X-API-Key header"}},
    413: {"too large": {"detail": "body of 40000000 bytes exceeds the limit of 33554432 bytes"}},
    415: {"not JSON": {"detail": "this route takes a JSON body (Content-Type: application/json); got text/plain"}},
    422: {
        "a rule": {"detail": "windows[0]: at 60 Hz a window has 128 samples, got 127"},
        "a field": {"detail": "body: Field required", "errors": [_FIELD_ERROR], "errors_total": 1},
    },
    503: {
        "no model": {"detail": "no i2s_assignment model is loaded; loaded: none"},
        "overloaded": {
            "detail": "overloaded: the estimated wait of 2.40 s passes this request's deadline (time left 1.00 s); "
            "retry in 2 s"
        },
    },
}
_ERROR_DESCRIPTIONS = {
    400: "the body is not UTF-8 text",
    401: "missing or wrong X-API-Key header (when the service has an API key)",
    413: "too large: a body over WEARMOCAP_MAX_BODY_BYTES (or, where the examples say so, too many windows)",
    415: "a body sent with a Content-Type other than JSON on a route that reads JSON",
    422: "the body is not JSON, or the request breaks a rule of the schema or one stated in a field's description",
    503: "no model for this route is loaded, or the service is overloaded (then with Retry-After)",
}
RETRY_AFTER = {
    "Retry-After": {
        "description": "seconds to wait before retrying, when the service is overloaded",
        "schema": {"type": "integer", "minimum": 0},
    }
}


def file_responses(prefix: str, example: str, what: str) -> dict[int | str, dict]:
    """The OpenAPI entry of a route's 200 that also answers as a file (``format``): JSON or the file's text, with
    the model and warnings headers of ``service.api.routes.file_answer``."""
    return {
        200: {
            "description": f"JSON (default), or with `format` {what}",
            "content": {"text/plain": {"example": example}},
            "headers": {
                f"X-{prefix}-Model": {"description": "the model's name and version", "schema": {"type": "string"}},
                f"X-{prefix}-Warnings": {
                    "description": "a JSON list of the answer's warnings (the first 8, then how many more)",
                    "schema": {"type": "string"},
                },
            },
        }
    }


def error_responses(*codes: int, details: dict[int, dict[str, str]] | None = None) -> dict[int | str, dict]:
    """OpenAPI entries for the 4xx/5xx answers of a route: the ``ErrorBody`` schema with an example body per cause
    (``details``: this route's ``detail`` per code and cause, replacing or adding to the default causes)."""
    out: dict[int | str, dict] = {}
    for code in codes:
        ours = {name: {"detail": detail} for name, detail in (details or {}).get(code, {}).items()}
        examples = _ERROR_EXAMPLES[code] | ours
        entry = {
            "model": ErrorBody,
            "description": _ERROR_DESCRIPTIONS[code],
            "content": {"application/json": {"examples": {k: {"value": v} for k, v in examples.items()}}},
        }
        if code == 503:
            entry["headers"] = RETRY_AFTER
        out[code] = entry
    return out
