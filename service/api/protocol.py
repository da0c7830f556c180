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
  {"type": "stop"}
``seq`` is the sensor's sample counter of the packet's first sample (0, 1, 2, … per sample).

Server → client
  started · result (per window: class, probabilities, moving, turns_about_vertical, alignment: the window's own
  answer over all seven segments) · moment (sessions of two or more sensors or with worn_segments, per window end
  time: the one-to-one answer of the sensors' windows that end then, as /v1/imu/assign's window_segments; sent
  once every sensor has reached that time, or when 32 moments wait on a stalled sensor, whose windows then come
  in moments of their own) · assignment (joint, one-to-one over the session's evidence, and per sensor the robust
  mean alignment over its last WEARMOCAP_STREAM_ALIGNMENT_WINDOWS moving windows with its spread; after each group
  of results) · gap / late (sequence problems, in order with the results) · error (then close, after the results
  of every accepted packet).
Close codes: 1003 unsupported data, 1008 protocol violation, 1009 message too big, 1000 after stop.
"""

from __future__ import annotations

import struct
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.api.schemas import (
    CANDIDATE_SEGMENTS_DESCRIPTION,
    WORN_SEGMENTS_DESCRIPTION,
    AccUnit,
    GyrUnit,
    SegmentSet,
    check_declarations,
)

HEADER = struct.Struct("<HHI")


class ProtocolError(ValueError):
    """A client broke the protocol; ``code`` is the WebSocket close code to use."""

    def __init__(self, message: str, code: int = 1008) -> None:
        super().__init__(message)
        self.code = code


class StreamSensor(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sensor_id: str = Field(min_length=1, max_length=128)
    sample_rate_hz: float = Field(60.0, ge=10.0, le=2000.0)
    acc_unit: AccUnit = "m/s^2"
    gyr_unit: GyrUnit = "rad/s"
    candidate_segments: SegmentSet | None = Field(None, description=CANDIDATE_SEGMENTS_DESCRIPTION)


class StartMessage(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: Literal["start"]
    sensors: list[StreamSensor] = Field(min_length=1, max_length=64)
    allow_shared: bool = False
    worn_segments: SegmentSet | None = Field(None, description=WORN_SEGMENTS_DESCRIPTION)

    @model_validator(mode="after")
    def _declarations_agree(self) -> StartMessage:
        check_declarations([s.candidate_segments for s in self.sensors], self.worn_segments, "sensors")
        return self


class SamplesMessage(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: Literal["samples"]
    sensor_id: str
    seq: int = Field(ge=0)
    samples: list[list[float]] = Field(min_length=1)


def decode_binary(data: bytes, n_sensors: int, max_samples: int) -> tuple[int, int, np.ndarray]:
    """(sensor index, seq, samples ``(n, 6)`` float64) from a binary packet."""
    if len(data) < HEADER.size:
        raise ProtocolError(f"binary packet needs an {HEADER.size}-byte header, got {len(data)} bytes", 1003)
    index, n, seq = HEADER.unpack_from(data)
    if index >= n_sensors:
        raise ProtocolError(f"binary packet names sensor index {index}; the session has {n_sensors} sensors")
    if n > max_samples:
        raise ProtocolError(f"at most {max_samples} samples per packet, got {n}", 1009)
    expected = HEADER.size + 24 * n
    if len(data) != expected:
        raise ProtocolError(f"binary packet with n={n} must be {expected} bytes, got {len(data)}", 1003)
    return index, seq, np.frombuffer(data, dtype="<f4", offset=HEADER.size).reshape(n, 6).astype(np.float64)


def encode_binary(index: int, seq: int, samples: np.ndarray) -> bytes:
    """The client side of ``decode_binary``."""
    return HEADER.pack(index, len(samples), seq) + np.asarray(samples, dtype="<f4").tobytes()


def check_samples(samples: np.ndarray, max_samples: int, where: str) -> None:
    if samples.ndim != 2 or samples.shape[1] != 6:
        raise ProtocolError(f"{where}: samples must be rows of 6 values, got shape {samples.shape}")
    if len(samples) > max_samples:
        raise ProtocolError(f"{where}: at most {max_samples} samples per packet, got {len(samples)}", 1009)
    if not np.all(np.isfinite(samples)):
        raise ProtocolError(f"{where}: samples must be finite, got NaN or Inf")
