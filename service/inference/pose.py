"""Running an ``imu_pose`` model: offline in overlapping chunks, or streaming with its LSTM state (several live
sessions in one call: ``process_live``), and turning its root-relative output into whole-body orientations and
joint positions (docs/conventions.md, pose output).

Used by the service and by training's evaluation alike, so a shipped model is scored the way it is served.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from service.core.body import BODY_SEGMENTS, PARENT_INDEX, Body, feet_of, segment_origins
from service.core.calibration import (
    LEG_SEGMENTS,
    CalibrationError,
    is_still,
    legs_heading_sum,
    pose_features,
    segment_readings,
    still_pose_calibration,
    turn_about_own_axis,
    turn_about_z,
)
from service.core.joint_angles import answered_joints, joint_angles_deg
from service.core.rotations import canonical_quat, quat_from_matrix
from service.core.translation import RootTracker, advance_bodies
from service.core.windowing import MODEL_RATE_HZ
from service.inference.registry import LoadedModel
from service.inference.stateful import StreamState, batchable, step_many, zero_state
from service.inference.velocity import VelocityModel, world_velocity

Predictor = Callable[[np.ndarray], np.ndarray]  # features (T, F) → R_root_segment (T, S_out, 3, 3)

# What an offline request may hold: readings at 20-400 Hz (resampled to the models' 60 Hz), at most ten minutes.
MIN_POSE_IMU_RATE_HZ, MAX_POSE_IMU_RATE_HZ = 20.0, 400.0
MAX_POSE_FRAMES = 60 * 60 * 10  # frames at 60 Hz per request
# chunks an offline model runs in one call: a 10-minute request in groups, so its memory stays that of ~80 s
CHUNKS_PER_CALL = 32


def chunk_plan(n_frames: int, window: int, context: int) -> list[tuple[int, int, int, int]]:
    """Chunks ``(start, stop, keep_from, keep_to)`` (absolute frames) that cover ``n_frames``: each chunk is at most
    ``window`` long and keeps its middle, ``context`` frames from either end (Zheng et al. 2021: every answer has up to
    150 past and 150 future frames in its 300-frame sequence); the first and last chunks keep their outer ends."""
    if n_frames <= window:
        return [(0, n_frames, 0, n_frames)]
    if window - 2 * context < 1:
        raise ValueError(f"window {window} must exceed twice the context {context}")
    plan, start, keep_from = [], 0, 0
    while start + window < n_frames:
        keep_to = start + window - context
        plan.append((start, start + window, keep_from, keep_to))
        keep_from, start = keep_to, keep_to - context
    plan.append((n_frames - window, n_frames, keep_from, n_frames))
    return plan


def run_chunked(
    predict: Predictor,
    features: np.ndarray,
    window: int,
    context: int,
    predict_many: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """An offline predictor over a whole recording, chunk by chunk (``chunk_plan``). ``predict_many``: the same
    network over a stack of chunks ``(B, window, F)`` in one call; a recording longer than the window is cut into
    chunks all exactly ``window`` long, so they stack (2.6 times faster on 30 s of six sensors, the same answers)."""
    plan = chunk_plan(len(features), window, context)
    if predict_many is not None and len(plan) > 1:
        groups = [plan[k : k + CHUNKS_PER_CALL] for k in range(0, len(plan), CHUNKS_PER_CALL)]
        ys = [y for g in groups for y in predict_many(np.stack([features[start:stop] for start, stop, _, _ in g]))]
    else:
        ys = [predict(features[start:stop]) for start, stop, _, _ in plan]
    out = np.empty((len(features),) + ys[0].shape[1:], dtype=ys[0].dtype)
    for y, (start, _, keep_from, keep_to) in zip(ys, plan, strict=True):
        out[keep_from:keep_to] = y[keep_from - start : keep_to - start]
    return out


class PoseModel:
    """A loaded ``imu_pose`` model with its manifest's pose section."""

    def __init__(self, loaded: LoadedModel) -> None:
        if loaded.manifest.pose is None:
            raise ValueError(f"{loaded.manifest.name} is not an imu_pose model")
        self.loaded, self.spec = loaded, loaded.manifest.pose
        self.body = Body.from_json(self.spec.body)
        self.sensor_index = [BODY_SEGMENTS.index(s) for s in self.spec.sensors]
        self.output_index = [BODY_SEGMENTS.index(s) for s in self.spec.output_segments]

    @property
    def hinge_joints(self) -> bool:
        """Whether its answers' knees are hinges, its elbows in plane and its wrists neutral (``whole_body``): in the
        frames whose limbs take their turn from their hinges, where those hinges are y; a model in a rig's own frames
        is answered as it is."""
        return hinge_joints(self.loaded.manifest.training_data.get("limb_twist"))

    @property
    def assembly(self) -> str:
        """How its answers are assembled, as evaluation digests name it (``assembly``)."""
        return assembly(self.hinge_joints, self.spec.sensors, self.spec.output_segments)

    @property
    def scenario(self) -> dict | None:
        """What the model was trained for when its data were selected for one scenario (``selected_for`` of its
        manifest's training data), else None: a general model."""
        return self.loaded.manifest.training_data.get("selected_for")

    @property
    def name(self) -> str:
        return self.loaded.manifest.name

    def _run(self, features: np.ndarray) -> np.ndarray:
        if not self.spec.streaming:
            return self._run_many(features[None])[0]
        state = self.new_state()
        y, _ = self.step(features, state)
        return y

    def predict(self, features: np.ndarray) -> np.ndarray:
        """R_root_segment ``(T, S_out, 3, 3)`` of every frame of ``features`` ``(T, F)``.

        A streaming model is run over the recording with its look-ahead: the last frame is repeated
        ``look_ahead_frames`` times at the end, so that frame t's answer is the one it gives ``look_ahead`` frames
        later, exactly as on the live stream.
        """
        if self.spec.streaming:
            L = self.spec.look_ahead_frames
            padded = np.concatenate([features, np.repeat(features[-1:], L, axis=0)]) if L else features
            return self._run(padded)[L:]
        return run_chunked(
            self._run, features, self.spec.window_frames, self.spec.context_frames, predict_many=self._run_many
        )

    def _run_many(self, features: np.ndarray) -> np.ndarray:
        """An offline model over a stack of sequences ``(B, T, F)`` → ``(B, T, S_out, 3, 3)``."""
        return self.loaded.session.run(None, {self.loaded.manifest.inputs[0].name: features.astype(np.float32)})[0]

    def new_state(self) -> StreamState:
        return zero_state(self.spec.state_layers, self.spec.state_hidden)

    def step(self, features: np.ndarray, state: StreamState) -> tuple[np.ndarray, StreamState]:
        """Streaming: frames ``(n, F)`` → their outputs ``(n, S_out, 3, 3)`` (each for the frame
        ``look_ahead_frames`` earlier) and the new state."""
        (y,), (state,) = self.step_many([features], [state])
        return y, state

    @property
    def batchable(self) -> bool:
        """Whether the streaming graph takes several sessions in one call (its batch dimension is symbolic)."""
        return batchable(self.loaded.session)

    def step_many(
        self, features: list[np.ndarray], states: list[StreamState]
    ) -> tuple[list[np.ndarray], list[StreamState]]:
        """``step`` for several sessions at once (``service.inference.stateful.step_many``)."""
        return step_many(self.loaded.session, features, states)


