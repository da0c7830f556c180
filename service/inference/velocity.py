"""Running an ``imu_pose_velocity`` model: the learned pelvis velocity that moves the body with
``service.core.translation`` (``translation: learned``). Used by the service and by training's evaluation alike."""

from __future__ import annotations

import numpy as np

from service.core.manifest import PoseSpec
from service.inference.registry import LoadedModel
from service.inference.stateful import StreamState, step_many, zero_state


class VelocityModel:
    """A loaded ``imu_pose_velocity`` model with its manifest's velocity section."""

    def __init__(self, loaded: LoadedModel) -> None:
        if loaded.manifest.velocity is None:
            raise ValueError(f"{loaded.manifest.name} is not an imu_pose_velocity model")
        self.loaded, self.spec = loaded, loaded.manifest.velocity

    @property
    def name(self) -> str:
        return self.loaded.manifest.name

    def new_state(self) -> StreamState:
        return zero_state(self.spec.state_layers, self.spec.state_hidden)

    def step_many(
        self, features: list[np.ndarray], states: list[StreamState]
    ) -> tuple[list[np.ndarray], list[StreamState]]:
        """Live sessions' frames ``(n_k, F)`` → each one's velocities ``(n_k, 3)`` in the pelvis frame (each for the
        frame ``look_ahead_frames`` earlier) and new state (``service.inference.stateful.step_many``)."""
        return step_many(self.loaded.session, features, states)

    def predict(self, features: np.ndarray) -> np.ndarray:
        """The pelvis velocity in the pelvis frame ``(T, 3)``, m/s, of every frame of ``features`` ``(T, F)``: run
        over the recording from a zero state with the last frame repeated for the look-ahead, as a live stream
        that ends would answer."""
        L = self.spec.look_ahead_frames
        x = np.concatenate([features, np.repeat(features[-1:], L, axis=0)]) if L else features
        (v,), _ = self.step_many([x], [self.new_state()])
        return v[L:].astype(np.float64)


def world_velocity(R_world_pelvis: np.ndarray, v_pelvis: np.ndarray) -> np.ndarray:
    """Velocities in the pelvis frame ``(T, 3)`` → the world the pelvis orientations ``(T, 3, 3)`` are given in."""
    return np.einsum("tij,tj->ti", R_world_pelvis, v_pelvis)


def velocity_model_for(models: dict[str, VelocityModel], pose: PoseSpec) -> VelocityModel | None:
    """The velocity model that reads the pose features of the pose model ``pose`` (the same sensors in the same
    order, feature version and acceleration scale) and, for a streaming one, answers within its look-ahead; or
    None."""
    return next(
        (
            m
            for m in models.values()
            if m.spec.sensors == list(pose.sensors)
            and m.spec.feature_version == pose.feature_version
            and m.spec.acc_scale_mps2 == pose.acc_scale_mps2
            and (not pose.streaming or m.spec.look_ahead_frames <= pose.look_ahead_frames)
        ),
        None,
    )


def learned_velocity_model(
    models: dict[str, VelocityModel], pose: PoseSpec, pose_name: str, translation: str
) -> VelocityModel | None:
    """The velocity model that translation ``learned`` runs beside the pose model ``pose_name`` (None for the other
    translations); LookupError, saying what is loaded and what to use instead, where none reads its features."""
    if translation != "learned":
        return None
    velocity = velocity_model_for(models, pose)
    if velocity is None:
        loaded = {name: m.spec.sensors for name, m in sorted(models.items())} or "none"
        within = f" that answers within its {pose.look_ahead_frames} frames of look-ahead" if pose.streaming else ""
        raise LookupError(
            f"'learned' needs a velocity model for the sensors {pose.sensors} of {pose_name}{within}; loaded velocity "
            f"models: {loaded}; 'feet' moves the body without one"
        )
    return velocity
