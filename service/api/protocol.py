"""WebSocket ``/v1/stream`` protocol: JSON messages and the compact binary sample packet.

Client → server
  {"type": "start", "sensors": [{"sensor_id": "a", "sample_rate_hz": 60, "acc_unit": "m/s^2",
   "gyr_unit": "rad/s", "candidate_segments": ["LeftFoot", "RightFoot"]}, ...], "allow_shared": false,
   "worn_segments": ["LeftFoot", "RightFoot"]}         (first message, once; worn_segments optional: the joint and
                                                       moment answers are drawn from those segments only; a
                                                       sensor's candidate_segments, optional: its answers are
                                                       drawn from those only)
  {"type": "samples", "sensor_id": "a", "seq": 0, "samples": [[ax, ay, az, gx, gy, gz], ...]}
  binary packet (little-endian): uint16 sensor index (order of "start"), uint16 n, uint32 seq,
  then n × 6 float32 (acc xyz, gyr xyz in the declared units)                 8 + 24 n bytes
  binary frame packet, every sensor's samples of the same seq at once (what a suit's receiver delivers): sensor
  index 65535 (ALL_SENSORS), then n × S × 6 float32, the S sensors in the order of "start"   8 + 24 n S bytes
  {"type": "stop"}
  {"type": "calibrate"}   (still-pose sessions: the person holds the still pose again, e.g. after a sensor slipped;
                          the pose starts afresh after the new span, as at the start)
  {"type": "calibrate", "q_segment_sensor": {"a": [w, x, y, z], ...}}   (declared sessions: new alignments of the
                          named sensors from the next frame all sensors complete; the pose goes on, nothing restarts)
  Pose sessions add "pose": {"calibration": "declared" | "still_pose" | "assignment", ...} to "start" and each
  sensor's "segment" (and "q_segment_sensor" when declared); their samples are rows of 10 values, acc xyz, gyr xyz,
  q_world_sensor w x y z (binary: n x 10 float32), at 60 Hz (``PoseStreamOptions``).
``seq`` is the sensor's sample counter of the packet's first sample (0, 1, 2, … per sample).

Server → client
  started (the session's sensors, window_samples, hop_samples, model_rate_hz, assignment_interval_s and its
  declarations) · result (per window: class, probabilities, moving, turns_about_vertical, alignment: the window's own
  answer over all seven segments) · moment (sessions of two or more sensors or with worn_segments, per window end
  time: the one-to-one answer of the sensors' windows that end then, as /v1/imu/assign's window_segments; sent once
  every sensor has reached that time, or when 32 moments wait on a stalled sensor, whose windows then come in moments
  of their own) · assignment (joint, one-to-one over the session's evidence, and per sensor the robust mean alignment
  over its last WEARMOCAP_STREAM_ALIGNMENT_WINDOWS moving windows with its spread, its calibrated p_correct and
  whether it is committed on its own, the probability p_all_correct that every sensor is right, and status, as
  /v1/imu/assign; after the first results, then once the session has answered as many windows as its sensors
  make in WEARMOCAP_STREAM_ASSIGNMENT_INTERVAL_S of stream time (0.5 s: two per sensor; 0, or a pose session
  calibrating from the assignment until it has: after each group of results), and at stop or before an error) ·
  warning (once per sensor, when its first 4 windows read implausibly for its declared units: the REST routes'
  `warnings`) · gap / late (sequence problems, in order with the results) · error (then close, after the results of
  every accepted packet).
  Pose sessions also get: calibration ({"status": "waiting" | "calibrated", ...}: how the session calibrates; declared
  sessions are calibrated at the start and after each calibrate with q_segment_sensor (every sensor's alignment, by
  segment), still-pose sessions after a still span, assignment sessions when the
  assignment is sure of the model's segments, with the segments of the session's other sensors placed as surely in
  "measured"; sensors beyond the model's are answered as measured, "started" lists them in pose.measured for declared
  and still-pose sessions; "started" also says pose.pelvis_heading: "legs" turns the pelvis to the leg sensors'
  heading, the default of assignment sessions) · pose (from the streaming model, as frames complete: first_frame,
  frames, q_world_segment and joint_positions_m per frame in "started"'s pose.segments order; each frame answers
  look_ahead_frames late; with "pose": {"translation": "feet" | "learned"} also root_position_m, the pelvis per frame
  by /v1/pose/imu's rule (with "learned" and the learned pelvis velocity of the velocity model of the pose model's
  sensors), run over the frames this stream answers, from its first answered frame; "started" says pose.translation
  and, with "learned", pose.velocity_model; with "pose": {"joint_angles": true} also joint_angles_deg, per joint whose
  two segments are answered its flexion, abduction and rotation per frame in degrees, frames × 3, and "started" says
  pose.joint_angles) · warning
  (pose-only sessions: once per sensor, when the first 2 s of body frames read implausibly for its declared units).
  With "pose": {"output": "binary"} each pose message is a binary pose block instead (little-endian): uint16 1,
  uint16 S segments, uint32 first_frame, uint32 frames, then frames × S × 4 float32 q_world_segment (w x y z) and
  frames × S × 3 float32 joint_positions_m: 12 + 28 × frames × S bytes (``decode_pose_block``); with translation
  the block's kind is 2 and frames × 3 float32 root_position_m follow: 12 + 28 × frames × S + 12 × frames bytes.
  With "pose": {"output": "bvh"} (a live BVH stream, as motion-capture suits broadcast to animation tools)
  "started" carries pose.bvh_hierarchy (the HIERARCHY of a BVH file of the session's body) and
  pose.frame_time_s, and each pose message is {"type": "pose", first_frame, frames, bvh_motion}: one line of the
  file's MOTION table per frame (the root's position channels: the translation, or the pelvis kept in place);
  the hierarchy, "MOTION", "Frames: N", "Frame Time: ..." and the lines make the file
  (``service.core.body.body_bvh``).
  gap / late notices of a sensor that are still queued are merged into one ("count" notices; "missing" summed), and
  only the newest assignment is queued.
Close codes: 1003 unsupported data, 1008 protocol violation (also a wrong X-API-Key or a browser Origin not allowed,
and a consumer that stays behind: nothing taken for WEARMOCAP_STREAM_SLOW_CONSUMER_S while messages wait), 1009
message too big, 1011 no model loaded or inference failed, 1013 at capacity (try again later), 1000 after stop.
"""