def cost_key(model: PoseModel, velocity: VelocityModel | None) -> str:
    return model.name if velocity is None else f"{model.name}+{velocity.name}"


def general_first(models: dict[str, PoseModel]) -> list[PoseModel]:
    """The loaded pose models, the general ones before those trained for a scenario: a request that names no model
    gets a general one where one takes its sensors."""
    return sorted(models.values(), key=lambda m: m.scenario is not None)


def fitting_models(models: list[PoseModel], segments: Sequence[str]) -> list[PoseModel]:
    """Of ``models`` (in order of preference), those whose sensors are exactly ``segments``; where none is, those
    that read the most of them (sensors beyond a model's are answered as measured)."""
    exact = [m for m in models if sorted(m.spec.sensors) == sorted(segments)]
    if exact:
        return exact
    within = [m for m in models if set(m.spec.sensors) < set(segments)]
    most = max((len(m.spec.sensors) for m in within), default=0)
    return [m for m in within if len(m.spec.sensors) == most]


# (thigh, shank) per leg: the knee, a hinge about the segments' y axes (conventions.md frames, the limbs' turn taken
# from the knee's hinge). In the mocap the knee is a hinge within 0.7° in every rig (median per clip),
# docs/pose.md "The knee as a hinge".
KNEES = tuple((BODY_SEGMENTS.index(f"{s}UpperLeg"), BODY_SEGMENTS.index(f"{s}LowerLeg")) for s in ("Left", "Right"))
# (upper arm, forearm) per side: the elbow, whose hinge is the upper arm's y in the same frames (the forearm's long
# axis lies in the upper arm's x-z plane, behind its z: in CMU's rigs exactly, in Bandai-Namco's within 6°, over
# training clips). Not made a hinge as the knee is: a forearm sensor turns with pronation, its long axis does not.
ELBOWS = tuple((BODY_SEGMENTS.index(f"{s}UpperArm"), BODY_SEGMENTS.index(f"{s}ForeArm")) for s in ("Left", "Right"))
# (hand, forearm) per side: the wrist. A hand's frame is fitted to its forearm's target (service.core.body, rule
# "parent"), so the two agree over a rig's walks on average; person by person they do not (CMU's retargeted hands
# sit 10-90° from the forearm: docs/pose.md "Neutral wrists"), and no sensor here sees the wrist's own angle.
WRISTS = tuple((BODY_SEGMENTS.index(f"{s}Hand"), BODY_SEGMENTS.index(f"{s}ForeArm")) for s in ("Left", "Right"))
# elbow flexion (degrees) below which the plane is too ill-defined to turn the upper arm by, and from which it is
# turned fully (linear between; fixed before the figures were read, docs/pose.md "The elbows in plane")
ELBOW_PLANE_FLEXION_DEG = (10.0, 30.0)


