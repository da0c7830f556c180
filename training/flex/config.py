"""Flex experiment configuration (one YAML file per model in ``training/configs/flex_*.yaml``)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from service.core.flex import FLEX_JOINTS, FLEX_SENSOR_JOINTS
from training.config import Strict, TrackingConfig, read_yaml

# Chen et al. 2024 Table 3's joints that the canonical body has (service.core.flex.FLEX_JOINTS).
TABLE3_JOINTS = list(FLEX_JOINTS)


class FlexDataConfig(Strict):
    # As for pose: held-out subjects (the test set) and validation subjects (early stopping and every choice);
    # Bandai-Namco names no actors and stays on the training side.
    test_subjects: list[str] = Field(default_factory=lambda: ["cmu_05", "cmu_06", "cmu_07"])
    val_subjects: list[str] = Field(default_factory=lambda: ["cmu_02", "cmu_03"])
    test_activities_of_unlabelled: dict[str, list[str]] = Field(default_factory=lambda: {"cmu_li2018": ["run"]})
    sources: list[str] | None = None
    suits_per_clip: int = Field(3, ge=1)  # simulated suits (sensor draws) per training clip, fixed per build
    activity_cap_frames: int = 24_000  # at 20 Hz; as pose's cap: Bandai's waves and hand raises drawn less often
    # Bandai-Namco's share of the drawn windows (None: by frames, 97 % of them Bandai-Namco's three actors)
    bandai_share: float | None = Field(None, ge=0.0, le=1.0)
    # also train on every training clip performed by the mirror-image body (``training.pose.data.mirrored``)
    mirror: bool = False
    # the limbs' turn about their long axes: each rig's ("rig") or from the elbow's and knee's hinge axes ("hinge",
    # as PoseDataConfig.limb_twist)
    limb_twist: Literal["rig", "hinge"] = "rig"
    # the upper trunk's frames: from each rig's spine joints ("spine") or the hip and shoulder joint centres
    # ("thorax", as PoseDataConfig.trunk_axes)
    trunk_axes: Literal["spine", "thorax"] = "spine"
    # Chen et al. 2024 §3.3's protocol beside ours: this share of the training clips (other takes of the same people
    # and activities, ``training.pose.data.seen_split``) is kept out of training and scored as "seen people" (their
    # test is 10 % of each recorded action of the same ten subjects); 0: off
    seen_share: float = Field(0.0, ge=0.0, le=0.5)


class FlexModelConfig(Strict):
    kind: Literal["bilstm", "transformer", "fcn", "tcn"] = "bilstm"
    calibration: bool = False  # C: Chen et al. 2024 eq. 2
    # how eq. 2's linear layer starts (the paper does not say): "default" PyTorch's random init; "baseline" every
    # output the mean of the pooled minima, so the module starts as a subtraction of the window's baseline
    calibration_init: Literal["default", "baseline"] = "default"
    median: bool = False  # M: Chen et al. 2024 §3.4.4
    window: int = 100  # calibrated sequence length (§4.2.4, Table 6)
    steps: int = 5  # input sequence length to the network (§4.2.4)
    min_kernel: int = 15  # §4.2.4's final choice (§3.4.2 says 25)
    avg_kernel: int = 10
    avg_padding: int = 8
    # minmax: the training set's per-channel bounds (§3.4.3). window_relative (ours, for real sleeves whose
    # read-outs differ tenfold between legs): each channel over its window's mean, minus one, then min-max;
    # window_standardised (ours, tried, not served): that over its window's standard deviation.
    # log_resistance (ours, for the simulated strips): the counts read back through eq. 1's nominal divider and
    # amplifier to log(R / R_i), then min-max; ageing multiplies the resistance, so there it is an offset, which
    # eq. 2's subtraction can take out (in counts the divider turns it into a change of level and of swing)
    input_norm: Literal["minmax", "window_relative", "window_standardised", "log_resistance"] = "minmax"
    # bilstm: Dense1, Dense2, the LSTM's hidden units per direction, Dense3, Dense4 (appendix B: 100, 512, 512,
    # 1024, 150)
    bilstm_sizes: tuple[int, int, int, int, int] = (100, 512, 512, 1024, 150)
    # ours, not in Chen et al. 2024: a linear map from the (calibrated) readings of each step added to the network's
    # output, so that readings beyond the trained range answer beyond it where the recurrent layer saturates
    linear_path: bool = False


class FlexTrainConfig(Strict):
    batch_size: int = 64  # §3.4.1
    lr: float = 1e-3
    lr_step_epochs: int = 10  # decays by 0.1 every 10 epochs (§3.4.1)
    windows_per_epoch: int = 12_800
    max_epochs: int = 40
    # §3.4.1 stops when the error fell by less than 0.1° over 10 epochs; our CPU budget stops earlier.
    min_improvement_deg: float = 0.1
    patience: int = 10
    time_budget_s: float = 300.0
    threads: int = 2
    grad_clip: float = 1.0
    # which epoch's weights the run keeps: the best on validation (ours), or the last (Chen et al. 2024 §3.4.1
    # trains until the error stops falling and says nothing of going back to an earlier epoch)
    keep: Literal["best", "last"] = "best"
    # each training window's channels swing about their window mean by a factor drawn per window and channel,
    # log-uniform in [1 / (1 + channel_gain), 1 + channel_gain] (ours, for sleeves whose channels modulate by
    # different amounts on another leg or person); 0: off
    channel_gain: float = Field(0.0, ge=0.0)
    # each training window bent further: its readings and its angles scaled about the window's least-flexed sample
    # by a factor per window, log-uniform in [1, 1 + deeper] (ours, for a knee that bends beyond what the trials
    # trained on hold, which a recurrent network does not extrapolate to; it assumes each channel moves in proportion
    # to the flexion over that stretch). Single-joint models only (the capacitive knee); 0: off
    deeper: float = Field(0.0, ge=0.0)
    # networks trained from the seeds seed, seed + 1, … and answering as their mean (``FlexEnsemble``; ours): each
    # trains as one network would (time_budget_s each), chooses its own epoch on the validation part, and costs its
    # share at run time
    members: int = Field(1, ge=1, le=8)


class _FlexRun(Strict):
    """What every flex experiment has: a name, the network (Chen et al. 2024 Table 5's variants) and training."""

    name: str
    seed: int = 0
    model: FlexModelConfig = Field(default_factory=FlexModelConfig)
    train: FlexTrainConfig = Field(default_factory=FlexTrainConfig)
    tracking: TrackingConfig = Field(default_factory=lambda: TrackingConfig(experiment="flex"))

    @model_validator(mode="after")
    def _steps(self) -> _FlexRun:
        if self.model.steps > self.model.window:
            raise ValueError("model.steps must not exceed model.window")
        return self

    @property
    def registered_model(self) -> str:
        return self.tracking.registered_model or self.name

    @property
    def variant(self) -> str:
        """Chen et al. 2024 Table 5's name: BiLSTM, Transformer, FCN, TCN, BiLSTM-C, -M, -CM."""
        base = {"bilstm": "BiLSTM", "transformer": "Transformer", "fcn": "FCN", "tcn": "TCN"}[self.model.kind]
        suffix = ("C" if self.model.calibration else "") + ("M" if self.model.median else "")
        return f"{base}-{suffix}" if suffix else base


class FlexConfig(_FlexRun):
    """Simulated flex sensors over knees and elbows → the Table 3 joints, three angles each."""

    sensors: list[str] = Field(default_factory=lambda: list(FLEX_SENSOR_JOINTS))
    joints: list[str] = Field(default_factory=lambda: list(TABLE3_JOINTS))
    data: FlexDataConfig = Field(default_factory=FlexDataConfig)

    @model_validator(mode="after")
    def _joints(self) -> FlexConfig:
        unknown = sorted(set(self.sensors + self.joints) - set(FLEX_JOINTS))
        if unknown:
            raise ValueError(f"joints are {list(FLEX_JOINTS)}; unknown {unknown}")
        return self

    @property
    def components(self) -> int:
        return 3  # flexion, abduction, rotation (service.core.joint_angles.JOINT_COMPONENTS)


class CapacitiveConfig(_FlexRun):
    """Real capacitive sleeves (seven channels on one leg's shank and thigh) → that knee's flexion. Both legs'
    sleeves train one model; one trial type trains, the other is held out. A model for others to use trains on
    every trial (``also_train``, no ``test_trial``) and carries the held-out figures of its recipe's runs."""

    source: str = "capacitive_sub01"
    train_trial: str = "CSBaseline"  # trains, and the knee hinge reference is fitted on it
    test_trial: str | None = "CSStiffKnee"
    also_train: list[str] = Field(default_factory=list)  # further trials that train (their last val_share validates)
    # a leg whose sleeve never trains and is the test over the training trials: a sleeve the model never saw, the
    # nearest this one person's data comes to another person's sleeve
    held_out_leg: Literal["Left", "Right"] | None = None
    rate_hz: float = 50.0  # the sleeves record at 100 Hz; window 100 at 50 Hz holds about two strides
    val_share: float = Field(0.2, gt=0.0, lt=0.5)  # the training trial's last part, per leg: early stopping
    # each sleeve put in step with the Xsens sensors by its board's IMU (service.core.recordings.capacitive_sleeve_sync)
    sync: bool = True

    @property
    def training_trials(self) -> list[str]:
        return [self.train_trial, *self.also_train]

    @property
    def joints(self) -> list[str]:
        return ["Knee"]

    @property
    def sensors(self) -> list[str]:
        return []

    @property
    def components(self) -> int:
        return 1

    @model_validator(mode="after")
    def _trials_are_distinct(self) -> CapacitiveConfig:
        if self.test_trial in self.training_trials or len(set(self.training_trials)) < len(self.training_trials):
            raise ValueError(
                f"each trial trains or is held out, once: training {self.training_trials}, held out {self.test_trial}"
            )
        if self.held_out_leg and self.test_trial:
            raise ValueError(f"hold out a leg ({self.held_out_leg}) or a trial ({self.test_trial}), not both")
        return self


def load_flex_config(path: str | Path, overrides: list[str] | None = None) -> FlexConfig:
    return FlexConfig.model_validate(read_yaml(path, overrides))


def load_capacitive_config(path: str | Path, overrides: list[str] | None = None) -> CapacitiveConfig:
    return CapacitiveConfig.model_validate(read_yaml(path, overrides))