from __future__ import annotations

import struct
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictBool, field_validator, model_validator

from service.api.schemas import (
    CANDIDATE_SEGMENTS_DESCRIPTION,
    PELVIS_HEADING_DESCRIPTION,
    TRANSLATION_DESCRIPTION,
    WORN_SEGMENTS_DESCRIPTION,
    AccUnit,
    BodySegmentName,
    Direction3,
    GyrUnit,
    Sample,
    SegmentSet,
    check_declarations,
)
from service.core.body import Body, body_bvh
from service.core.bvh import bvh_hierarchy_text, bvh_motion_text
from service.core.rotations import UNIT_QUAT_TOLERANCE, is_unit_quaternion, matrix_from_quat
from service.core.windowing import MODEL_RATE_HZ
from service.inference.predict import MAX_ABS_READING

HEADER = struct.Struct("<HHI")
ALL_SENSORS = 0xFFFF  # a binary packet's sensor index for "every sensor's samples, in the order of start"


class ProtocolError(ValueError):
    """A client broke the protocol; ``code`` is the WebSocket close code to use."""

    def __init__(self, message: str, code: int = 1008) -> None:
        super().__init__(message)
        self.code = code


def unit_quaternion(q: list[float] | None) -> list[float] | None:
    """A declared alignment: four finite numbers of norm 1 (within ``UNIT_QUAT_TOLERANCE``, then normalised)."""
    if q is not None and not is_unit_quaternion(q):
        raise ValueError(f"expected a finite unit quaternion (w, x, y, z), got {q}")
    return q


