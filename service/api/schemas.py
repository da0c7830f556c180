"""Request and response bodies of the REST API (pydantic v2)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from service.core.segments import SEGMENTS

SegmentName = Literal[SEGMENTS]  # type: ignore[valid-type]
AccUnit = Literal["m/s^2", "g"]
GyrUnit = Literal["rad/s", "deg/s"]

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

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_WINDOW]})
    samples: list[list[float]] = Field(min_length=1)
    sample_rate_hz: float = Field(60.0, gt=0, description="between 10 and 2000 Hz")
    acc_unit: AccUnit = "m/s^2"
    gyr_unit: GyrUnit = "rad/s"
    segment: SegmentName | None = Field(None, description="known segment: the alignment is given for it")


class WindowsRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"windows": [EXAMPLE_WINDOW]}]})
    windows: list[ImuWindow] = Field(min_length=1)


class Alignment(BaseModel):
    segment: SegmentName
    q_segment_imu: list[float] = Field(description="unit quaternion w, x, y, z (w >= 0): v_segment = R(q) v_imu")
    R_segment_imu: list[list[float]]


class WindowResult(BaseModel):
    segment: SegmentName
    confidence: float
    probabilities: dict[str, float]
    moving: bool = Field(description="false: the gyroscope was still, the class is a guess")
    alignment: Alignment | None = None


class WindowsResponse(BaseModel):
    results: list[WindowResult]
    model_versions: dict[str, str]


class SensorWindows(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sensor_id: str = Field(min_length=1, max_length=128)
    windows: list[ImuWindow] = Field(min_length=1)


class AssignRequest(BaseModel):
    """Sensors recorded at the same time; each is assigned one segment.

    One-to-one by default (more sensors than segments: the weakest stay unassigned; fewer: some
    segments stay empty). ``allow_shared`` lets several sensors share a segment.
    """

    model_config = ConfigDict(extra="forbid")
    sensors: list[SensorWindows] = Field(min_length=1, max_length=64)
    allow_shared: bool = False


class SensorAssignment(BaseModel):
    sensor_id: str
    segment: SegmentName | None
    confidence: float
    margin: float = Field(
        description="summed log-probability lead of the assigned segment over the sensor's best other segment; "
        "negative when the one-to-one constraint overrode the sensor's own preference"
    )
    windows: int
    moving_windows: int
    alignment: Alignment | None = None


class AssignResponse(BaseModel):
    sensors: list[SensorAssignment]
    model_versions: dict[str, str]
