"""WebSocket ``/v1/stream`` (protocol in ``service.api.protocol``).

A slow consumer never grows server memory without bound: every outgoing message type is bounded and a consumer
that stays behind is closed with 1008 and a reason (``service.api.outbox``). A new session is admitted against
the measured inference capacity or refused with 1013 (``service.api.stream_admission``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from fastapi import APIRouter, FastAPI, WebSocket, WebSocketDisconnect
from pydantic import ValidationError

from service.api.outbox import Outbox, SlowConsumer, accept, close, end_session, sender, serve_watched
from service.api.protocol import (
    ALL_SENSORS,
    CalibrateMessage,
    ProtocolError,
    SamplesMessage,
    StartMessage,
    bvh_pose_message,
    bvh_started,
    check_frame_samples,
    check_samples,
    decode_binary,
    encode_pose_block,
)
from service.api.schemas import finite_or_none
from service.api.stream_admission import I2S_WINDOWS_PER_SENSOR_S, admit_or_refuse, record_answer_latency
from service.core.assignment import (
    ConfidenceModel,
    MomentAssembler,
    allowed_segments,
    assignment_confidence,
    gyro_norm,
    is_moving,
    joint_assignment,
    session_swing_weight,
    turns_about_vertical,
)
from service.core.body import BODY_SEGMENTS
from service.core.calibration import LEG_SEGMENTS
from service.core.pose_stream import AlignResult, FrameAligner, StreamLagError
from service.core.rotations import canonical_quat
from service.core.segments import SEGMENTS, segment_indices, segment_names
from service.core.stream import SensorStream
from service.core.units import ACC_UNITS, GYR_UNITS, UNIT_CHECK_SECONDS, unit_warnings
from service.inference.pose import LivePose, PoseModel, fitting_models, general_first
from service.inference.predict import RunningAlignment, alignment_answer, window_results
from service.inference.velocity import VelocityModel, learned_velocity_model, velocity_model_for

log = logging.getLogger(__name__)

# A sensor's units are checked over its first windows (about 3 s of readings), as the REST routes check a request's.
UNIT_CHECK_WINDOWS = 4

router = APIRouter()


@dataclass
class Work:
    """One accepted packet on its way through inference: its windows and any gap/late notices."""

    sensor: int
    received: float  # perf_counter() when the packet arrived
    windows: list[np.ndarray] = field(default_factory=list)
    window_end_s: list[float] = field(default_factory=list)
    notices: list[dict] = field(default_factory=list)


class Session:
    """One WebSocket session: its sensors' ring buffers, the joint-assignment evidence and the inference
    pipeline. The receive loop never waits for inference: accepted packets queue here and one worker per
    session runs everything queued as one ``batcher.infer`` call, so a session that fell behind catches up
    in one round trip instead of one round trip per packet. At most ``max_pending`` windows wait; beyond
    that the receive loop stops reading the socket until the worker catches up (TCP back-pressure)."""

    def __init__(
        self,
        start: StartMessage,
        max_pending: int,
        alignment_windows: int = 450,
        confidence: ConfidenceModel | None = None,
        assignment_interval_s: float = 0.0,
    ) -> None:
        ids = [s.sensor_id for s in start.sensors]
        if len(set(ids)) != len(ids):
            raise ProtocolError(f"sensor_id values must be unique, got {ids}")
        self.streams = [SensorStream(s.sensor_id, s.sample_rate_hz, s.acc_unit, s.gyr_unit) for s in start.sensors]
        self.index = {s.sensor_id: k for k, s in enumerate(self.streams)}
        self.allow_shared = start.allow_shared
        self.worn = segment_indices(start.worn_segments)
        self.candidates = [segment_indices(s.candidate_segments) for s in start.sensors]
        # A sensor that the declarations leave on one segment: its windows' alignments are given for that segment.
        allowed = allowed_segments(len(self.streams), len(SEGMENTS), self.worn, self.candidates)
        self.known = [int(row.argmax()) if row.sum() == 1 else None for row in allowed]
        # Each sensor's evidence, as ``/v1/imu/assign`` weighs it (``session_assignment``): its moving windows, or all
        # its windows while none of them has moved (a pelvis on a slow walker may not move for seconds).
        self.evidence = np.zeros((len(self.streams), len(SEGMENTS)))
        self.still_evidence = np.zeros((len(self.streams), len(SEGMENTS)))
        self.still_windows = np.zeros(len(self.streams), dtype=np.int64)
        self.votes = np.zeros((len(self.streams), len(SEGMENTS)), dtype=np.int64)  # moving windows ranking each first
        self.confidence = confidence
        # A one-sensor session without declarations: its moment is its window's own answer, already in the result.
        many = len(self.streams) > 1 or self.worn is not None or self.candidates[0] is not None
        self.moments = (
            MomentAssembler(len(self.streams), start.allow_shared, worn=self.worn, candidates=self.candidates)
            if many
            else None
        )
        self.windows = np.zeros(len(self.streams), dtype=np.int64)
        # Each sensor's first UNIT_CHECK_WINDOWS windows, checked once for implausible units, then dropped.
        self.unit_check: list[list[np.ndarray] | None] = [[] for _ in self.streams]
        self.alignments = [RunningAlignment(alignment_windows) for _ in self.streams]
        # The running assignment goes out after the first results, then once the session has answered as many
        # windows as its sensors make in ``assignment_interval_s`` of stream time (a count, so that a sensor whose
        # clock jumps cannot hold it back, and a replay gets about as many per second of stream time), and at the
        # end: the joint answer, its calibration and the robust alignment means were the event loop's largest
        # per-window work, and an answer over seconds of evidence moves little from one hop to the next.
        self.assignment_interval_s = assignment_interval_s
        per_sensor = math.ceil(assignment_interval_s * I2S_WINDOWS_PER_SENSOR_S - 1e-9)
        self.assignment_every = max(1, per_sensor * len(self.streams))  # windows between messages
        self.windows_since_assignment: int | None = None  # None: none sent yet
        self.max_pending = max_pending
        self.work: deque[Work] = deque()
        self.pending = 0  # windows queued or being inferred
        self.wake, self.idle, self.room = asyncio.Event(), asyncio.Event(), asyncio.Event()
        self.idle.set()
        self.room.set()
        self.failure: Exception | None = None
        self.pose: LivePose | None = None
        self.pose_order: list[int] | None = None  # stream sensor index of each of the model's, then measured, sensors
        self.aligner: FrameAligner | None = None
        self.run_i2s = True
        self.width = 6  # values per sample: 10 in pose sessions
        self._units_all: np.ndarray | None = None
        # A pose session's first UNIT_CHECK_SECONDS of body frames, checked once for implausible units, then dropped.
        self.pose_unit_check: list[np.ndarray] | None = []
        self.pose_threshold = 0.9
        self.outbox: Outbox | None = None

    def start_pose(
        self, start: StartMessage, models: dict[str, PoseModel], velocity_models: dict[str, VelocityModel]
    ) -> None:
        """Choose the streaming model, its calibration and translation (``PoseStreamOptions``); ProtocolError if
        none fits."""
        opts = start.pose
        segments = [s.segment for s in start.sensors]

        def first(found: list[PoseModel]) -> PoseModel:  # with translation learned, one a velocity model reads
            learned = opts.translation == "learned"
            return min(found, key=lambda m: learned and velocity_model_for(velocity_models, m.spec) is None)

        if opts.calibration == "assignment":
            candidates = [m for m in general_first(models) if m.spec.streaming and set(m.spec.sensors) <= set(SEGMENTS)]
            if opts.model is not None:
                candidates = [m for m in candidates if m.name == opts.model]
            if not candidates:
                raise ProtocolError(
                    f"pose.calibration 'assignment' needs a streaming model whose sensors are lower-body segments "
                    f"({opts.model or 'any'}); loaded pose models: {sorted(models)}"
                )
            model = first(candidates)
            measured: list[str] = []  # the assignment's other sensors join at the hand-over (``hand_over``)
        else:
            streaming = [m for m in general_first(models) if m.spec.streaming and opts.model in (None, m.name)]
            fitting = fitting_models(streaming, segments)
            if not fitting:
                placements = sorted({", ".join(m.spec.sensors) for m in models.values() if m.spec.streaming})
                raise ProtocolError(
                    f"pose: no streaming pose model{' ' + opts.model if opts.model else ''} takes sensors on "
                    f"{segments}; "
                    f"the loaded ones take [{'] or ['.join(placements)}]"
                )
            model = first(fitting)
            measured = [seg for seg in segments if seg not in model.spec.sensors]
            self.pose_order = [segments.index(seg) for seg in [*model.spec.sensors, *measured]]
        pelvis_heading = opts.pelvis_heading or ("legs" if opts.calibration == "assignment" else "alignment")
        if pelvis_heading == "legs" and not LEG_SEGMENTS & set(model.spec.sensors):
            raise ProtocolError(
                f"pose.pelvis_heading 'legs' needs a sensor on a thigh, shank or foot; {model.name} reads "
                f"{model.spec.sensors}"
            )
        q = None
        if opts.calibration == "declared":
            q = canonical_quat(np.array([start.sensors[k].q_segment_sensor for k in self.pose_order], dtype=np.float64))
        self.pose = LivePose(
            model,
            opts.calibration,
            q,
            int(round(opts.still_seconds * 60.0)),
            opts.still_pose,
            tuple(opts.pelvis_back_axis),
            opts.body_height_m,
            opts.translation,
            _velocity_model(model, opts.translation, velocity_models),
            pelvis_heading,
            measured,
            opts.joint_angles,
        )
        self.aligner = FrameAligner(len(self.streams), 10, [st.sensor_id for st in self.streams])
        self.run_i2s = opts.calibration == "assignment"
        self.width = 10
        self.pose_threshold = opts.assignment_confidence
        # committed where the assignment model is calibrated: the softmax confidence nears 1 right or wrong
        self.hand_over_when = opts.hand_over or ("confidence" if self.confidence is None else "committed")
        if self.run_i2s and opts.hand_over == "committed" and self.confidence is None:
            raise ProtocolError(
                "pose: hand_over 'committed' needs an assignment model with a calibration (its manifest's "
                "`confidence`); the served one has none: use hand_over 'confidence'"
            )
        self.pose_output = opts.output

    def pose_units_all(self) -> np.ndarray:
        """``pose_units`` of every sensor ``(N, 10)``."""
        if self._units_all is None:
            units = [(ACC_UNITS[s.acc_unit], GYR_UNITS[s.gyr_unit]) for s in self.streams]
            self._units_all = np.array([[acc] * 3 + [gyr] * 3 + [1.0] * 4 for acc, gyr in units])
        return self._units_all

    def pose_units(self, k: int) -> np.ndarray:
        """Per-column factors of sensor ``k``'s rows into m/s², rad/s and a unitless quaternion."""
        return self.pose_units_all()[k]

    def sure_enough(self, sensor: dict) -> bool:
        """A sensor's place is sure enough to pose on (``PoseStreamOptions.hand_over``): its softmax confidence at
        ``assignment_confidence`` (quick; it reaches 1 within seconds, right or wrong), or committed by the
        assignment model's calibration (the answers its selective accuracy counts; it may take long)."""
        if self.hand_over_when == "committed":
            return bool(sensor["committed"])
        return sensor["confidence"] >= self.pose_threshold

    def hand_over(self, message: dict) -> dict | None:
        """Assignment calibration: once the joint assignment puts a sensor on each of the model's segments with
        an alignment and each is sure (``sure_enough``), those become the pose calibration; the calibration
        message."""
        live = self.pose
        if live is None or live.calibrated or live.method != "assignment":
            return None
        by_segment = {s["segment"]: (k, s) for k, s in enumerate(message["sensors"]) if s["segment"] is not None}
        need = live.model.spec.sensors
        if not all(seg in by_segment for seg in need):
            return None
        chosen = [by_segment[seg] for seg in need]
        if any(s["alignment"] is None or not self.sure_enough(s) for _, s in chosen):
            return None
        # the session's other sensors placed and aligned as surely: answered as measured
        more = [(k, s) for seg, (k, s) in by_segment.items() if seg not in need]
        more = [(k, s) for k, s in more if s["alignment"] is not None and self.sure_enough(s)]
        self.pose_order = [k for k, _ in chosen + more]
        live.measure([s["segment"] for _, s in more])
        live.q_segment_sensor = canonical_quat(np.array([s["alignment"]["q_segment_imu"] for _, s in chosen + more]))
        return {
            "type": "calibration",
            "status": "calibrated",
            "method": "assignment",
            "segments": {s["sensor_id"]: s["segment"] for _, s in chosen + more},
            "measured": live.measured,
        }

    def submit(self, work: Work) -> None:
        self.work.append(work)
        self.pending += len(work.windows)
        self.idle.clear()
        self.wake.set()
        if self.pending >= self.max_pending:
            self.room.clear()

    async def flush(self) -> None:
        """Wait until every accepted packet's results are in the outbox."""
        await self.idle.wait()
        self.raise_failure()

    def raise_failure(self) -> None:
        if self.failure is not None:
            raise ProtocolError(f"inference failed on the server: {self.failure}", 1011)

    def moment_messages(self, final: bool = False) -> list[dict]:
        """The per-moment one-to-one answers that are ready (all of them at the end of the stream)."""
        if self.moments is None:
            return []
        answered = self.moments.flush() if final else self.moments.ready()
        return [
            {
                "type": "moment",
                "window_end_s": end_s,
                "segments": {self.streams[k].sensor_id: SEGMENTS[g] if g >= 0 else None for k, g in answer.items()},
            }
            for end_s, answer in answered
        ]

    def check_units(self, item: Work) -> dict | None:
        """A ``warning`` message once a sensor's first ``UNIT_CHECK_WINDOWS`` windows read implausibly for its
        declared units (``service.core.units.unit_warnings``, as the REST routes give ``warnings``); None otherwise.
        Each sensor is checked once."""
        first = self.unit_check[item.sensor]
        if first is None or not item.windows:
            return None
        first.extend(item.windows[: UNIT_CHECK_WINDOWS - len(first)])
        if len(first) < UNIT_CHECK_WINDOWS:
            return None
        self.unit_check[item.sensor] = None
        stream = self.streams[item.sensor]
        found = unit_warnings(np.stack(first), stream.acc_unit, stream.gyr_unit)
        return {"type": "warning", "sensor_id": stream.sensor_id, "warnings": found} if found else None

    def check_pose_units(self, frames: np.ndarray) -> list[dict]:
        """``warning`` messages, once per sensor, when a pose session's first ``UNIT_CHECK_SECONDS`` of body frames
        ``(n, sensors, 10)`` read implausibly for the sensor's declared units (as ``check_units`` for I2S windows;
        an I2S-and-pose session is checked there)."""
        if self.pose_unit_check is None or self.run_i2s or not len(frames):
            return []
        self.pose_unit_check.append(frames)
        first = np.concatenate(self.pose_unit_check)
        if len(first) < UNIT_CHECK_SECONDS * self.streams[0].sample_rate_hz:
            return []
        self.pose_unit_check = None
        messages = []
        for k, stream in enumerate(self.streams):
            found = unit_warnings(first[None, :, k, :6], stream.acc_unit, stream.gyr_unit)
            if found:
                messages.append({"type": "warning", "sensor_id": stream.sensor_id, "warnings": found})
        return messages

    def assignment_due(self, windows: int) -> bool:
        """Whether the running assignment goes out after this group of ``windows`` results
        (``assignment_interval_s``). A session that calibrates its pose from the assignment gets one after every
        group until the hand-over, which reads them."""
        since = windows + (self.windows_since_assignment or 0)
        waiting_pose = self.pose is not None and self.pose.method == "assignment" and not self.pose.calibrated
        if self.windows_since_assignment is not None and since < self.assignment_every and not waiting_pose:
            self.windows_since_assignment = since
            return False
        self.windows_since_assignment = 0
        return True

    def assignment_pending(self) -> bool:
        """Results have been sent since the last running assignment (or none was sent yet after results)."""
        answered = bool((self.windows + self.still_windows).any())
        return bool(self.windows_since_assignment) or (self.windows_since_assignment is None and answered)

    def assignment_message(self, dropped: int, final: bool = False) -> dict:
        """The running joint assignment; ``final``: the stream's last, whose alignments read every window."""
        evidence = np.where(self.windows[:, None] > 0, self.evidence, self.still_evidence)
        swing = None if self.moments is None else self.moments.swing  # as /v1/imu/assign weighs it
        joint = joint_assignment(
            [e[None] for e in evidence],
            self.allow_shared,
            worn=self.worn,
            candidates=self.candidates,
            swing=swing,
            swing_weight=session_swing_weight(self.confidence),
        )
        calibrated = assignment_confidence(self.confidence, joint, self.votes, self.windows)
        p_correct = calibrated.p_correct
        sensors = []
        seen = self.windows + self.still_windows
        for k, (s, g, n) in enumerate(zip(self.streams, joint.segment.tolist(), self.windows, strict=True)):
            mean = self.alignments[k].mean(g, fresh=final) if g >= 0 and n else None
            sensors.append(
                {
                    "sensor_id": s.sensor_id,
                    "segment": SEGMENTS[g] if g >= 0 and seen[k] else None,
                    "confidence": float(joint.confidence[k]) if seen[k] else 0.0,
                    "p_correct": None if p_correct is None else float(p_correct[k]),
                    "committed": None if calibrated.committed is None else bool(calibrated.committed[k]),
                    "margin": finite_or_none(joint.margin[k]) if seen[k] else 0.0,
                    "windows": int(n),
                    "alignment": None if mean is None else alignment_answer(g, mean[0]),
                    "alignment_spread_deg": None if mean is None else mean[1],
                }
            )
        return {
            "type": "assignment",
            "sensors": sensors,
            "p_all_correct": calibrated.p_all_correct,
            "status": calibrated.status,
            "results_dropped": dropped,
        }