def hinge_joints(limb_twist: str | None) -> bool:
    """Whether a model's knees are answered as hinges, its elbows in plane and its wrists neutral: only in the segment
    frames whose limbs take their turn from their hinges (``limb_twist`` "hinge", where the hinges are the y axes; in
    a rig's own frames they lie up to 25° off y, docs/pose.md "Part of it is the rigs' frames")."""
    return limb_twist == "hinge"


def assembly(hinges: bool, sensors: Sequence[str], outputs: Sequence[str]) -> str:
    """How ``whole_body`` assembles a model's answer, as evaluation digests name it: "+knee-hinges" with ``hinges``,
    "+elbow-planes" where also an upper arm is answered beside a sensed forearm and "+neutral-wrists" where a hand is
    (a figure scored one way is not compared with one scored another)."""
    if not hinges:
        return ""

    def beside_a_forearm(joints: tuple[tuple[int, int], ...]) -> bool:
        return any(BODY_SEGMENTS[a] in outputs and BODY_SEGMENTS[f] in sensors for a, f in joints)

    return (
        "+knee-hinges"
        + ("+elbow-planes" if beside_a_forearm(ELBOWS) else "")
        + ("+neutral-wrists" if beside_a_forearm(WRISTS) else "")
    )


def knees_as_hinges(R: np.ndarray, thigh_answered: np.ndarray, shank_sensed: np.ndarray) -> np.ndarray:
    """``R`` ``(T, 21, 3, 3)`` with each thigh the model answered (``thigh_answered[t, k]``) beside a sensed shank
    (``shank_sensed[t, k]``, k the leg) replaced by that shank turned about its y axis by the flexion the model's
    thigh implies: the rotation about y nearest to M = shank⁻¹ · thigh, the twist of its quaternion (w, x, y, z),
    whose angle 2·atan2(y, w) is atan2(M₀₂ − M₂₀, M₀₀ + M₂₂). The model then answers one angle per knee; where the
    thigh lies and how it is turned come from the shank's sensor. In place (``whole_body``'s own array); returns R."""
    for k, (thigh, shank) in enumerate(KNEES):
        use = thigh_answered[:, k] & shank_sensed[:, k]
        if not use.any():
            continue
        M = np.einsum("tji,tjk->tik", R[use, shank], R[use, thigh])
        sin2, cos2 = M[:, 0, 2] - M[:, 2, 0], M[:, 0, 0] + M[:, 2, 2]
        ok = np.hypot(sin2, cos2) > 1e-9  # a half turn about an axis across y has no nearest twist: kept
        rows = np.flatnonzero(use)[ok]
        R[rows, thigh] = turn_about_own_axis(R[rows, shank], np.arctan2(sin2[ok], cos2[ok]), 1)
    return R


def elbows_in_plane(R: np.ndarray, upper_answered: np.ndarray, forearm_sensed: np.ndarray) -> np.ndarray:
    """``R`` ``(T, 21, 3, 3)`` with each upper arm the model answered (``upper_answered[t, k]``) beside a sensed
    forearm (``forearm_sensed[t, k]``, k the side) turned about its own long axis (z) so that the forearm's long axis
    lies in its x-z plane, behind z: the elbow's hinge then runs along the upper arm's y, as in the mocap. Only the
    forearm's long axis is read, so a forearm sensor that turns with pronation changes nothing, and the upper arm's
    direction, with every joint position, stays the model's. The turn is weighted by the elbow's flexion: none below
    ``ELBOW_PLANE_FLEXION_DEG[0]``, where a nearly straight arm does not define the plane, in full from the second.
    Between the two a forearm on the far side of the plane (the elbow read as overstretched, 0.16 % of the arms'
    frames of the validation and held-out clips) is turned by a share of ±180°, whose sign flips as it crosses: such
    a frame's upper arm may turn round against its neighbours'. In place; returns R."""
    low, full = ELBOW_PLANE_FLEXION_DEG
    for k, (upper, forearm) in enumerate(ELBOWS):
        use = upper_answered[:, k] & forearm_sensed[:, k]
        if not use.any():
            continue
        v = np.einsum("tji,tj->ti", R[use, upper], R[use, forearm, :, 2])  # the forearm's z in the upper arm's frame
        flexion = np.degrees(np.arccos(np.clip(v[:, 2], -1.0, 1.0)))
        weight = np.clip((flexion - low) / (full - low), 0.0, 1.0)
        off_plane = np.angle(-(v[:, 0] + 1j * v[:, 1]))  # its azimuth about z from the upper arm's −x
        R[use, upper] = turn_about_own_axis(R[use, upper], weight * off_plane, 2)
    return R


