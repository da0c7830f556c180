"""Pose experiment configuration (one YAML file per model in ``training/configs/pose_*.yaml``)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from service.core.body import BODY_SEGMENTS
from training.config import Strict, TrackingConfig, read_yaml

# Zheng et al. 2021 §7.2
SIX_SENSORS = ["Pelvis", "Head", "LeftForeArm", "RightForeArm", "LeftLowerLeg", "RightLowerLeg"]


class PoseSelectionConfig(Strict):
    """Zheng et al. 2021 §5 (``training/pose/selection.py``): the training clips narrowed to what resembles a
    reference set of one scenario, which is then trained on with them."""

    # the reference D_ref: training clips of these activities (and of these sources; None: every source)
    reference_activities: list[str] = Field(min_length=1)
    reference_sources: list[str] | None = None
    unit_s: float = Field(0.5, gt=0.0)  # §5.2: units of 50 frames, 0.5 s
    eta0: float = Field(0.8, gt=0.0, le=1.0)  # §5.2, eq. 5
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0)  # α, β, γ of eq. 4 (the paper gives none)
    # step 2 (§5.3, eq. 12-13) after step 1; off: train on step 1's similar data D_B (docs/pose.md, Comparisons)
    optimise: bool = True


class PoseOwnDataConfig(Strict):
    """A user's own motion capture beside (or instead of) the data directory's (``training.pose.pipeline.own_clips``):
    BVH files (plain or .gz) in one folder per person, ``<path>/<person>/…/*.bvh``; a file's activity is the name
    of the folder it lies in, where that is below the person's. A person's sessions can be split by folders too
    (``<path>/p01_monday``, ``<path>/p01_friday``): the split is by these first-level folders."""

    path: str
    # a skeleton none of the known families (CMU, iClone, Bandai-Namco) fits needs one (docs/pose.md)
    mapping: str | None = None
    # first-level folders whose clips choose the epoch and the registry's champion instead of the data directory's
    # validation subjects (none: the data directory's choose), and folders held out and reported apart from its
    # held-out subjects; every other folder trains
    val_people: list[str] = Field(default_factory=list)
    test_people: list[str] = Field(default_factory=list)
    # share of the drawn training sequences from these clips (the rest from the data directory's, as configured);
    # 1.0: these clips only
    share: float = Field(0.5, gt=0.0, le=1.0)


class PoseDataConfig(Strict):
    # Held-out subjects (never trained on, reported as the test set) and validation subjects (early stopping and
    # every choice between variants). Splits are by subject; Bandai-Namco names no actors and stays in training.
    test_subjects: list[str] = Field(default_factory=lambda: ["cmu_05", "cmu_06", "cmu_07"])
    val_subjects: list[str] = Field(default_factory=lambda: ["cmu_02", "cmu_03"])
    # Whole clips of pools without subject ids held out as test: li2018's runs (the only CMU running here).
    test_activities_of_unlabelled: dict[str, list[str]] = Field(default_factory=lambda: {"cmu_li2018": ["run"]})
    sources: list[str] | None = None  # None: every mocap source of the data directory
    # Frames per activity beyond which an activity's clips are drawn less often (Bandai-Namco waves and raises a
    # hand for 2.2 h of its 3.9 h): a simple balance; Zheng et al. 2021's selection for one scenario is `selection`.
    activity_cap_frames: int = 72_000
    # Share of the drawn training sequences from Bandai-Namco (None: by frames, about 97 %). Its clips are three
    # actors; the CMU training clips are many people, which is what held-out people need.
    bandai_share: float | None = Field(None, ge=0.0, le=1.0)
    selection: PoseSelectionConfig | None = None  # None: every training clip
    # How each limb segment is turned about its long axis: as its rig's frames put it ("rig"), or so that the
    # elbow's and knee's hinge axes lie along y ("hinge": training.pose.data.hinge_twisted; the same rule for
    # every rig, where the rigs' own frames differ by up to 42°)
    limb_twist: Literal["rig", "hinge"] = "rig"
    # How the upper trunk's frames (T8, shoulders, neck, head) are read: from each rig's spine and neck joints
    # ("spine"), or from the hip and shoulder joint centres, which the rigs place alike ("thorax":
    # service.core.body; the rigs' own spine joints read the same trial up to 18° apart)
    trunk_axes: Literal["spine", "thorax"] = "spine"
    # Zheng et al. 2021 §7's protocol beside ours: this share of the training clips (other takes of the same people
    # and activities, ``training.pose.data.seen_split``) is kept out of training and scored as "seen people" (their
    # test set is 20,000 frames of their own four people's walking, running and basketball); 0: off
    seen_share: float = Field(0.0, ge=0.0, le=0.5)
    # the user's own motion capture (``PoseOwnDataConfig``); None: the data directory's clips only
    own: PoseOwnDataConfig | None = None


class PoseModelConfig(Strict):
    kind: Literal["bilstm", "lstm", "ffn"] = "bilstm"
    representation: Literal["6d", "axis_angle"] = "6d"
    hidden: int = 256
    layers: int = 2
    input_dropout: float = 0.2  # Zheng et al. 2021 §4.2
    look_ahead: int = Field(0, ge=0, le=30)  # lstm: frames of future it sees (streaming: 5)
    # each output segment answered relative to a sensed segment next to it (``training.pose.models.anchor_sensors``:
    # a thigh from its shank, a hand from its forearm) instead of the pelvis (ours); not for look-ahead models
    anchored: bool = False


class PoseTrainConfig(Strict):
    sequence_frames: int = 300  # Zheng et al. 2021 §4.2
    context_frames: int = 75  # offline inference keeps this much past and future around each chunk's answers
    batch_size: int = 32
    sequences_per_epoch: int = 1024
    lr: float = 1e-3
    # "cosine": the rate falls from lr to lr * lr_floor over max_epochs (half a cosine, per epoch), so the last
    # epochs settle instead of wandering about a plateau at the full rate
    lr_schedule: Literal["constant", "cosine"] = "constant"
    lr_floor: float = Field(0.05, gt=0.0, le=1.0)
    max_epochs: int = 30
    patience: int = 6
    time_budget_s: float = 1800.0
    threads: int = 2
    acc_method: Literal["finite_difference", "butterworth"] = "finite_difference"
    # Share of the drawn training sequences performed by the mirror-image body (``data.mirrored``; our addition)
    mirror: float = Field(0.0, ge=0.0, le=1.0)
    # Each drawn training sequence played faster or slower by a factor uniform in this range (the motion resampled;
    # cadence, angular rates and accelerations change with it: the I2S simulation's most useful augmentation,
    # Zimmermann et al. 2018's people and ours walk at other speeds than the mocap actors), and its body scaled by a
    # factor uniform in ``size`` (the segment positions, so the accelerations; orientations and targets unchanged).
    # (1, 1): no draw, as before (our addition)
    speed: tuple[float, float] = (1.0, 1.0)
    size: tuple[float, float] = (1.0, 1.0)
    # Weight (1/m²) of a joint-position term beside the rotation loss: the mean squared distance of the segment
    # origins after forward kinematics with each sequence's own bones, root-relative (TransPose and PIP supervise
    # joint positions; ours is one term on the same network). 0: rotations only (Zheng et al. 2021).
    position_loss: float = Field(0.0, ge=0.0)
    # Assemble instead of training: the mean of these finished runs' networks (MLflow run ids of this recipe with
    # other seeds; ``training.pose.models.PoseEnsemble``, our addition), offline models only
    ensemble_of: list[str] | None = None
    # and each of them also run on the mirror image of the input, its answer mirrored back (our addition; the
    # sensors and outputs must come in left/right pairs); with it one run is enough
    ensemble_mirror: bool = False
    # Start from a shipped single-network file of this recipe (onnx_models/<name>/<version>: its weights and its
    # feature standardisation; ``training.pose.warmstart``) instead of at random: fine-tuning, e.g. on ``data.own``.
    # Its validation figure is epoch 0's, so a run that never beats it returns it unchanged.
    init_from_onnx: str | None = None

    @model_validator(mode="after")
    def _ranges(self) -> PoseTrainConfig:
        for name, (lo, hi), (least, most) in (("speed", self.speed, (0.5, 2.0)), ("size", self.size, (0.5, 1.5))):
            if not least <= lo <= hi <= most:
                raise ValueError(
                    f"train.{name}: expected [low, high] with {least} <= low <= high <= {most}, got {[lo, hi]}"
                )
        return self


class PoseConfig(Strict):
    name: str
    seed: int = 0
    sensors: list[str] = Field(default_factory=lambda: list(SIX_SENSORS))
    output_segments: list[str] | None = None  # None: every segment without a sensor
    data: PoseDataConfig = Field(default_factory=PoseDataConfig)
    model: PoseModelConfig = Field(default_factory=PoseModelConfig)
    train: PoseTrainConfig = Field(default_factory=PoseTrainConfig)
    tracking: TrackingConfig = Field(default_factory=lambda: TrackingConfig(experiment="pose"))

    @model_validator(mode="after")
    def _segments(self) -> PoseConfig:
        unknown = sorted(set(self.sensors + (self.output_segments or [])) - set(BODY_SEGMENTS))
        if unknown or self.sensors[0] != "Pelvis":
            raise ValueError(f"sensors start with Pelvis; segments are {list(BODY_SEGMENTS)}; unknown {unknown}")
        if self.model.look_ahead and self.model.kind != "lstm":
            raise ValueError("look_ahead is for the unidirectional lstm")
        if self.model.anchored and self.model.look_ahead:
            raise ValueError("model.anchored needs the input frame of each answer: not with look_ahead")
        fewest = 1 if self.train.ensemble_mirror else 2
        if self.train.ensemble_of is not None and (len(self.train.ensemble_of) < fewest or self.model.kind != "bilstm"):
            raise ValueError(
                "train.ensemble_of assembles two or more offline (bilstm) networks (one with train.ensemble_mirror); "
                f"got {len(self.train.ensemble_of)} of kind {self.model.kind}"
            )
        if self.train.init_from_onnx and self.train.ensemble_of:
            raise ValueError("train.init_from_onnx starts one network's training; train.ensemble_of trains none")
        own = self.data.own
        if own and set(own.val_people) & set(own.test_people):
            raise ValueError(f"data.own: {sorted(set(own.val_people) & set(own.test_people))} both validate and test")
        if own and own.share == 1.0 and self.data.seen_share:
            raise ValueError(
                "data.seen_share holds back the data directory's training clips; data.own.share 1.0 trains on none"
            )
        if self.train.ensemble_mirror and self.train.ensemble_of is None:
            raise ValueError("train.ensemble_mirror mirrors the networks of train.ensemble_of; name them")
        if self.train.sequence_frames <= 2 * self.train.context_frames:
            raise ValueError(
                f"train.sequence_frames ({self.train.sequence_frames}) must exceed twice train.context_frames "
                f"({self.train.context_frames})"
            )
        return self

    @property
    def outputs(self) -> list[str]:
        return self.output_segments or [s for s in BODY_SEGMENTS if s not in self.sensors]

    @property
    def registered_model(self) -> str:
        return self.tracking.registered_model or self.name


def load_pose_config(path: str | Path, overrides: list[str] | None = None) -> PoseConfig:
    return PoseConfig.model_validate(read_yaml(path, overrides))


def is_streaming(cfg: PoseConfig) -> bool:
    """Served as a live stream (the unidirectional LSTM with its look-ahead); every other kind is served offline,
    in chunks (``served_chunks``)."""
    return cfg.model.kind == "lstm"


def served_chunks(cfg: PoseConfig) -> tuple[int, int] | None:
    """(window, context) frames of the chunks an offline model is served in (its manifest's ``window_frames`` and
    ``context_frames``; ``service.inference.pose.run_chunked``); None for a streaming model."""
    return None if is_streaming(cfg) else (cfg.train.sequence_frames, cfg.train.context_frames)


class PoseVelocityConfig(Strict):
    """A learned pelvis velocity for a shipped pose model's sensors (``training/pose/velocity.py``): its data split
    and sensors are ``pose_config``'s; the share it gets on the ground is chosen with ``pose_model``'s answers on
    the validation subjects."""

    name: str
    seed: int = 0
    pose_config: str
    pose_model: str
    hidden: int = 256
    layers: int = 2
    look_ahead: int = Field(5, ge=0, le=30)  # TransPose 2021's online mode: 5 frames, 83 ms at 60 Hz
    max_epochs: int = 16
    sequences_per_epoch: int = 1024
    lr: float = 1e-3
    patience: int = 6
    shares: list[float] = Field(default_factory=lambda: [0.25, 0.5, 0.75, 1.0])
    tracking: TrackingConfig = Field(default_factory=lambda: TrackingConfig(experiment="pose"))


def load_velocity_config(path: str | Path, overrides: list[str] | None = None) -> PoseVelocityConfig:
    return PoseVelocityConfig.model_validate(read_yaml(path, overrides))