async def _accept_pose(app: FastAPI, session: Session, k: int, seq: int, samples: np.ndarray, outbox: Outbox) -> None:
    """Join the packet into body frames and run the live pose on every frame all sensors have reached."""
    try:
        joined = session.aligner.push(k, seq, samples * session.pose_units(k))
    except StreamLagError as exc:
        raise ProtocolError(str(exc)) from None
    sensor_id = session.streams[k].sensor_id
    if joined.late is not None and not session.run_i2s:
        expected, received = joined.late
        outbox.put(
            {
                "type": "late",
                "sensor_id": sensor_id,
                "expected_seq": expected,
                "received_seq": received,
                "samples_dropped": joined.late_dropped,
                "action": _late_action(joined.late_dropped, len(samples)),
            }
        )
    if joined.filled and not session.run_i2s:
        outbox.put(_gap_message(sensor_id, seq, joined.filled))
    if len(joined.frames):
        await _pose_frames(app, session, joined)


def _late_action(dropped: int, received: int) -> str:
    if dropped == received:
        return "packet dropped"
    return f"{dropped} repeated samples dropped, the {received - dropped} new ones accepted"


def _gap_message(sensor_id: str, seq: int, filled: int) -> dict:
    return {
        "type": "gap",
        "sensor_id": sensor_id,
        "expected_seq": seq - filled,
        "received_seq": seq,
        "missing": filled,
        "action": "held the last sample",
    }


