"""What the frame loop tells its observers: the per-step report, the listener interface, the recorder's listener.

:class:`LoopListener` is the observer interface of :class:`appliance.orchestrator.Orchestrator` (a live
view, the recorder); an exception raised by a listener stops the loop and surfaces as
:class:`ListenerError`, never swallowed. :class:`FrameReport` is one step's result; :class:`LoopStats`
the counts and latencies of a run; :class:`RecordingListener` writes it all into a session recording.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from appliance.errors import ApplianceError


class ListenerError(ApplianceError):
    """A loop listener (recorder, live view) failed; the loop stopped and the coils were zeroed."""


class LoopListener:
    """Observer of the loop. Override what you need; exceptions stop the loop (they are never swallowed)."""

    def on_start(self, t_s: float, info: dict[str, Any]) -> None: ...

    def on_frame(self, report: FrameReport) -> None: ...

    def on_ots(self, t_s: float, samples: list[dict[str, Any]]) -> None: ...

    def on_status(self, t_s: float, device: str, status: dict[str, Any]) -> None: ...

    def on_fault(self, t_s: float, fault: dict[str, Any]) -> None: ...

    def on_stop(self, t_s: float, summary: dict[str, Any]) -> None: ...


@dataclass
class FrameReport:
    """What one step saw and did (all lengths mm, fields T, forces N, currents A, times s)."""

    index: int
    t_s: float
    frame: int | None                     # biplane pair number; None when no pair came this step
    posture: dict[str, Any] | None        # the posture record (architecture.md contract)
    tracked: bool
    mode: str                             # safety mode after this step: run, hold, zero, stop
    reason: str | None
    cross_track_mm: float | None
    progress: float | None
    done: bool
    field_T: np.ndarray
    force_N: np.ndarray
    commanded_a: np.ndarray
    measured_a: np.ndarray | None
    scale: float
    limited_by: str | None
    stages_us: dict[str, float] = field(default_factory=dict)
    latency_write_s: float | None = None  # later frame of the pair on the host -> command written
    latency_ack_s: float | None = None    # ... -> command acknowledged with the measured currents
    stopped: bool = False
    images: tuple[np.ndarray, np.ndarray] | None = None   # the pair's (p, q) images, for the recorder
    available_s: float | None = None      # time.monotonic() when the later frame of the pair was on the host
    written_s: float | None = None        # time.monotonic() when the command's write returned

    def command_record(self) -> dict[str, Any]:
        return {"frame": self.frame, "mode": self.mode, "reason": self.reason, "tracked": self.tracked,
                "field_T": self.field_T.tolist(), "force_N": self.force_N.tolist(),
                "commanded_a": self.commanded_a.tolist(), "scale": self.scale, "limited_by": self.limited_by,
                "cross_track_mm": self.cross_track_mm, "progress": self.progress, "done": self.done}


@dataclass
class LoopStats:
    steps: int = 0
    pairs: int = 0
    tracked: int = 0
    lost: int = 0            # pairs where recognition found no (plausible) robot
    rejected: int = 0        # ... of which recognition reported one too far from the last to be it
    no_pair: int = 0         # steps without a new pair
    latency_write_s: list[float] = field(default_factory=list)
    latency_ack_s: list[float] = field(default_factory=list)
    step_s: list[float] = field(default_factory=list)


class RecordingListener(LoopListener):
    """Writes the loop into a :class:`appliance.recording.Recorder`. The frame's timing is
    written last: it is the recorder's frame boundary, where the file is flushed to disk."""

    def __init__(self, recorder: Any) -> None:
        self.recorder = recorder

    def on_frame(self, report: FrameReport) -> None:
        rec = self.recorder
        if report.posture is not None:
            rec.write_posture(report.t_s, report.posture)
        rec.write_command(report.t_s, report.command_record())
        if report.measured_a is not None:
            rec.write_currents(report.t_s, report.measured_a.tolist(), report.commanded_a.tolist())
        if report.images is not None and report.frame is not None:
            rec.write_frames(report.t_s, report.frame, report.images[0], report.images[1])
        rec.write_timing(report.t_s, report.frame, report.stages_us)

    def on_ots(self, t_s: float, samples: list[dict[str, Any]]) -> None:
        for sample in samples:
            self.recorder.write_ots(t_s, sample)

    def on_status(self, t_s: float, device: str, status: dict[str, Any]) -> None:
        self.recorder.write_status(t_s, device, status)

    def on_fault(self, t_s: float, fault: dict[str, Any]) -> None:
        self.recorder.write_fault(t_s, fault)

    def on_stop(self, t_s: float, summary: dict[str, Any]) -> None:
        self.recorder.write_status(t_s, "loop", summary)
        self.recorder.flush()