def neutral_wrists(R: np.ndarray, hand_answered: np.ndarray, forearm_sensed: np.ndarray) -> np.ndarray:
    """``R`` ``(T, 21, 3, 3)`` with each hand the model answered (``hand_answered[t, k]``) beside a sensed forearm
    (``forearm_sensed[t, k]``, k the side) answered as that forearm: the wrist in its neutral, where the hand's frame
    meets the forearm's. A forearm sensor near the wrist turns with pronation, which the hand follows and the network,
    trained on mocap forearms that do not pronate, cannot tell; the wrist's own flexion no sensor here sees. In place;
    returns R."""
    for k, (hand, forearm) in enumerate(WRISTS):
        use = hand_answered[:, k] & forearm_sensed[:, k]
        R[use, hand] = R[use, forearm]
    return R


def whole_body(
    R_world_sensor_segment: np.ndarray,
    R_root_out: np.ndarray,
    sensor_index: list[int],
    output_index: list[int],
    measured: np.ndarray | None = None,
    *,
    hinges: bool,
) -> np.ndarray:
    """Global orientations of all ``BODY_SEGMENTS`` ``(T, 21, 3, 3)``: the sensors' segments as measured, the
    others the measured root times the model's root-relative answer (Vlutters 2016 §IV-D). With ``hinges``, each knee
    a hinge where the model answers the thigh and a sensor gives the shank, each elbow in plane and each wrist neutral
    where it answers the upper arm or the hand and a sensor gives the forearm (``knees_as_hinges``,
    ``elbows_in_plane``, ``neutral_wrists``; a model's ``hinge_joints``: False for a model in a rig's own frames, and
    for the mean-pose baseline, which takes nothing from the sensors but the root's and their own segments').
    ``measured`` ``(T, 21, 3, 3)``: segments of sensors the model does not read, NaN elsewhere, in place of the
    model's answer. Segments that no sensor and not the model covers (e.g. the arms of a lower-body model) take their
    parent's orientation."""
    T = R_root_out.shape[0]
    R = np.full((T, len(BODY_SEGMENTS), 3, 3), np.nan)
    R[:, sensor_index] = R_world_sensor_segment
    R[:, output_index] = np.einsum("tij,tsjk->tsik", R_world_sensor_segment[:, 0], R_root_out)
    answered = np.zeros((T, len(BODY_SEGMENTS)), bool)
    answered[:, output_index] = True
    sensed = np.zeros((T, len(BODY_SEGMENTS)), bool)
    sensed[:, sensor_index] = True
    if measured is not None:
        by_sensor = ~np.isnan(measured[:, :, 0, 0])  # per frame: frames of several sessions may measure others
        R = np.where(by_sensor[:, :, None, None], measured, R)
        answered &= ~by_sensor
        sensed |= by_sensor
    if hinges:
        R = knees_as_hinges(R, answered[:, [t for t, _ in KNEES]], sensed[:, [s for _, s in KNEES]])
        R = elbows_in_plane(R, answered[:, [u for u, _ in ELBOWS]], sensed[:, [f for _, f in ELBOWS]])
        R = neutral_wrists(R, answered[:, [h for h, _ in WRISTS]], sensed[:, [f for _, f in WRISTS]])
    for k in range(1, len(BODY_SEGMENTS)):
        empty = np.isnan(R[:, k, 0, 0])
        if empty.any():
            R[empty, k] = R[empty, PARENT_INDEX[k]]
    return R


def measured_segments(segments: Sequence[str], R_world_segment: np.ndarray) -> np.ndarray | None:
    """``whole_body``'s ``measured`` ``(T, 21, 3, 3)``: the orientations ``(T, E, 3, 3)`` of sensors on
    ``segments`` that a model does not read at their segments' places, NaN elsewhere; None where there are none."""
    if not len(segments):
        return None
    out = np.full((len(R_world_segment), len(BODY_SEGMENTS), 3, 3), np.nan)
    out[:, [BODY_SEGMENTS.index(s) for s in segments]] = R_world_segment
    return out