async def _pose_frames(app: FastAPI, session: Session, joined: AlignResult) -> None:
    """Run the live pose on the body frames all sensors have reached; queue its messages."""
    outbox = session.outbox
    for warning in session.check_pose_units(joined.frames):
        outbox.put(warning)
    if not len(joined.frames) or session.pose_order is None:
        return
    received = time.perf_counter()
    frames = joined.frames[:, session.pose_order]
    messages = await app.state.pose_batcher.process(session.pose, frames, joined.first_frame)
    for message in messages:
        binary = message["type"] == "pose" and session.pose_output == "binary"
        if message["type"] == "pose" and session.pose_output == "bvh":
            message = bvh_pose_message(message, session.pose.body)
        if outbox.put_binary("pose", encode_pose_block(message)) if binary else outbox.put(message):
            app.state.metrics.dropped.inc()
        if message["type"] == "pose":
            record_answer_latency(app, time.perf_counter() - received, pose=True)


async def _accept_packet(app: FastAPI, session: Session, k: int, seq: int, samples: np.ndarray) -> None:
    """Buffer a packet's samples and queue its windows (and any sequence notice) for inference."""
    if session.pose is not None:
        await _accept_pose(app, session, k, seq, samples, session.outbox)
        if not session.run_i2s:
            return
        samples = samples[:, :6]
    stream = session.streams[k]
    work = Work(k, time.perf_counter())
    pushed = stream.push(seq, samples)
    app.state.metrics.samples.inc(len(samples))
    for kind, problem, extra in (("gap", pushed.gap, "missing"), ("late", pushed.late, "action")):
        if problem is None:
            continue
        app.state.metrics.gaps.inc()
        expected, received = problem
        message = {"type": kind, "sensor_id": stream.sensor_id, "expected_seq": expected, "received_seq": received}
        if kind == "gap":
            message[extra] = received - expected
        else:
            message["samples_dropped"] = pushed.late_dropped
            message[extra] = _late_action(pushed.late_dropped, len(samples))
        work.notices.append(message)
    if not (pushed.windows or work.notices):
        return
    work.windows, work.window_end_s = pushed.windows, pushed.window_end_s
    session.submit(work)
    await session.room.wait()
    session.raise_failure()


