"""``manifest.json``: the train/serve contract beside each ``model.onnx`` (docs/conventions.md)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

MANIFEST_SCHEMA_VERSION = 1
# Key of the manifest inside a logged MLflow model's MLmodel metadata (models served from the registry).
MLMODEL_METADATA_KEY = "wearmocap_manifest"


class TensorSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    shape: list[int | str]  # "batch" for the dynamic dimension
    dtype: Literal["float32", "int64"]
    description: str = ""


class Evaluation(BaseModel):
    """One evaluation of the shipped ONNX file: what data, which metrics, and the command that made them."""

    model_config = ConfigDict(extra="forbid")
    name: str
    command: str
    data: str
    metrics: dict[str, float]


class PoseSpec(BaseModel):
    """What an ``imu_pose`` model needs from the service and gives back (Zheng et al. 2021 §4; docs/conventions.md).

    The input is ``(batch, frames, features)`` of ``service.core.calibration.pose_features`` for ``sensors`` in
    that order (the first is the root, the Pelvis); the output ``(batch, frames, segments, 3, 3)`` holds the
    root-relative orientations R_root_segment of ``output_segments``. A ``streaming`` model also takes and returns
    its LSTM state ``h``/``c`` of shape ``(layers, batch, hidden)`` and answers each frame ``look_ahead_frames``
    late; an offline model is run on ``window_frames`` chunks that keep ``context_frames`` either side.
    """

    model_config = ConfigDict(extra="forbid")
    sensors: list[str]
    output_segments: list[str]
    feature_version: str
    acc_scale_mps2: float
    representation: Literal["6d", "axis_angle"]
    architecture: str
    streaming: bool
    look_ahead_frames: int = Field(ge=0)
    window_frames: int = Field(ge=1)
    context_frames: int = Field(ge=0)
    state_layers: int = 0
    state_hidden: int = 0
    body: dict[str, list] = Field(description="default skeleton: segments and offsets_m (service.core.body.Body)")
    body_height_m: float


class VelocitySpec(BaseModel):
    """What an ``imu_pose_velocity`` model needs and gives (the fallback velocity of TransPose, Yi et al. 2021 §3.3;
    ``training.pose.velocity``). The input is the pose features (``service.core.calibration.pose_features``) of
    ``sensors`` in that order, with the LSTM state ``h``/``c`` of shape ``(layers, batch, hidden)``; the output
    ``(batch, frames, 3)`` the pelvis velocity in the pelvis frame (m/s), each frame ``look_ahead_frames`` late.
    ``service.core.translation`` moves the body with it, ``learned_share`` of it on the ground (the share chosen on
    the validation subjects with the pose model ``chosen_with``)."""

    model_config = ConfigDict(extra="forbid")
    sensors: list[str]
    feature_version: str
    acc_scale_mps2: float
    architecture: str
    look_ahead_frames: int = Field(ge=0)
    state_layers: int = Field(ge=1)
    state_hidden: int = Field(ge=1)
    learned_share: float = Field(ge=0.0, le=1.0)
    chosen_with: str


class ReadoutCheckSpec(BaseModel):
    """The read-out failure rule of a model's sensors (``service.core.flex.ReadoutCheck``): a reading off its
    channel's median over the first ``reference_s`` seconds by more than ``max_deviation`` of it has failed."""

    model_config = ConfigDict(extra="forbid")
    reference_s: float = Field(gt=0.0)
    max_deviation: float = Field(gt=0.0)


class FlexSpec(BaseModel):
    """What a ``flex_pose`` model needs and gives (Chen et al. 2024 §3.4): the input is ``(batch, window_samples,
    channels)`` raw readings, the newest last; the answer is the pose ``latency_samples`` before the newest one.
    The network sees the last ``steps`` samples after the dynamic calibration (if ``calibration``) has used the
    whole window; a stream keeps the last ``window_samples`` rows per session."""

    model_config = ConfigDict(extra="forbid")
    architecture: str
    calibration: bool
    median: bool
    steps: int
    latency_samples: int
    angle_convention: str
    simulated_sensor: str = ""  # the sensor model trained on, for simulated-data models
    readout_check: ReadoutCheckSpec | None = None  # refuse readings of a failed read-out (capacitive sleeves)
    # how the graph reads the raw readings before its min-max bounds: as they are ("minmax"), each channel over its
    # window's mean ("window_relative"), that over its window's standard deviation ("window_standardised"), or as log
    # resistance through the read-out named in the channels' units
    # ("log_resistance": another divider or amplifier needs another model); None: not stated (manifests before
    # 2026-12-05)
    input_norm: Literal["minmax", "window_relative", "window_standardised", "log_resistance"] | None = None