def covered_segments(model: PoseModel) -> list[str]:
    return [BODY_SEGMENTS[k] for k in sorted(model.sensor_index + model.output_index)]


def pose_answer(R_world: np.ndarray, body: Body) -> dict[str, np.ndarray]:
    """Per frame and segment ``q_world_segment``, ``q_parent_segment`` (w, x, y, z; the root's parent is the
    world) and the joint positions (segment origins) in metres, the pelvis at the origin."""
    parent = np.array([k if p < 0 else p for k, p in enumerate(PARENT_INDEX)])
    R_parent = np.einsum("tsji,tsjk->tsik", R_world[:, parent], R_world)
    R_parent[:, 0] = R_world[:, 0]
    return {
        "q_world_segment": quat_from_matrix(R_world),
        "q_parent_segment": quat_from_matrix(R_parent),
        "joint_positions_m": body.forward(R_world),
    }


class LivePose:
    """One live session's pose: calibration (declared, a still pose at the start, or handed over by the I2S
    assignment), the streaming model's state, and the last ``look_ahead`` frames' segment readings that its
    answers refer to.

    Frames are ``(m, N, 10)``: accelerometer xyz (m/s²), gyroscope xyz (rad/s), q_world_sensor wxyz, in the model's
    sensor order, then the sensors it does not read (``measured``, answered as measured), 60 Hz.
    """

    def __init__(
        self,
        model: PoseModel,
        method: str,
        q_segment_sensor: np.ndarray | None = None,
        still_frames: int = 120,
        still_pose: str = "npose",
        back_axis: tuple[float, float, float] = (0.0, 0.0, 1.0),
        height_m: float | None = None,
        translation: str = "none",
        velocity: VelocityModel | None = None,
        pelvis_heading: str = "alignment",
        measured: Sequence[str] = (),
        joint_angles: bool = False,
    ) -> None:
        if not model.spec.streaming:
            raise ValueError(f"{model.name} is an offline model; live sessions need a streaming one")
        if (translation == "learned") != (velocity is not None):
            raise ValueError("translation 'learned', and it alone, runs a velocity model")
        if velocity is not None:
            if velocity.spec.sensors != model.spec.sensors:
                raise ValueError(f"{velocity.name} reads {velocity.spec.sensors}, {model.name} {model.spec.sensors}")
            if velocity.spec.look_ahead_frames > model.spec.look_ahead_frames:
                raise ValueError(
                    f"{velocity.name} answers {velocity.spec.look_ahead_frames} frames late, after {model.name}'s "
                    f"pose ({model.spec.look_ahead_frames})"
                )
        if pelvis_heading == "legs" and not LEG_SEGMENTS & set(model.spec.sensors):
            raise ValueError(f"pelvis_heading 'legs': {model.name} reads no leg sensor ({model.spec.sensors})")
        self.model, self.method = model, method
        self.q_segment_sensor = q_segment_sensor  # (N, 4): the model's sensors, then the measured ones
        self.measure(measured)
        # pelvis_heading 'legs': the running sum of the legs' heading against the pelvis's (``legs_heading_sum``)
        # over the calibrated frames so far; each frame's pelvis is turned by its angle
        self.pelvis_heading = pelvis_heading
        self.heading_sum = 0j
        self.still_frames, self.still_pose, self.back_axis = still_frames, still_pose, back_axis
        self.body = model.body.scaled(height_m) if height_m else model.body
        self.state = model.new_state()
        self.still: list[np.ndarray] = []
        self.history = np.zeros((0, len(model.sensor_index), 3, 3))  # segment readings awaiting their answer
        self.pelvis_acc = np.zeros((0, 3))  # and the pelvis's free acceleration in those frames
        self.translation = translation
        # translation learned: the velocity network's state, and its answers (pelvis frame) awaiting their pose
        self.velocity = velocity
        self.tracker = self._new_tracker()
        self.velocity_state = velocity.new_state() if velocity is not None else None
        self.velocities = np.zeros((0, 3))
        self.velocity_inputs = 0  # frames fed to the velocity network
        self.inputs = 0  # frames fed to the network
        self.first_frame = 0  # stream frame index of the first frame fed to the network
        self.joint_angles = joint_angles  # pose messages carry the answered joints' angles

    def answered_joints(self) -> list[str]:
        """The joints whose two segments the model or a sensor answers (the measured ones included)."""
        return answered_joints(set(covered_segments(self.model)) | set(self.measured))

    @property
    def calibrated(self) -> bool:
        return self.q_segment_sensor is not None

    def recalibrate(self) -> None:
        """Still-pose sessions: hold the still pose again (a sensor slipped, or drifted about the vertical). The
        pose starts afresh after the new span, as at the start of the session: the network's state, the frames
        awaiting their look-ahead (never answered) and the translation, which restarts at the origin."""
        if self.method != "still_pose":
            raise ValueError(f"a session calibrated by {self.method!r} is not recalibrated by a still pose")
        self.q_segment_sensor, self.still = None, []
        self.state = self.model.new_state()
        self.history = self.history[:0]
        self.measured_history = self.measured_history[:0]
        self.pelvis_acc = self.pelvis_acc[:0]
        self.heading_sum = 0j
        self.inputs = 0
        self.tracker = self._new_tracker()
        if self.velocity is not None:
            self.velocity_state = self.velocity.new_state()
            self.velocities, self.velocity_inputs = self.velocities[:0], 0

    def realign(self, q_segment_sensor: dict[int, np.ndarray]) -> None:
        """Declared sessions: new alignments ``{sensor index (frame order): q_segment_sensor wxyz}`` from the next
        frame on (a sensor strapped on again, or aligned anew by ``/v1/imu/assign``). Unlike a still pose nothing
        restarts: the network keeps its state, the frames awaiting their look-ahead are answered, the translation
        goes on; the pelvis's heading from the legs is averaged anew where the pelvis or a leg sensor is re-aligned."""
        if self.method != "declared":
            raise ValueError(f"a session calibrated by {self.method!r} does not take declared alignments")
        q = self.q_segment_sensor.copy()
        for k, quat in q_segment_sensor.items():
            q[k] = canonical_quat(np.asarray(quat, dtype=np.float64))
        self.q_segment_sensor = q
        if {self.segments[k] for k in q_segment_sensor} & (LEG_SEGMENTS | {"Pelvis"}) & set(self.model.spec.sensors):
            self.heading_sum = 0j

    def _new_tracker(self) -> RootTracker | None:
        """The translation's rule from the body's first answered frame on (None: no translation)."""
        if self.translation == "none":
            return None
        tracker = RootTracker(feet_of(self.body), MODEL_RATE_HZ)
        if self.velocity is not None:
            tracker.learned_share = self.velocity.spec.learned_share
        return tracker

    @property
    def segments(self) -> list[str]:
        """The segments of the session's sensors in frame order: the model's, then the measured ones."""
        return [*self.model.spec.sensors, *self.measured]

    def measure(self, segments: Sequence[str]) -> None:
        """Sensors on ``segments`` that the model does not read, after its own in every frame: their segments are
        answered as measured."""
        overlap = [s for s in segments if s in self.model.spec.sensors]
        if overlap:
            raise ValueError(f"{self.model.name} reads {overlap} itself")
        self.measured = list(segments)
        self.measured_history = np.zeros((0, len(self.measured), 3, 3))  # awaiting their answer, as ``history``

    @property
    def cost_key(self) -> str:
        """What the session runs, as the streams' admission counts its cost per frame: the pose model, and the
        velocity model beside it where the translation is learned."""
        return cost_key(self.model, self.velocity)

    def process(self, frames: np.ndarray, first_frame: int) -> list[dict]:
        """Frames ``(m, N, 10)`` from stream frame ``first_frame`` on → ``calibration`` and ``pose`` messages."""
        return process_live([(self, frames, first_frame)])[0]

    def calibrate(self, frames: np.ndarray, first_frame: int) -> tuple[list[dict], np.ndarray, int]:
        """Calibration messages, and the frames (from which stream frame) that are ready for the network."""
        if self.calibrated:
            return [], frames, first_frame
        if self.method != "still_pose":
            return [], frames[:0], first_frame  # waiting for the assignment to hand over the alignments
        message, frames, first_frame = self._collect_still(frames, first_frame)
        messages = [message] if message is not None else []
        return messages, (frames if self.calibrated else frames[:0]), first_frame

    def _collect_still(self, frames: np.ndarray, first_frame: int) -> tuple[dict | None, np.ndarray, int]:
        """Collect the still span; a message once it is judged, and the frames after it."""
        if not self.still:
            self.still_first = first_frame
        self.still.append(frames)
        span = np.concatenate(self.still)
        if len(span) < self.still_frames:
            return None, frames[:0], first_frame
        rest, rest_first = span[self.still_frames :], self.still_first + self.still_frames
        span = span[: self.still_frames]
        self.still = []
        ok, why = is_still(span[:, :, 3:6], span[:, :, :3], self.segments)
        if not ok:
            detail = f"frames {self.still_first}-{rest_first} are not still: {why}; hold the pose still"
            return {"type": "calibration", "status": "waiting", "detail": detail}, rest[:0], rest_first
        try:
            q = still_pose_calibration(span[:, :, 6:10], self.segments, self.still_pose, 0, self.back_axis)
        except CalibrationError as exc:
            return {"type": "calibration", "status": "waiting", "detail": str(exc)}, rest[:0], rest_first
        self.q_segment_sensor = q
        message = {
            "type": "calibration",
            "status": "calibrated",
            "method": "still_pose",
            "frames": [self.still_first, rest_first],
            "q_segment_sensor": {s: np.round(q[k], 6) for k, s in enumerate(self.segments)},
        }
        return message, rest, rest_first