async def _infer_loop(app: FastAPI, session: Session, outbox: Outbox) -> None:
    """The session's worker: takes everything queued, one inference call, results in arrival order."""
    wait_ms = app.state.settings.stream_batch_wait_ms
    while True:
        await session.wake.wait()
        session.wake.clear()
        while session.work:
            items = list(session.work)
            session.work.clear()
            try:
                await _run_work(app, session, items, outbox, wait_ms)
            except Exception as exc:  # a model failure ends the session with 1011, never silently
                log.exception("stream inference failed")
                session.failure = exc
                session.idle.set()
                session.room.set()
                return
            session.pending -= sum(len(w.windows) for w in items)
            if session.pending < session.max_pending:
                session.room.set()
        session.idle.set()


async def _run_work(app: FastAPI, session: Session, items: list[Work], outbox: Outbox, wait_ms: float) -> None:
    windows = [w for item in items for w in item.windows]
    results: list[dict] = []
    moving, log_probs, quats = np.zeros(0, dtype=bool), np.zeros((0, len(SEGMENTS))), None
    norms = np.zeros((0, 0))
    if windows:
        imu = np.stack(windows)
        probs, quats = await app.state.batcher.infer(imu, wait_ms)
        moving = is_moving(imu)
        norms = gyro_norm(imu)
        known = [session.known[item.sensor] for item in items for _ in item.windows]
        results = window_results(probs, quats, moving, turns_about_vertical(imu), known)
        log_probs = np.log(np.clip(probs, 1e-12, 1.0))
    row = 0
    for item in items:
        for notice in item.notices:
            outbox.put(notice)
        sensor_id = session.streams[item.sensor].sensor_id
        for end_s in item.window_end_s:
            message = {"type": "result", "sensor_id": sensor_id, "window_end_s": round(end_s, 6)}
            message.update(results[row])
            if session.moments is not None:
                session.moments.add(item.sensor, end_s, log_probs[row], bool(moving[row]), norms[row])
            if not moving[row]:
                session.still_evidence[item.sensor] += log_probs[row]
                session.still_windows[item.sensor] += 1
            else:
                session.evidence[item.sensor] += log_probs[row]
                session.votes[item.sensor, int(log_probs[row].argmax())] += 1
                session.windows[item.sensor] += 1
                if quats is not None:
                    session.alignments[item.sensor].add(quats[row])
            if outbox.put(message):
                app.state.metrics.dropped.inc()
            row += 1
        if item.windows:
            record_answer_latency(app, time.perf_counter() - item.received)
        if (warning := session.check_units(item)) is not None:
            outbox.put(warning)
    for moment in session.moment_messages():
        if outbox.put(moment):
            app.state.metrics.dropped.inc()
    if windows and session.assignment_due(len(windows)):
        message = session.assignment_message(outbox.dropped)
        outbox.put(message)
        handed = session.hand_over(message)
        if handed is not None:
            outbox.put(handed)


