"""How the streaming client shows a stream: the live display (the stream's messages, ``service/api/stream.py``,
folded into one rich table, a row per sensor, that a ``rich.live.Live`` redraws as they arrive), the plain log of
its notices, and the summary at the end."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rich import box
from rich.console import Group, JustifyMethod, RenderableType
from rich.table import Table
from rich.text import Text

if TYPE_CHECKING:
    from service.client import StreamOutcome

log = logging.getLogger(__name__)

NUMERIC = ("conf", "moving", "p_correct", "spread")
STATUS_STYLE = {"assigned": "bold green", "not_enough_walking": "yellow", "uncalibrated": "dim"}


@dataclass
class SensorRow:
    """What the stream has said about one sensor so far."""

    window: str = "-"  # the last window's own answer
    window_confidence: float | None = None  # and its probability
    moving: bool | None = None  # whether that window moved
    moment: str = "-"  # the last per-moment one-to-one answer
    assigned: str = "-"  # the stream's joint assignment
    moving_windows: int = 0  # the moving windows it rests on
    p_correct: float | None = None
    spread_deg: float | None = None
    notices: dict[str, int] = field(default_factory=dict)  # gap / late: how many


class LiveView:
    """The state of one stream, updated message by message (``update``) and drawn by rich (``__rich__``, which a
    ``Live`` calls from its refresh thread: the rows are fixed at the start, and what it iterates is copied)."""

    def __init__(self, sensor_ids: list[str]) -> None:
        self.rows = {sensor_id: SensorRow() for sensor_id in sensor_ids}
        self.status = "waiting for the first windows"
        self.p_all_correct: float | None = None
        self.time_s = 0.0  # the latest window end the stream has answered
        self.declared = ""
        self.errors: list[str] = []
        self.dropped = 0

    def update(self, message: dict) -> None:
        kind = message.get("type")
        if kind == "started":
            self._started(message)
        elif kind == "result":
            self._result(message)
        elif kind == "moment":
            self.time_s = max(self.time_s, message["window_end_s"])
            for sensor_id, segment in message["segments"].items():
                self.rows[sensor_id].moment = segment or "(still)"
        elif kind == "assignment":
            self._assignment(message)
        elif kind in ("gap", "late"):
            notices = self.rows[message["sensor_id"]].notices
            notices[kind] = notices.get(kind, 0) + message.get("count", 1)
        elif kind == "error":
            self.errors.append(f"{message.get('detail')} (close code {message.get('close_code')})")

    def _started(self, message: dict) -> None:
        parts = []
        if message.get("worn_segments"):
            parts.append("worn: " + ", ".join(message["worn_segments"]))
        candidates = {k: v for k, v in (message.get("candidate_segments") or {}).items() if v}
        parts += [f"{k} on {' or '.join(v)}" for k, v in candidates.items()]
        self.declared = "; ".join(parts)
        self.status = "streaming"

    def _result(self, message: dict) -> None:
        row = self.rows[message["sensor_id"]]
        row.window, row.window_confidence = message["segment"], message["confidence"]
        row.moving = message["moving"]
        self.time_s = max(self.time_s, message["window_end_s"])

    def _assignment(self, message: dict) -> None:
        self.status = message["status"]
        self.p_all_correct = message.get("p_all_correct")
        self.dropped = message.get("results_dropped", 0)
        for s in message["sensors"]:
            row = self.rows[s["sensor_id"]]
            row.assigned = s["segment"] or "-"
            row.moving_windows, row.p_correct = s["windows"], s.get("p_correct")
            row.spread_deg = s.get("alignment_spread_deg")

    def table(self) -> Table:
        """One row per sensor: the last window's own answer and its confidence (dim when it was still), the last
        per-moment answer, the joint assignment with its moving windows, ``p_correct`` and alignment spread."""
        title = Text.assemble(
            ("wearmocap stream", "bold"),
            f"  {self.time_s:.1f} s answered  status ",
            (self.status, STATUS_STYLE.get(self.status, "")),
            "" if self.p_all_correct is None else f"  p_all_correct {self.p_all_correct:.3f}",
        )
        table = Table(title=title, caption=self.declared or None, box=box.SIMPLE_HEAD, padding=0, show_edge=False)
        columns = ["sensor", "window", "conf", "moment", "assigned", "moving", "p_correct", "spread"]
        notices = any(row.notices for row in self.rows.values())
        widest = max(len(sensor_id) for sensor_id in self.rows)
        for name in columns + (["notices"] if notices else []):
            justify: JustifyMethod = "right" if name in NUMERIC else "left"
            table.add_column(name, justify=justify, no_wrap=True, min_width=widest if name == "sensor" else None)
        for sensor_id, row in self.rows.items():
            cells = [
                sensor_id,
                Text(row.window, style="dim" if row.moving is False else ""),
                _number(row.window_confidence, "{:.0%}"),
                row.moment,
                Text(row.assigned, style="bold" if self.status == "assigned" else ""),
                str(row.moving_windows),
                _number(row.p_correct, "{:.2f}"),
                _number(row.spread_deg, "{:.0f}°"),
            ]
            if notices:
                cells.append(", ".join(f"{n} {kind}" for kind, n in list(row.notices.items())))
            table.add_row(*cells)
        return table

    def __rich__(self) -> RenderableType:
        lines: list[RenderableType] = [self.table()]
        if self.dropped:
            lines.append(Text(f"{self.dropped} results dropped by the server (this client read too slowly)", "yellow"))
        lines += [Text(f"error: {e}", "bold red") for e in self.errors]
        return Group(*lines)


def _number(value: float | None, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)


class PlainNotices:
    """Plain display (a callable for ``stream_sensors``' ``on_message``): every notice (started, gap, late, error)
    logged as it arrives, and each change of the stream's status with the stream time it happened at."""

    def __init__(self) -> None:
        self.status: str | None = None
        self.time_s = 0.0

    def __call__(self, message: dict) -> None:
        kind = message["type"]
        if kind in ("result", "moment"):
            self.time_s = max(self.time_s, message["window_end_s"])
        elif kind == "assignment":
            if message["status"] != self.status:
                log.info("status %s at %.1f s", message["status"], self.time_s)
                self.status = message["status"]
        else:
            log.info("%s", message)


def log_summary(outcome: StreamOutcome, notices_logged: bool) -> None:
    """The end of a stream on the log: its notices (unless ``PlainNotices`` logged them as they came), how many
    answers arrived, and each sensor's final segment, confidence, margin and alignment, then the status."""
    if not notices_logged:
        for event in outcome.events:
            if event["type"] != "started":
                log.info("%s", event)
    log.info("%d window results, %d moments", len(outcome.results), len(outcome.moments))
    for s in (outcome.assignment or {}).get("sensors", []):
        alignment = s.get("alignment")
        q = "" if alignment is None else " ".join(f"{v:+.3f}" for v in alignment["q_segment_imu"])
        log.info(
            "%-32s -> %-14s confidence %.3f  margin %s  (%d moving windows)  q_segment_imu [%s] spread %s",
            s["sensor_id"],
            s["segment"],
            s["confidence"],
            "-" if s["margin"] is None else f"{s['margin']:.1f}",
            s["windows"],
            q,
            "-" if s.get("alignment_spread_deg") is None else f"{s['alignment_spread_deg']:.1f}°",
        )
    if outcome.assignment is not None:
        log.info("status %s", outcome.assignment["status"])