class SessionConfidenceSpec(BaseModel):
    """The probability that a session's whole joint assignment is right, from its sensors' calibrated probabilities
    (``service.core.assignment.ConfidenceModel.p_all_correct``): logistic coefficients over ``features`` and the
    probability the service commits at."""

    model_config = ConfigDict(extra="forbid")
    features: list[str]
    coef: list[float]
    intercept: float
    threshold: float = Field(gt=0.0, lt=1.0)


class ConfidenceSpec(BaseModel):
    """An ``i2s_assignment`` model's calibrated confidence of a session's joint assignment
    (``service.core.assignment.ConfidenceModel``): logistic coefficients over ``features`` per sensor, the probability
    the service commits at, and what it was fitted and scored on (``training.i2s.calibration``). With ``session``
    the service commits on the probability that every sensor is right instead of on each sensor's own."""

    model_config = ConfigDict(extra="forbid")
    features: list[str]
    coef: list[float]
    intercept: float
    threshold: float = Field(gt=0.0, lt=1.0)
    min_moving_windows: int = Field(ge=1)
    session: SessionConfidenceSpec | None = None
    # The weight of how the sensors swing together in the joint answers it was fitted on
    # (``service.core.assignment.SWING_WEIGHT``); 0: not weighed (calibrations before it). The service answers a
    # session as the calibration saw it answered.
    swing_weight: float = Field(0.0, ge=0.0)
    fitted_on: str
    metrics: dict[str, float] = Field(default_factory=dict)
    command: str = ""