def process_live(jobs: list[tuple[LivePose, np.ndarray, int]]) -> list[list[dict]]:
    """Several live sessions' new frames ``(session, frames (m, N, 10), first stream frame)`` of one model at once:
    each session's messages. The calibrated frames of all sessions go through the network together (one call per
    frame count, ``PoseModel.step_many``) and through the per-frame geometry as one array, so a busy service pays
    numpy's and onnxruntime's per-call costs once per batch instead of once per session and packet."""
    messages: list[list[dict]] = []
    ready: list[tuple[int, LivePose, np.ndarray, int]] = []
    for k, (live, frames, first_frame) in enumerate(jobs):
        calibration, frames, first_frame = live.calibrate(frames, first_frame)
        messages.append(calibration)
        if len(frames):
            ready.append((k, live, frames, first_frame))
    if ready:
        answers = _step_live([r[1] for r in ready], [r[2] for r in ready], [r[3] for r in ready])
        for (k, *_), answer in zip(ready, answers, strict=True):
            if answer is not None:
                messages[k].append(answer)
    return messages


def _step_live(lives: list[LivePose], frames: list[np.ndarray], first_frames: list[int]) -> list[dict | None]:
    """Calibrated frames of sessions of one model → each session's ``pose`` message (None: no frame answered yet)."""
    model = lives[0].model
    n_in = len(model.spec.sensors)
    counts = [len(f) for f in frames]
    bounds = np.cumsum([0, *counts])
    joined = np.concatenate([f[:, :n_in] for f in frames])
    q_seg = np.repeat(np.stack([live.q_segment_sensor[:n_in] for live in lives]), counts, axis=0)
    R_w_seg, a_w = segment_readings(joined[:, :, 6:10], joined[:, :, :3], q_seg)
    _turn_pelvises(lives, R_w_seg, bounds)
    _measure(lives, frames)
    features = pose_features(R_w_seg, a_w)
    per_session = [features[bounds[i] : bounds[i + 1]] for i in range(len(lives))]
    outs, states = model.step_many(per_session, [live.state for live in lives])
    _step_velocities(lives, per_session)
    L = model.spec.look_ahead_frames
    answered: list[tuple[int, int, int]] = []  # (session, first network frame answered, frames answered)
    R_out, R_sensors, offsets, measured = [], [], [], []
    # (index into answered, tracker, pelvis free acc, learned velocity in the world or None)
    tracked: list[tuple[int, RootTracker, np.ndarray, np.ndarray | None]] = []
    for i, live in enumerate(lives):
        live.state = states[i]
        if live.inputs == 0:
            live.first_frame = first_frames[i]
        live.history = np.concatenate([live.history, R_w_seg[bounds[i] : bounds[i + 1]]])
        if live.tracker is not None:
            live.pelvis_acc = np.concatenate([live.pelvis_acc, a_w[bounds[i] : bounds[i + 1], 0]])
        answered_from = max(0, live.inputs - L)
        live.inputs += counts[i]
        n = max(0, live.inputs - L) - answered_from
        if n == 0:
            continue
        answered.append((i, answered_from, n))
        R_out.append(outs[i][len(outs[i]) - n :])
        R_sensors.append(live.history[:n])
        measured.append(measured_segments(live.measured, live.measured_history[:n]))
        live.measured_history = live.measured_history[n:]
        if live.tracker is not None:
            learned = None
            if live.velocity is not None:  # the pelvis velocity of each answered frame, turned into the world
                learned = world_velocity(live.history[:n, 0], live.velocities[:n])
                live.velocities = live.velocities[n:]
            tracked.append((len(answered) - 1, live.tracker, live.pelvis_acc[:n], learned))
            live.pelvis_acc = live.pelvis_acc[n:]
        live.history = live.history[n:]
        offsets.append(np.broadcast_to(live.body.offsets_m, (n, *live.body.offsets_m.shape)))
    results: list[dict | None] = [None] * len(lives)
    if not answered:
        return results
    measured_all = None  # per answered frame, the segments of sensors beyond the model's (NaN: none)
    if any(m is not None for m in measured):
        measured_all = np.concatenate(
            [
                np.full((n, len(BODY_SEGMENTS), 3, 3), np.nan) if m is None else m
                for (_, _, n), m in zip(answered, measured, strict=True)
            ]
        )
    R_world = whole_body(
        np.concatenate(R_sensors),
        np.concatenate(R_out),
        model.sensor_index,
        model.output_index,
        measured_all,
        hinges=model.hinge_joints,
    )
    q_world = np.round(quat_from_matrix(R_world), 5)
    exact = segment_origins(R_world, np.concatenate(offsets))
    positions = np.round(exact, 4)
    rows = np.cumsum([0, *(n for _, _, n in answered)])
    roots: dict[int, np.ndarray] = {}
    if tracked:
        moved = advance_bodies(
            [tracker for _, tracker, _, _ in tracked],
            [exact[rows[a] : rows[a + 1]] for a, _, _, _ in tracked],
            [acc for _, _, acc, _ in tracked],
            [learned for _, _, _, learned in tracked],
        )
        roots = {a: np.round(p, 4) for (a, *_), (p, _) in zip(tracked, moved, strict=True)}
    for a, (i, answered_from, n) in enumerate(answered):
        row = rows[a]
        results[i] = {
            "type": "pose",
            "first_frame": lives[i].first_frame + answered_from,
            "frames": n,
            "q_world_segment": np.ascontiguousarray(q_world[row : row + n]),  # orjson serialises C order only
            "joint_positions_m": np.ascontiguousarray(positions[row : row + n]),
        }
        if a in roots:
            results[i]["root_position_m"] = roots[a]
        if lives[i].joint_angles:
            joints = lives[i].answered_joints()
            angles = np.round(joint_angles_deg(R_world[row : row + n], joints), 2)
            results[i]["joint_angles_deg"] = {j: np.ascontiguousarray(angles[:, k]) for k, j in enumerate(joints)}
    return results