def _recalibrate(session: Session, data: dict) -> None:
    """``{"type": "calibrate"}``: a still-pose session holds its still pose again (``LivePose.recalibrate``); with
    ``q_segment_sensor``, a declared session takes new alignments from the next frame on (``LivePose.realign``)."""
    try:
        message = CalibrateMessage.model_validate(data)
    except ValidationError as exc:
        raise ProtocolError(f"invalid 'calibrate' message: {_first_error(exc)}") from None
    pose = session.pose
    how = "no pose" if pose is None else f"pose calibration {pose.method!r}"
    if message.q_segment_sensor is None:
        if pose is None or pose.method != "still_pose":
            hint = "; send its new alignments in q_segment_sensor"
            raise ProtocolError(
                f"'calibrate' restarts a still-pose calibration; this session has {how}"
                + (hint if pose is not None and pose.method == "declared" else "")
            )
        pose.recalibrate()
        detail = f"calibrate: hold the still pose for {pose.still_frames / 60.0:g} s; the pose starts afresh after it"
        session.outbox.put({"type": "calibration", "status": "waiting", "detail": detail})
        return
    if pose is None or pose.method != "declared":
        raise ProtocolError(f"'calibrate' with q_segment_sensor re-aligns a declared session; this session has {how}")
    unknown = sorted(set(message.q_segment_sensor) - set(session.index))
    if unknown:
        raise ProtocolError(f"calibrate: unknown sensor_id {unknown}; declared: {list(session.index)}")
    order = session.pose_order
    pose.realign({order.index(session.index[i]): q for i, q in message.q_segment_sensor.items()})
    q = pose.q_segment_sensor
    session.outbox.put(
        {
            "type": "calibration",
            "status": "calibrated",
            "method": "declared",
            "detail": f"new alignments of {sorted(message.q_segment_sensor)} from the next frame all sensors complete",
            "q_segment_sensor": {s: np.round(q[k], 6).tolist() for k, s in enumerate(pose.segments)},
        }
    )


