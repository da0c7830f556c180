"""I2S experiment configuration: one YAML file per experiment, validated into ``ExperimentConfig``."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from service.core.segments import SEGMENTS
from training.config import Strict, TrackingConfig, read_yaml
from training.i2s.data.windows import Augmentation

_Strict = Strict  # the I2S sections below predate the common name


class DataConfig(_Strict):
    activities: list[str] = Field(default_factory=lambda: ["walk"])
    test_subjects: list[str] = Field(default_factory=list)  # LOSO: subject groups held out for testing
    # the catalogue sources whose clips are simulated (index.csv's `source`); None: every source that has clips of
    # the activities. A model trained on Bandai-Namco's clips carries their CC BY-NC 4.0 licence (its manifest).
    sources: list[str] | None = None
    val_fraction: float = 0.05  # Zimmermann et al. 2018 §3.3: 95 % / 5 % training / validation split (by clip)
    # Real recordings mixed into training (Zimmermann et al. 2018 §4.3, assignment only); never evaluated on.
    real_train_recordings: list[str] = Field(default_factory=list)
    real_fraction: float = Field(0.0, ge=0.0, lt=1.0)  # share of each batch drawn from them
    # the real recordings a run's evaluation scores (None: every one it did not train on); a short list makes a
    # quick job quick, and its figures are then only those recordings'
    real_eval_recordings: list[str] | None = None
    # the last part of every real training recording (in time) is kept for validation: early stopping and the
    # warm start's epoch 0 are then judged on real windows too, not on simulated ones alone (0: train on all)
    real_val_fraction: float = Field(0.2, ge=0.0, lt=1.0)
    # the real windows' share of the validation loss that selects the epoch; None weighs by window count, where
    # the 4,096 simulated windows outweigh a few hundred real ones and a fine-tune that gains on real data but
    # grows less sure on simulated data returns its warm start unchanged
    real_val_weight: float | None = Field(None, gt=0.0, lt=1.0)
    # the share of drawn real training windows read as if worn by the mirror-image body (``mirrored_readings``):
    # the other side's segment, so a group's one-sided habits (a paretic leg, a braced knee) cannot teach the side
    real_mirror: float = Field(0.0, ge=0.0, le=1.0)
    # turn every drawn real training window by a random rotation, as if its sensor were strapped on another way
    # (uniform over rotations; accelerometer and gyroscope alike): the real gaits in every mounting. Only where a
    # teacher answers for the turned window (an alignment network's label would turn with it; train.distill_from)
    real_rotation: bool = False
    # how real windows are drawn (training and validation alike): "window" uniformly over all of them, where
    # MovingReality's eight long treadmill recordings are 85 % of the windows; "source" each source equally often,
    # within it each person equally often (``source_balanced_weights``)
    real_balance: Literal["window", "source"] = "window"
    # with real_balance "source": the share of real draws that follow it, the rest drawn by window
    real_balance_share: float = Field(1.0, ge=0.0, le=1.0)
    sample_rate_hz: float = 60.0
    cutoff_hz: float = 10.0
    filter_order: int = 8

    @model_validator(mode="after")
    def _scores_only_held_out_recordings(self) -> DataConfig:
        trained_on = sorted(set(self.real_eval_recordings or []) & set(self.real_train_recordings))
        if trained_on:
            raise ValueError(f"data.real_eval_recordings names recordings this run trains on: {trained_on}")
        return self


class TrainConfig(_Strict):
    batch_size: int = 256  # Table A1
    lr: float = 1e-3  # Table A1, Adam
    weight_decay: float = 1e-4  # Table A1, L2 factor
    keep_prob: float = 0.8  # Table A1, input dropout keep probability
    hidden: int = 128
    channels: int = 64
    kernel: int = 16
    # rotate each window into its own canonical frame first (training.i2s.models.CanonicalFrame; not in the paper)
    canonical_frame: bool = False
    # assignment: average the class probabilities over the window turned by 0/90/180/270° about the sensor's z
    # axis (training.i2s.models.AssignmentNet; not in the paper): the same weights, 4× the compute
    quarter_turns: bool = False
    # assignment: also average over the window turned by 360°/n about its mean specific force (the limb's long
    # axis, eq. 8's θ₂; training.i2s.models.AssignmentNet; not in the paper): n × the compute; 1 = off
    gravity_turns: int = Field(default=1, ge=1)
    # assignment: the classes that take their probability from the turns about gravity (None: all); the others use
    # the window's own quarter turns (training.i2s.models.AssignmentNet; the legs, whose long axis is near gravity)
    gravity_turn_segments: list[str] | None = None
    # alignment: turn these segments' predicted frames about their z onto the axes the window's motion defines
    # (training.i2s.models.FunctionalAxes; not in the paper): the flexion axis (y) of the legs and feet, the
    # direction of travel (x) of the pelvis
    functional_axes: list[str] | None = None
    # alignment: with Pelvis among the functional axes, turn the pelvis by 180° about z where the walk's forward
    # acceleration lags its vertical one by at least this normalised contrast (training.i2s.models.FunctionalAxes:
    # walking's inverted pendulum says which way is forward); None = off
    pelvis_half_turn: float | None = Field(default=None, ge=0)
    # alignment: average the CNN features over runs of this many samples before the LSTM (not in the paper;
    # training.i2s.models.AlignmentNet): the LSTM takes 128 / rnn_stride steps; 1 = every sample, as the paper
    rnn_stride: int = Field(default=1, ge=1)
    # alignment loss: sign-invariant quaternion distance, or the paper's L2 on the stereographic projection
    alignment_loss: Literal["quaternion", "stereographic_l2"] = "quaternion"
    grad_clip_norm: float | None = None  # clip the global gradient norm (stabilises the LSTM)
    steps_per_epoch: int = 100  # windows are drawn fresh; an "epoch" is this many batches
    max_epochs: int = 20
    patience: int = 5  # early stopping on validation loss
    val_windows: int = 4096
    threads: int = 2
    # where the network trains: "cpu", or "cuda" on a GPU machine (training.cli fit); the exported graph is the same
    device: str = "cpu"
    # processes that simulate batches ahead of the optimiser (torch DataLoader); 0 draws them in the training
    # process, as every run before this option did. Each worker has its own seeded generator, so a run is
    # reproducible for a given worker count, but differs between counts.
    loader_workers: int = 0
    init_from_run: str | None = None  # MLflow run id whose checkpoint warm-starts training (pre-training)
    init_from_onnx: str | None = None  # or a shipped float32 model dir (onnx_models/<name>/<version>)
    # assignment: average the class probabilities of these shipped float32 models (onnx_models/<name>/<version>),
    # each with its own turn averages (training.i2s.models.AssignmentEnsemble; not in the paper); assembled, not
    # trained: needs max_epochs 0, and takes no init_from_* and no turn averages of its own
    ensemble_of: list[str] | None = None
    max_minutes: float | None = None  # wall-time budget; stops after the epoch that crosses it
    # distil this shipped float32 model of the same task (onnx_models/<name>/<version>) into the network trained
    # (Hinton et al. 2015; not in Zimmermann et al. 2018). Assignment (an ensemble stands for its members, each with
    # its turn averages): loss = (1 - distill_weight) × cross entropy + distill_weight × τ² × KL(teacher ‖ student),
    # both softened at τ = distill_temperature (training.i2s.train.distillation_loss). Alignment (the teacher's
    # network without its functional axes, which the student's export adds again): (1 - distill_weight) × the
    # quaternion distance to the label + distill_weight × the distance to the teacher's quaternion; real windows,
    # which carry no alignment label, learn the teacher's alone (training.i2s.train.alignment_distillation_loss)
    distill_from: str | None = None
    distill_weight: float = Field(default=0.9, ge=0.0, le=1.0)
    distill_temperature: float = Field(default=2.0, gt=0.0)
    # the activities whose simulated windows the teacher speaks for (None: every window; real windows always): the
    # others train on their labels alone, e.g. a gait-trained teacher on gait only
    distill_activities: list[str] | None = None
    # which weights a run returns: "best", those of the epoch with the lowest validation loss (the warm start counts
    # as epoch 0) with early stopping after ``patience`` epochs; "last", those of the final epoch, for a fixed budget
    # (max_epochs or max_minutes): to compare augmentations that the validation set, drawn without them, would
    # judge against (a warm start never sees them and so wins on it)
    keep: Literal["best", "last"] = "best"
    # exponential moving average of the weights (and batch-norm statistics) after every step, decay per step;
    # validation, early stopping and the returned model use the average (None: the raw weights, as before)
    ema_decay: float | None = Field(default=None, ge=0.0, lt=1.0)

    @model_validator(mode="after")
    def _loss_fits_the_net(self) -> TrainConfig:
        if self.canonical_frame and self.alignment_loss == "stereographic_l2":
            raise ValueError(
                "alignment_loss stereographic_l2 regresses p in the sensor frame; it needs canonical_frame false"
            )
        return self

    @model_validator(mode="after")
    def _an_ensemble_is_assembled(self) -> TrainConfig:
        if self.ensemble_of is None:
            return self
        own = {
            "max_epochs": self.max_epochs != 0,
            "init_from_run": self.init_from_run is not None,
            "init_from_onnx": self.init_from_onnx is not None,
            "quarter_turns": self.quarter_turns,
            "gravity_turns": self.gravity_turns != 1,
            "canonical_frame": self.canonical_frame,
        }
        if len(self.ensemble_of) < 2 or any(own.values()):
            raise ValueError(
                "ensemble_of assembles two or more shipped models as they are: it needs max_epochs 0 and no "
                f"init_from_*, turn averages or canonical frame of its own; got {len(self.ensemble_of)} members "
                f"and {[k for k, v in own.items() if v]}"
            )
        return self

    @model_validator(mode="after")
    def _quarter_turns_need_an_invariant_task(self) -> TrainConfig:
        if self.quarter_turns and self.canonical_frame:
            raise ValueError("quarter_turns averages over sensor rotations the canonical frame already removes")
        if self.gravity_turns > 1 and self.canonical_frame:
            raise ValueError("gravity_turns averages over turns about gravity that the canonical frame already removes")
        if self.gravity_turn_segments is not None:
            unknown = sorted(set(self.gravity_turn_segments) - set(SEGMENTS))
            if unknown or not self.gravity_turn_segments or self.gravity_turns == 1:
                raise ValueError(
                    f"gravity_turn_segments needs gravity_turns > 1 and some of {list(SEGMENTS)}; "
                    f"got gravity_turns={self.gravity_turns}, unknown names {unknown}"
                )
        if self.functional_axes is not None:
            unknown = sorted(set(self.functional_axes) - set(SEGMENTS))
            if unknown or not self.functional_axes:
                raise ValueError(f"functional_axes must be some of {list(SEGMENTS)}; unknown names {unknown}")
        if self.pelvis_half_turn is not None and "Pelvis" not in (self.functional_axes or []):
            raise ValueError("pelvis_half_turn turns the pelvis of the functional axes: name Pelvis in functional_axes")
        return self


class ExperimentConfig(_Strict):
    name: str
    task: Literal["assignment", "alignment"]
    seed: int = 0
    data: DataConfig = Field(default_factory=DataConfig)
    augmentation: Augmentation = Field(default_factory=Augmentation)
    train: TrainConfig = Field(default_factory=TrainConfig)
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)

    @property
    def registered_model(self) -> str:
        return self.tracking.registered_model or self.name

    @model_validator(mode="after")
    def _a_teacher_teaches_a_network_that_trains(self) -> ExperimentConfig:
        taught = self.train.distill_activities
        if taught is not None and self.train.distill_from is None:
            raise ValueError("train.distill_activities names the windows a teacher speaks for; set train.distill_from")
        if taught is not None and (not taught or set(taught) - set(self.data.activities)):
            raise ValueError(
                f"train.distill_activities must be some of data.activities {self.data.activities}; got {taught}"
            )
        if self.train.distill_from is not None and self.train.ensemble_of:
            raise ValueError("train.distill_from teaches a network that trains; ensemble_of is assembled, not trained")
        if self.train.distill_from is not None and self.task == "alignment":
            t = self.train
            if t.alignment_loss == "stereographic_l2":
                raise ValueError("an alignment teacher teaches through the quaternion loss: alignment_loss quaternion")
            if (t.functional_axes or t.pelvis_half_turn is not None) and t.max_epochs > 0:
                raise ValueError(
                    "an alignment teacher answers without functional axes: train the student without them and wrap "
                    "it afterwards (train.max_epochs 0 with train.functional_axes)"
                )
        if self.train.distill_from is None and self.task == "alignment" and self.data.real_fraction > 0:
            raise ValueError(
                "real recordings carry no alignment labels: real windows in alignment training need a teacher "
                "(train.distill_from) to learn from"
            )
        if self.data.real_rotation and (
            self.train.distill_from is None or self.task != "alignment" or self.data.real_fraction == 0
        ):
            raise ValueError(
                "data.real_rotation turns real windows for a teacher to answer: it needs an alignment run with "
                "train.distill_from and data.real_fraction > 0"
            )
        if self.task == "alignment" and self.data.real_fraction > 0 and self.data.real_val_fraction > 0:
            raise ValueError(
                "the alignment's validation is scored on labels, which real windows lack: set data.real_val_fraction 0"
            )
        return self


def load_config(path: str | Path, overrides: list[str] | None = None) -> ExperimentConfig:
    """Read a YAML config; ``overrides`` are ``dotted.key=yaml_value`` strings (e.g. ``train.max_epochs=2``)."""
    return ExperimentConfig.model_validate(read_yaml(path, overrides))