class Manifest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    schema_version: int = MANIFEST_SCHEMA_VERSION
    name: str
    # i2s_*: Zimmermann et al. 2018. imu_pose (sparse IMUs, Zheng et al. 2021) and flex_pose (flex sensors, Chen et al.
    # 2024) are served by the generic pose routes from what the manifest declares: input channels, rate, window, value
    # range, joints.
    task: Literal["i2s_assignment", "i2s_alignment", "imu_pose", "imu_pose_velocity", "flex_pose"]
    version: str
    created_utc: str
    inputs: list[TensorSpec]
    outputs: list[TensorSpec]
    # joint_angles_deg: output (batch, joints, components) in degrees (flex_pose).
    output_kind: Literal[
        "probabilities",
        "logits",
        "quaternion_per_segment",
        "joint_angles_deg",
        "rotation_matrix_per_segment",
        "velocity_mps",
    ]
    sample_rate_hz: float
    window_samples: int
    hop_samples: int
    channels: list[str]
    units: dict[str, str]
    classes: list[str]
    joints: list[str] = Field(default_factory=list, description="pose models: output joints, in order")
    joint_components: list[str] = Field(
        default_factory=list, description="joint_angles_deg models: the angle names per joint, in order"
    )
    value_range: list[float] | None = Field(
        None, min_length=2, max_length=2, description="inclusive bounds of every input value, e.g. 12-bit counts"
    )
    quaternion_convention: str | None = None
    pose: PoseSpec | None = None
    velocity: VelocitySpec | None = None
    flex: FlexSpec | None = None
    confidence: ConfidenceSpec | None = None
    sha256: str
    training_data: dict[str, object] = Field(default_factory=dict)
    evaluations: list[Evaluation] = Field(default_factory=list)
    mlflow: dict[str, str] = Field(default_factory=dict)
    exporter: dict[str, str | bool | int | float | list[str]] = Field(default_factory=dict)
    golden: str = "golden.npz"
    parity_atol: float = 1e-4

    @model_validator(mode="after")
    def _pose_contract_is_consistent(self) -> Manifest:
        """A pose model's manifest must describe its tensors fully: the service builds inputs and labels
        outputs from it alone."""
        if self.task == "imu_pose":
            return self._imu_pose_contract()
        if self.task == "imu_pose_velocity":
            return self._velocity_contract()
        if self.task != "flex_pose":
            return self
        if self.output_kind != "joint_angles_deg":
            raise ValueError(f"a {self.task} model needs output_kind joint_angles_deg, got {self.output_kind}")
        expected_in = ["batch", self.window_samples, len(self.channels)]
        if len(self.inputs) != 1 or self.inputs[0].shape != expected_in:
            raise ValueError(f"a {self.task} model takes one input of shape {expected_in}")
        k = len(self.joint_components)
        expected_out = ["batch", len(self.joints), k]
        if len(self.outputs) != 1 or self.outputs[0].shape != expected_out or not self.joints or not k:
            raise ValueError(f"a {self.task} model gives one output of shape {expected_out} (joints × components)")
        if self.flex is None or not 0 <= self.flex.latency_samples < self.window_samples:
            raise ValueError(f"a {self.task} model needs a 'flex' section with 0 <= latency_samples < window_samples")
        return self

    def _imu_pose_contract(self) -> Manifest:
        from service.core.body import BODY_SEGMENTS
        from service.core.calibration import FEATURE_VERSION, features_per_frame

        p = self.pose
        if p is None or self.output_kind != "rotation_matrix_per_segment":
            raise ValueError("an imu_pose model needs a 'pose' section and output_kind rotation_matrix_per_segment")
        unknown = sorted(set(p.sensors + p.output_segments) - set(BODY_SEGMENTS))
        if unknown or not p.sensors or p.sensors[0] != "Pelvis" or set(p.sensors) & set(p.output_segments):
            raise ValueError(
                "imu_pose: sensors must start with Pelvis and not overlap output_segments, all of "
                f"{list(BODY_SEGMENTS)}; "
                f"unknown {unknown}"
            )
        if p.feature_version != FEATURE_VERSION:
            raise ValueError(f"imu_pose: features {p.feature_version!r}, this service computes {FEATURE_VERSION!r}")
        # A streaming graph takes a batch of live sessions (each its own state), or one at a time (batch 1)
        batch = self.inputs[0].shape[0] if p.streaming and self.inputs[0].shape[:1] in ([1], ["batch"]) else "batch"
        expected_in = [batch, "frames", features_per_frame(len(p.sensors))]
        if self.inputs[0].shape != expected_in:
            raise ValueError(f"an imu_pose model takes features of shape {expected_in}, got {self.inputs[0].shape}")
        expected_out = [batch, "frames", len(p.output_segments), 3, 3]
        if self.outputs[0].shape != expected_out:
            raise ValueError(f"an imu_pose model gives rotations of shape {expected_out}, got {self.outputs[0].shape}")
        if p.streaming and (len(self.inputs) != 3 or len(self.outputs) != 3 or not p.state_layers):
            raise ValueError("a streaming imu_pose model takes (features, h, c) and returns (rotations, h, c)")
        return self

    def _velocity_contract(self) -> Manifest:
        from service.core.body import BODY_SEGMENTS
        from service.core.calibration import ACC_SCALE_MPS2, FEATURE_VERSION, features_per_frame

        v = self.velocity
        if v is None or self.output_kind != "velocity_mps":
            raise ValueError("an imu_pose_velocity model needs a 'velocity' section and output_kind velocity_mps")
        if not v.sensors or v.sensors[0] != "Pelvis" or set(v.sensors) - set(BODY_SEGMENTS):
            raise ValueError(f"imu_pose_velocity: sensors start with Pelvis and are of {list(BODY_SEGMENTS)}")
        if v.feature_version != FEATURE_VERSION or v.acc_scale_mps2 != ACC_SCALE_MPS2 or self.sample_rate_hz != 60.0:
            raise ValueError(
                f"imu_pose_velocity: features {v.feature_version!r} / {v.acc_scale_mps2:g} m/s^2 at "
                f"{self.sample_rate_hz:g} Hz, this service computes {FEATURE_VERSION!r} / {ACC_SCALE_MPS2:g} m/s^2 "
                "at 60 Hz"
            )
        state = [v.state_layers, "batch", v.state_hidden]
        expected_in = [["batch", "frames", features_per_frame(len(v.sensors))], state, state]
        expected_out = [["batch", "frames", 3], state, state]
        if [t.shape for t in self.inputs] != expected_in or [t.shape for t in self.outputs] != expected_out:
            raise ValueError(
                f"an imu_pose_velocity model takes (features, h0, c0) of shapes {expected_in} and returns "
                f"(velocity, h, c) of shapes {expected_out}"
            )
        return self


def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read_manifest(path: Path) -> Manifest:
    return Manifest.model_validate_json(Path(path).read_text())


def with_evaluation(manifest: Manifest, evaluation: Evaluation, after: str | None = None) -> Manifest:
    """``manifest`` with ``evaluation`` in place of any evaluation of the same name (a figure scored again): first,
    or right after the evaluation named ``after`` where there is one (a figure beside the headline one)."""
    others = [e for e in manifest.evaluations if e.name != evaluation.name]
    at = next((i + 1 for i, e in enumerate(others) if e.name == after), 0) if after else 0
    return manifest.model_copy(update={"evaluations": [*others[:at], evaluation, *others[at:]]})


def write_manifest(manifest: Manifest, path: Path) -> None:
    Path(path).write_text(manifest.model_dump_json(indent=2) + "\n")