class StreamSensor(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sensor_id: str = Field(min_length=1, max_length=128)
    sample_rate_hz: float = Field(60.0, ge=10.0, le=2000.0, allow_inf_nan=False)
    acc_unit: AccUnit = "m/s^2"
    gyr_unit: GyrUnit = "rad/s"
    candidate_segments: SegmentSet | None = Field(None, description=CANDIDATE_SEGMENTS_DESCRIPTION)
    segment: BodySegmentName | None = Field(None, description="pose sessions: the body segment the sensor is on")
    q_segment_sensor: list[float] | None = Field(
        None, min_length=4, max_length=4, description="pose sessions, calibration 'declared': v_segment = R(q) v_sensor"
    )
    _unit = field_validator("q_segment_sensor")(unit_quaternion)


class CalibrateMessage(BaseModel):
    """``{"type": "calibrate"}``: a still-pose session holds its still pose again. With ``q_segment_sensor``: a
    declared session's new alignments, by sensor_id, from the next frame all its sensors complete."""

    model_config = ConfigDict(extra="forbid")
    type: Literal["calibrate"]
    q_segment_sensor: dict[str, list[float]] | None = Field(
        None, min_length=1, description="declared sessions: sensor_id -> new v_segment = R(q) v_sensor"
    )

    @field_validator("q_segment_sensor")
    @classmethod
    def _units(cls, value: dict[str, list[float]] | None) -> dict[str, list[float]] | None:
        for sensor_id, q in (value or {}).items():
            if len(q) != 4:
                raise ValueError(f"{sensor_id}: expected 4 numbers (w, x, y, z), got {len(q)}")
            try:
                unit_quaternion(q)
            except ValueError as exc:
                raise ValueError(f"{sensor_id}: {exc}") from None
        return value


class PoseStreamOptions(BaseModel):
    """Pose on the stream. Samples are then rows of 10 values: acc xyz, gyr xyz, q_world_sensor w x y z (binary:
    n x 10 float32), at 60 Hz. Calibration: ``declared`` (each sensor's ``segment`` and ``q_segment_sensor``),
    ``still_pose`` (each sensor's ``segment``; the first ``still_seconds`` are a still N-pose or T-pose, repeated
    until still) or ``assignment`` (lower-body sensors: the stream's own I2S assignment places them and hands
    over its alignments once it is sure)."""

    model_config = ConfigDict(extra="forbid")
    model: str | None = Field(None, description="a streaming pose model's name; default: the one for the sensors")
    calibration: Literal["declared", "still_pose", "assignment"] = "declared"
    still_pose: Literal["npose", "tpose"] = "npose"
    still_seconds: float = Field(2.0, ge=0.5, le=10.0, allow_inf_nan=False)
    pelvis_back_axis: Direction3 = Field(default_factory=lambda: [0.0, 0.0, 1.0])
    body_height_m: float | None = Field(None, ge=0.5, le=2.5, allow_inf_nan=False)
    assignment_confidence: float = Field(0.9, gt=0.0, le=1.0, description="assignment: hand over at this confidence")
    hand_over: Literal["confidence", "committed"] | None = Field(
        None,
        description="assignment: hand over once each of the pose model's sensors is `committed` by the assignment "
        "model's calibration (sure as its selective accuracy; may take long, or never come on gaits it is unsure "
        "of), or once each reaches `assignment_confidence` (the softmax: quick, but near 1 right or wrong); default: "
        "`committed` where the served assignment model has a calibration, else `confidence` (the `started` message "
        "says which)",
    )
    output: Literal["json", "binary", "bvh"] = Field(
        "json",
        description="pose messages as JSON, as binary pose blocks (``encode_pose_block``), or as lines of a BVH "
        "file's motion table (``bvh_pose_message``)",
    )
    translation: Literal["none", "feet", "learned"] = Field("none", description=TRANSLATION_DESCRIPTION)
    pelvis_heading: Literal["alignment", "legs"] | None = Field(None, description=PELVIS_HEADING_DESCRIPTION)
    joint_angles: StrictBool = Field(
        False,
        description="each JSON pose message also carries joint_angles_deg: per joint whose two segments are answered "
        "(sensor or model), its flexion, abduction and rotation per frame in degrees (service.core.joint_angles)",
    )

    @model_validator(mode="after")
    def _angles_in_json(self) -> PoseStreamOptions:
        if self.joint_angles and self.output != "json":
            raise ValueError(f"joint_angles come in JSON pose messages; output {self.output!r} carries none")
        return self


class StartMessage(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: Literal["start"]
    sensors: list[StreamSensor] = Field(min_length=1, max_length=64)
    allow_shared: bool = False
    worn_segments: SegmentSet | None = Field(None, description=WORN_SEGMENTS_DESCRIPTION)
    pose: PoseStreamOptions | None = None

    @model_validator(mode="after")
    def _declarations_agree(self) -> StartMessage:
        check_declarations([s.candidate_segments for s in self.sensors], self.worn_segments, "sensors")
        if self.pose is None:
            return self
        for k, s in enumerate(self.sensors):
            if s.sample_rate_hz != 60.0:
                raise ValueError(
                    f"sensors[{k}].sample_rate_hz: pose sessions stream at 60 Hz, got {s.sample_rate_hz:g}"
                )
            if self.pose.calibration != "assignment" and s.segment is None:
                raise ValueError(
                    f"sensors[{k}].segment: calibration {self.pose.calibration!r} needs each sensor's segment"
                )
            if self.pose.calibration == "declared" and s.q_segment_sensor is None:
                raise ValueError(f"sensors[{k}].q_segment_sensor: calibration 'declared' needs each sensor's alignment")
        segments = [s.segment for s in self.sensors if s.segment is not None]
        if len(set(segments)) != len(segments):
            raise ValueError(f"sensors: one sensor per segment, got {segments}")
        return self


class SamplesMessage(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: Literal["samples"]
    sensor_id: str
    seq: int = Field(ge=0, strict=True)
    samples: list[Sample] = Field(min_length=1)


def decode_binary(data: bytes, n_sensors: int, max_samples: int, width: int = 6) -> tuple[int, int, np.ndarray]:
    """(sensor index, seq, samples ``(n, width)`` float64) from a binary packet (width 10 in pose sessions); for a
    frame packet (index ``ALL_SENSORS``) the samples of every sensor, ``(n, n_sensors, width)``."""
    if len(data) < HEADER.size:
        raise ProtocolError(f"binary packet needs an {HEADER.size}-byte header, got {len(data)} bytes", 1003)
    index, n, seq = HEADER.unpack_from(data)
    every = index == ALL_SENSORS
    if index >= n_sensors and not every:
        raise ProtocolError(
            f"binary packet names sensor index {index}; the session has {n_sensors} sensors "
            f"(0-{n_sensors - 1}, or {ALL_SENSORS} for all of them at once)"
        )
    if n > max_samples:
        raise ProtocolError(f"at most {max_samples} samples per packet, got {n}", 1009)
    shape = (n, n_sensors, width) if every else (n, width)
    expected = HEADER.size + 4 * n * width * (n_sensors if every else 1)
    if len(data) != expected:
        what = f"n={n} samples of {n_sensors} sensors" if every else f"n={n}"
        raise ProtocolError(f"binary packet with {what} must be {expected} bytes, got {len(data)}", 1003)
    return index, seq, np.frombuffer(data, dtype="<f4", offset=HEADER.size).reshape(shape).astype(np.float64)


def encode_binary(index: int, seq: int, samples: np.ndarray) -> bytes:
    """The client side of ``decode_binary``: one sensor's samples ``(n, width)``, or with ``ALL_SENSORS`` every
    sensor's ``(n, S, width)``."""
    return HEADER.pack(index, len(samples), seq) + np.asarray(samples, dtype="<f4").tobytes()


POSE_BLOCK = struct.Struct("<HHII")  # kind (1: pose, 2: pose and translation), segments, first_frame, frames
POSE_BLOCK_KIND = 1
POSE_BLOCK_KIND_TRANSLATED = 2


def encode_pose_block(message: dict) -> bytes:
    """A ``pose`` message as a binary pose block (the module docstring has the layout)."""
    q = np.asarray(message["q_world_segment"], dtype="<f4")
    p = np.asarray(message["joint_positions_m"], dtype="<f4")
    root = message.get("root_position_m")
    kind = POSE_BLOCK_KIND if root is None else POSE_BLOCK_KIND_TRANSLATED
    header = POSE_BLOCK.pack(kind, q.shape[1], message["first_frame"], message["frames"])
    tail = b"" if root is None else np.asarray(root, dtype="<f4").tobytes()
    return header + q.tobytes() + p.tobytes() + tail


def bvh_pose_message(message: dict, body: Body) -> dict:
    """A ``pose`` message as the lines of a BVH file's motion table (``bvh_started``'s joints and channels)."""
    R = matrix_from_quat(np.asarray(message["q_world_segment"], dtype=np.float64))
    root = message.get("root_position_m")
    rows = bvh_motion_text(body_bvh(R, body, MODEL_RATE_HZ, None if root is None else np.asarray(root)).motion)
    return {"type": "pose", "first_frame": message["first_frame"], "frames": message["frames"], "bvh_motion": rows}


def bvh_started(body: Body) -> dict:
    """What ``started.pose`` adds for a ``bvh`` pose stream: the HIERARCHY of the BVH file its lines belong to
    (``bvh_pose_message``) and the file's frame time."""
    hierarchy = bvh_hierarchy_text(body_bvh(np.zeros((0, len(body.segments), 3, 3)), body, MODEL_RATE_HZ))
    return {"bvh_hierarchy": hierarchy, "frame_time_s": 1.0 / MODEL_RATE_HZ}


def decode_pose_block(data: bytes) -> dict:
    """The client side of ``encode_pose_block``: the ``pose`` message it holds, with numpy arrays."""
    kind, segments, first_frame, frames = POSE_BLOCK.unpack_from(data)
    translated = kind == POSE_BLOCK_KIND_TRANSLATED
    size = POSE_BLOCK.size + 28 * frames * segments + (12 * frames if translated else 0)
    if kind not in (POSE_BLOCK_KIND, POSE_BLOCK_KIND_TRANSLATED) or len(data) != size:
        raise ValueError(f"not a pose block: kind {kind}, {len(data)} bytes for {frames} frames × {segments} segments")
    values = np.frombuffer(data, dtype="<f4", offset=POSE_BLOCK.size)
    q = values[: 4 * frames * segments].reshape(frames, segments, 4)
    p = values[4 * frames * segments : 7 * frames * segments].reshape(frames, segments, 3)
    message = {
        "type": "pose",
        "first_frame": first_frame,
        "frames": frames,
        "q_world_segment": q,
        "joint_positions_m": p,
    }
    if translated:
        message["root_position_m"] = values[7 * frames * segments :].reshape(frames, 3)
    return message


def check_samples(samples: np.ndarray, max_samples: int, where: str, width: int = 6) -> None:
    if samples.ndim != 2 or samples.shape[1] != width:
        raise ProtocolError(f"{where}: samples must be rows of {width} values, got shape {samples.shape}")
    if len(samples) > max_samples:
        raise ProtocolError(f"{where}: at most {max_samples} samples per packet, got {len(samples)}", 1009)
    # One reduction for the usual, valid packet (NaN fails the comparison, as Inf does); the messages below only
    # when it fails. Live streams check every packet, a few samples each, where each numpy call's own cost counts.
    largest = np.abs(samples).max(initial=0.0)
    if not largest <= MAX_ABS_READING:
        if not np.all(np.isfinite(samples)):
            raise ProtocolError(f"{where}: samples must be finite, got NaN or Inf")
        raise ProtocolError(
            f"{where}: samples must lie in [-{MAX_ABS_READING:g}, {MAX_ABS_READING:g}] (in their unit), got {largest:g}"
        )
    if width == 10:
        q = samples[:, 6:10]
        norm = np.sqrt(np.einsum("ij,ij->i", q, q))
        if np.abs(norm - 1.0).max(initial=0.0) > UNIT_QUAT_TOLERANCE:
            i = int(np.argmax(np.abs(norm - 1.0)))
            raise ProtocolError(
                f"{where}: sample {i}'s q_world_sensor must be a unit quaternion, got norm {norm[i]:.3f}"
            )


def check_frame_samples(samples: np.ndarray, max_samples: int, sensor_ids: list[str], width: int) -> None:
    """``check_samples`` for a frame packet's ``(n, S, width)``: one pass over every sensor, and on a mistake the
    error of the first sensor it is in."""
    flat = samples.reshape(-1, width)
    ok = bool(np.all(np.isfinite(flat))) and np.abs(flat).max(initial=0.0) <= MAX_ABS_READING
    if ok and width == 10:
        norm = np.sqrt(np.einsum("ij,ij->i", flat[:, 6:10], flat[:, 6:10]))
        ok = bool(np.all(np.abs(norm - 1.0) <= UNIT_QUAT_TOLERANCE))
    if ok:
        return
    for k, sensor_id in enumerate(sensor_ids):
        check_samples(samples[:, k], max_samples, f"sensor {sensor_id}", width)