def _parse_text(text: str) -> dict:
    try:
        message = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProtocolError(f"messages must be JSON objects; could not parse: {exc.msg} at {exc.pos}", 1003) from None
    except (RecursionError, ValueError):  # nested too deeply, or an integer of thousands of digits
        raise ProtocolError(
            "messages must be JSON objects of readings; this one nests too deeply or has a number of too many digits",
            1003,
        ) from None
    if not isinstance(message, dict) or "type" not in message:
        raise ProtocolError(f"messages need a 'type' field; got {str(message)[:80]}")
    return message


async def _receive_start(ws: WebSocket) -> Session:
    first = await ws.receive()
    if first.get("text") is None:
        raise ProtocolError("the first message must be a JSON 'start' message, got binary data", 1003)
    try:
        start = StartMessage.model_validate(_parse_text(first["text"]))
    except ValidationError as exc:
        raise ProtocolError(f"invalid start message: {_first_error(exc)}") from None
    settings = ws.app.state.settings
    session = Session(
        start,
        settings.stream_max_pending_windows,
        settings.stream_alignment_windows,
        ws.app.state.confidence,
        settings.stream_assignment_interval_s,
    )
    if start.pose is not None:
        session.start_pose(start, ws.app.state.pose_models, ws.app.state.velocity_models)
    return session