def _turn_pelvises(lives: list[LivePose], R_w_seg: np.ndarray, bounds: np.ndarray) -> None:
    """The pelvis of each session with ``pelvis_heading`` legs turned in place, frame by frame, to the legs' mean
    heading over every frame of the session so far (``service.core.calibration.legs_heading_sum``; a stream's first
    frames take the estimate of the few frames before them, which settles within a stride); all sessions' headings
    and turns computed together."""
    legs = [i for i, live in enumerate(lives) if live.pelvis_heading == "legs"]
    if not legs:
        return
    rows = np.concatenate([np.arange(bounds[i], bounds[i + 1]) for i in legs])
    h = legs_heading_sum(R_w_seg[rows], lives[0].model.spec.sensors)
    angles, start = np.empty(len(rows)), 0
    for i in legs:
        live, n = lives[i], bounds[i + 1] - bounds[i]
        running = live.heading_sum + np.cumsum(h[start : start + n])
        live.heading_sum = complex(running[-1])
        angles[start : start + n] = np.angle(running)
        start += n
    R_w_seg[rows, 0] = turn_about_z(R_w_seg[rows, 0], angles)


def _measure(lives: list[LivePose], frames: list[np.ndarray]) -> None:
    """Each session's sensors beyond the model's (``LivePose.measured``): their segments' orientations queued
    beside ``history``, computed in one call per number of such sensors."""
    n_in = len(lives[0].model.spec.sensors)
    by_count: dict[int, list[int]] = {}
    for i, live in enumerate(lives):
        if live.measured:
            by_count.setdefault(len(live.measured), []).append(i)
    for members in by_count.values():
        f = np.concatenate([frames[i][:, n_in:] for i in members])
        q = np.concatenate([np.repeat(lives[i].q_segment_sensor[None, n_in:], len(frames[i]), axis=0) for i in members])
        R, _ = segment_readings(f[:, :, 6:10], f[:, :, :3], q)
        start = 0
        for i in members:
            live, n = lives[i], len(frames[i])
            live.measured_history = np.concatenate([live.measured_history, R[start : start + n]])
            start += n


def _step_velocities(lives: list[LivePose], features: list[np.ndarray]) -> None:
    """The velocity networks of the sessions whose translation is learned, one call per network and frame count:
    each session's velocities (pelvis frame) queued for the frames its pose answers next. A network ``L`` frames
    late answers a stream's first ``L`` inputs for frames before its start; those are dropped."""
    by_network: dict[str, list[int]] = {}
    for i, live in enumerate(lives):
        if live.velocity is not None:
            by_network.setdefault(live.velocity.name, []).append(i)
    for members in by_network.values():
        network = lives[members[0]].velocity
        outs, states = network.step_many([features[i] for i in members], [lives[i].velocity_state for i in members])
        late = network.spec.look_ahead_frames
        for i, v, state in zip(members, outs, states, strict=True):
            live = lives[i]
            skip = max(0, late - live.velocity_inputs)
            live.velocity_state, live.velocity_inputs = state, live.velocity_inputs + len(v)
            live.velocities = np.concatenate([live.velocities, v[skip:].astype(np.float64)])