def _velocity_model(model: PoseModel, translation: str, models: dict[str, VelocityModel]) -> VelocityModel | None:
    """The velocity model translation 'learned' runs beside ``model`` (``learned_velocity_model``); ProtocolError if
    none reads its features."""
    try:
        return learned_velocity_model(models, model.spec, model.name, translation)
    except LookupError as exc:
        raise ProtocolError(f"pose.translation {exc}") from None


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"])  # empty for a check of the whole message (the error names fields)
    message = err["msg"].removeprefix("Value error, ")
    return f"{where}: {message}" if where else message


async def _serve(ws: WebSocket, session: Session, outbox: Outbox) -> None:
    settings = ws.app.state.settings
    max_samples = settings.stream_max_samples_per_packet
    while True:
        message = await ws.receive()
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000))
        if message.get("bytes") is not None:
            k, seq, samples = decode_binary(message["bytes"], len(session.streams), max_samples, session.width)
            if k == ALL_SENSORS:
                ids = [s.sensor_id for s in session.streams]
                check_frame_samples(samples, max_samples, ids, session.width)
                if session.pose is not None and not session.run_i2s:
                    try:
                        joined = session.aligner.push_all(seq, samples * session.pose_units_all())
                    except StreamLagError as exc:
                        raise ProtocolError(str(exc)) from None
                    if joined is not None:
                        for sensor_id in ids if joined.filled else ():
                            outbox.put(_gap_message(sensor_id, seq, joined.filled))
                        await _pose_frames(ws.app, session, joined)
                        continue
                for j in range(len(session.streams)):
                    await _accept_packet(ws.app, session, j, seq, samples[:, j])
                continue
        else:
            data = _parse_text(message["text"])
            if data["type"] == "calibrate":
                _recalibrate(session, data)
                continue
            if data["type"] == "stop":
                await session.flush()
                for moment in session.moment_messages(final=True):
                    if outbox.put(moment):
                        ws.app.state.metrics.dropped.inc()
                outbox.put(session.assignment_message(outbox.dropped, final=True))
                return
            if data["type"] != "samples":
                raise ProtocolError(
                    f"unexpected message type {str(data['type'])[:40]!r} in a started session: expected 'samples', "
                    "'calibrate' or 'stop'"
                )
            try:
                packet = SamplesMessage.model_validate(data)
            except ValidationError as exc:
                raise ProtocolError(f"invalid {data['type']!r} message: {_first_error(exc)}") from None
            if packet.sensor_id not in session.index:
                raise ProtocolError(f"unknown sensor_id {packet.sensor_id!r}; declared: {list(session.index)}")
            k, seq = session.index[packet.sensor_id], packet.seq
            if any(len(r) != session.width for r in packet.samples):
                what = "acc xyz, gyr xyz, q_world_sensor wxyz" if session.width == 10 else "acc xyz, gyr xyz"
                raise ProtocolError(f"sensor {packet.sensor_id}: every sample needs {session.width} values ({what})")
            samples = np.asarray(packet.samples, dtype=np.float64)
        check_samples(samples, max_samples, f"sensor {session.streams[k].sensor_id}", session.width)
        await _accept_packet(ws.app, session, k, seq, samples)


@router.websocket("/v1/stream")
async def stream(ws: WebSocket) -> None:
    if not await accept(ws):
        return
    settings, metrics = ws.app.state.settings, ws.app.state.metrics
    if "i2s_assignment" not in ws.app.state.models:
        await ws.send_text(json.dumps({"type": "error", "detail": "no i2s_assignment model is loaded"}))
        await close(ws, 1011, "no model loaded")
        return
    outbox = Outbox(settings.stream_queue_limit)
    sending = asyncio.create_task(sender(ws, outbox))
    metrics.open_streams.inc()
    code, reason = 1000, "stop"
    session: Session | None = None
    worker: asyncio.Task | None = None
    admitted: int | None = None
    try:
        session = await _receive_start(ws)
        admitted = _admit(ws.app, session)
        session.outbox = outbox
        worker = asyncio.create_task(_infer_loop(ws.app, session, outbox))
        outbox.put(_started(session))
        await serve_watched(_serve(ws, session, outbox), outbox, settings.stream_slow_consumer_s)
    except ProtocolError as exc:
        code, reason = exc.code, str(exc)
        if session is not None and session.failure is None and code != 1013:
            await session.flush()  # the results of every packet accepted before the mistake still go out
            if session.assignment_pending():  # and the running assignment over all of them
                outbox.put(session.assignment_message(outbox.dropped, final=True))
        outbox.put({"type": "error", "detail": reason, "close_code": code})
    except SlowConsumer as exc:
        code, reason = 1008, str(exc)
    except WebSocketDisconnect as exc:
        code, reason = -1, "1008-slow" if exc.code == 1008 else "client"  # 1008: closed for not answering a ping
    except Exception:  # a fault of the service, not of the client: 1011, never a normal close
        log.exception("stream session failed")
        code, reason = 1011, "internal error: the session failed; what was answered before stands"
        outbox.put({"type": "error", "detail": reason, "close_code": code})
    finally:
        metrics.open_streams.dec()
        ws.app.state.streams.release(admitted)
        if admitted is not None and session is not None and session.pose is not None:
            ws.app.state.pose_batcher.session_closed()
        if worker is not None:
            worker.cancel()
        await end_session(ws, outbox, sending, code, reason)


def _admit(app: FastAPI, session: Session) -> int:
    """The session's admission key; ProtocolError 1013 when it would take the streams past their capacity."""
    demand = len(session.streams) * I2S_WINDOWS_PER_SENSOR_S if session.run_i2s else 0.0
    if session.pose is not None:
        demand += app.state.streams.model_demand(app.state.batcher, session.pose.cost_key, 60.0)
        why = app.state.streams.pose_refusal(app.state.pose_batcher)
        if why:
            app.state.metrics.streams_refused.labels("capacity").inc()
            raise ProtocolError(why, 1013)
    key = admit_or_refuse(app, demand)
    if session.pose is not None:
        app.state.pose_batcher.session_opened()
    return key


def _started(session: Session) -> dict:
    return {
        "pose": _pose_started(session),
        "type": "started",
        "sensors": [s.sensor_id for s in session.streams],
        "window_samples": 128,
        "hop_samples": 16,
        "model_rate_hz": 60.0,
        "assignment_interval_s": session.assignment_interval_s,
        "worn_segments": segment_names(session.worn),
        "candidate_segments": {
            s.sensor_id: segment_names(c) for s, c in zip(session.streams, session.candidates, strict=True)
        },
    }


def _pose_started(session: Session) -> dict | None:
    live = session.pose
    if live is None:
        return None
    return {
        "model": live.model.name,
        "version": live.model.loaded.manifest.version,
        "sensors": live.model.spec.sensors,
        "segments": list(BODY_SEGMENTS),
        "look_ahead_frames": live.model.spec.look_ahead_frames,
        "calibration": live.method,
        "hand_over": session.hand_over_when if live.method == "assignment" else None,
        "still_frames": live.still_frames if live.method == "still_pose" else 0,
        "output": session.pose_output,
        "translation": live.translation,
        "velocity_model": live.velocity.name if live.velocity is not None else None,
        "pelvis_heading": live.pelvis_heading,
        "measured": live.measured if live.method != "assignment" else None,
        "body_height_m": round(live.body.height_m, 3),
        "joint_angles": live.joint_angles,
    } | (bvh_started(live.body) if session.pose_output == "bvh" else {})
