"""The validation session of the seed paper: each robot in several postures, each posture measured >= 30 times.

For each robot the session's devices are opened (:func:`appliance.device_factory.open_devices`: on a
bench the real grabbers and tracker, in simulation the loopback fakes on their real transports), the
X-ray <-> OTS registration is taken from the calibration file or measured with the fiducial phantom
(:mod:`appliance.validation.fiducials`, once per run: the tracker and the fluoroscope do not move between
robots), and then, posture by posture, the lab clamps the holder and the runner takes ``samples`` biplane
pairs from the frame stream and the next tracker frame of the holder tool after each. Every pair is
recognised by a fresh :class:`~appliance.recognition.PostureTracker` per posture (the first pair is a
full-frame search, the others track, as in a live session), timed on the wall clock, and compared with
the tracker's reference pose mapped into the X-ray frame (:mod:`appliance.validation.reference`).
In simulation the world's true pose is compared too, which separates the recognition's own error from
the reference chain's (tracker noise, registration, holder).
"""
from __future__ import annotations

import datetime as _dt
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from appliance.device_factory import Devices, open_devices
from appliance.errors import ConfigError
from appliance.recognition import PostureTracker
from appliance.recognition.posture import Posture
from appliance.registration import RigidTransform, registration_from_calibration
from appliance.robots import RobotSpec
from appliance.session_config import Session
from appliance.validation.fiducials import (
    FiducialRegistration,
    FiducialSettings,
    register_with_fiducials,
)
from appliance.validation.lab import Lab, PairFeed, ToolFeed, load_extra_tool
from appliance.validation.reference import ReferenceMapper, RobotPose
from appliance.validation.statistics import (
    axis_angle_deg,
    direction_angle_deg,
    position_error_mm,
    tip_errors_mm,
)

log = logging.getLogger(__name__)

#: The paper's protocol: each posture measured at least this many times.
PROTOCOL_SAMPLES = 30

Progress = Callable[[str], None]
LabFactory = Callable[[Devices, RobotSpec], Lab]


@dataclass(frozen=True)
class Plan:
    """What one run measures."""

    postures: int = 3
    samples: int = PROTOCOL_SAMPLES
    settle_frames: int = 6
    fiducials: FiducialSettings = field(default_factory=FiducialSettings)

    def __post_init__(self) -> None:
        if self.postures < 1:
            raise ConfigError(f"postures must be at least 1, got {self.postures}")
        if self.samples < 2:
            raise ConfigError(f"samples must be at least 2 per posture, got {self.samples}")

    @property
    def meets_protocol(self) -> bool:
        return self.samples >= PROTOCOL_SAMPLES


@dataclass
class Sample:
    """One biplane pair of one posture against its reference (errors None when the robot was not recognised)."""

    robot: int
    posture: int
    sample: int
    frame: int
    ots_frame: int | None
    ok: bool
    ambiguous: bool
    head_identified: bool
    head_correct: bool | None
    position_mm: float | None
    axis_deg: float | None
    tip_head_mm: float | None
    tip_tail_mm: float | None
    tip_mean_mm: float | None
    pixels_p: int | None
    pixels_q: int | None
    processing_ms: float
    #: Angle between the two views' axis planes (deg): near 0 the axis lies in an epipolar plane.
    plane_angle_deg: float | None
    reason: str | None
    centroid_mm: list[float] | None
    direction: list[float] | None
    reference_centroid_mm: list[float] | None
    reference_direction: list[float] | None
    #: Simulation only: the same errors against the world's true pose (recognition error alone).
    truth_position_mm: float | None = None
    truth_axis_deg: float | None = None
    truth_tip_mean_mm: float | None = None

    @property
    def pixels(self) -> float | None:
        """Pixels in the robot's cloud, mean of the two views."""
        counts = [c for c in (self.pixels_p, self.pixels_q) if c is not None]
        return float(np.mean(counts)) if counts else None


@dataclass
class RobotRun:
    robot: RobotSpec
    samples: list[Sample]
    reference_centroids_mm: list[list[float]]     # per posture: mean reference centroid (X-ray frame)
    devices: dict[str, str]
    wall_s: float


@dataclass
class ValidationResult:
    session: str
    simulation: bool
    plan: Plan
    runs: list[RobotRun]
    registration_source: str
    transform: RigidTransform                  # X-ray -> OTS
    fiducials: FiducialRegistration | None
    lab: str
    started: str
    wall_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    #: The appliance's X-ray calibration the session ran with (the registration belongs with it).
    calibration: Any = None

    @property
    def samples(self) -> list[Sample]:
        return [s for run in self.runs for s in run.samples]


def _errors(posture: Posture, reference: RobotPose) -> dict[str, Any]:
    if not posture.ok or posture.centroid_mm is None:
        return {}
    out: dict[str, Any] = {"position_mm": position_error_mm(posture.centroid_mm, reference.centroid_mm)}
    if posture.direction is not None:
        out["axis_deg"] = axis_angle_deg(posture.direction, reference.direction)
        if posture.head_identified:
            out["head_correct"] = direction_angle_deg(posture.direction, reference.direction) < 90.0
    if posture.tips_mm is not None and np.all(np.isfinite(posture.tips_mm)):
        tips = tip_errors_mm(posture.tips_mm, reference.head_mm, reference.tail_mm,
                             head_identified=posture.head_identified)
        out.update(tip_head_mm=tips.head_mm, tip_tail_mm=tips.tail_mm, tip_mean_mm=tips.mean_mm)
    return out


def _vector(value: Any) -> list[float] | None:
    return None if value is None else [round(float(v), 4) for v in np.asarray(value).ravel()]


def measure_posture(robot: RobotSpec, posture: int, plan: Plan, pairs: PairFeed, tools: ToolFeed, holder_handle: int,
                    mapper: ReferenceMapper, tracker: PostureTracker, lab: Lab) -> list[Sample]:
    """``plan.samples`` pairs of one posture, each with the next tracker frame of the holder tool."""
    samples: list[Sample] = []
    tracker.reset()
    for index in range(plan.samples):
        pair = pairs.next()
        start = time.perf_counter()
        recognised = tracker.process(pair.p.image, pair.q.image, frame=pair.number, t=pair.p.device_time_s)
        processing_ms = (time.perf_counter() - start) * 1e3
        ots_frame, tool = tools.next(holder_handle)
        reference = mapper.from_tool(tool) if tool is not None else None
        errors = _errors(recognised, reference) if reference is not None else {}
        truth = lab.true_pose()
        truth_errors = _errors(recognised, RobotPose.from_axis(*truth, robot)) if truth is not None else {}
        views = recognised.views
        reason = recognised.reason if reference is not None else "the tracker did not see the holder tool"
        samples.append(Sample(
            robot=robot.id, posture=posture, sample=index, frame=pair.number, ots_frame=ots_frame,
            ok=bool(recognised.ok and reference is not None), ambiguous=recognised.ambiguous,
            head_identified=recognised.head_identified, head_correct=errors.get("head_correct"),
            position_mm=errors.get("position_mm"), axis_deg=errors.get("axis_deg"),
            tip_head_mm=errors.get("tip_head_mm"), tip_tail_mm=errors.get("tip_tail_mm"),
            tip_mean_mm=errors.get("tip_mean_mm"),
            pixels_p=views["p"].pixel_count if views.get("p") is not None else None,
            pixels_q=views["q"].pixel_count if views.get("q") is not None else None,
            processing_ms=processing_ms, plane_angle_deg=recognised.plane_angle_deg, reason=reason,
            centroid_mm=_vector(recognised.centroid_mm), direction=_vector(recognised.direction),
            reference_centroid_mm=_vector(reference.centroid_mm) if reference else None,
            reference_direction=_vector(reference.direction) if reference else None,
            truth_position_mm=truth_errors.get("position_mm"), truth_axis_deg=truth_errors.get("axis_deg"),
            truth_tip_mean_mm=truth_errors.get("tip_mean_mm")))
    return samples


def _robot_line(robot: RobotSpec) -> str:
    return f"robot #{robot.id} ({robot.length_mm:g} mm x {robot.diameter_mm:g} mm, tip {robot.tip_angle_deg:g} deg)"


def run_validation(session: Session, robots: Sequence[RobotSpec], plan: Plan, lab_factory: LabFactory,
                   holder: RigidTransform, coils: Any, *, progress: Progress = lambda _: None,
                   session_for: Callable[[RobotSpec], Session] | None = None) -> ValidationResult:
    """The whole session for ``robots`` (see the module docstring); ``session_for(robot)`` may adapt the session
    per robot (in simulation: a vessel phantom wide enough for it)."""
    if not robots:
        raise ConfigError("no robot to validate")
    config = session.config
    if config.devices.ots.kind == "none":
        raise ConfigError(f"{session.source.name}: devices.ots: a validation session needs the optical tracker "
                          f"(kind: serial or loopback), got kind: none")
    if not plan.meets_protocol:
        progress(f"note: {plan.samples} samples per posture is fewer than the protocol's {PROTOCOL_SAMPLES}")
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    wall_start = time.perf_counter()
    transform: RigidTransform | None = None
    source = ""
    fiducials: FiducialRegistration | None = None
    runs: list[RobotRun] = []
    lab_name = ""
    calibration: Any = None
    for number, robot in enumerate(robots, start=1):
        head = f"[{number}/{len(robots)}] {_robot_line(robot)}"
        progress(f"{head}: opening the devices")
        robot_start = time.perf_counter()
        with open_devices(session_for(robot) if session_for else session, robot, coils) as devices:
            ots = devices.ots
            assert ots is not None   # kind none refused above; the factory opens the others
            lab = lab_factory(devices, robot)
            lab_name = lab.name
            pairs = PairFeed(devices.frames, lab, config.imaging.fps, settle_frames=plan.settle_frames)
            tools = ToolFeed(ots, lab)
            holder_handle = next(iter(ots.tools))
            if transform is None:
                calibration = devices.calibration
                saved = registration_from_calibration(devices.calibration)
                if saved is not None:
                    transform, source = saved, "saved with the calibration (metadata.ots_registration)"
                    progress(f"{head}: X-ray -> OTS registration {source}")
                else:
                    rom, name = lab.pointer_rom()
                    pointer = load_extra_tool(ots, rom, name, config.devices.ots.mode, config.devices.ots.rate_hz)
                    fiducials = register_with_fiducials(lab, devices.calibration, pairs, tools, pointer, plan.fiducials,
                                                        progress=lambda text, head=head: progress(f"{head}: {text}"))
                    transform, source = fiducials.registration.transform, "measured with the fiducial phantom"
            mapper = ReferenceMapper(transform, holder, robot)
            tracker = PostureTracker(devices.calibration, body=robot)
            samples: list[Sample] = []
            centroids: list[list[float]] = []
            for posture in range(plan.postures):
                lab.place_robot(posture, plan.postures)
                pairs.settle()
                measured = measure_posture(robot, posture, plan, pairs, tools, holder_handle, mapper, tracker, lab)
                samples.extend(measured)
                refs = [s.reference_centroid_mm for s in measured if s.reference_centroid_mm is not None]
                centroids.append(np.mean(refs, axis=0).round(3).tolist() if refs else [math.nan] * 3)
                ok = [s for s in measured if s.ok]
                pos = [s.position_mm for s in ok if s.position_mm is not None]
                ang = [s.axis_deg for s in ok if s.axis_deg is not None]
                progress(f"{head}: posture {posture + 1}/{plan.postures}: {len(ok)}/{len(measured)} recognised, "
                         f"position {np.mean(pos) if pos else math.nan:.3f} mm, "
                         f"axis {np.mean(ang) if ang else math.nan:.2f} deg")
            runs.append(RobotRun(robot, samples, centroids, dict(devices.names), time.perf_counter() - robot_start))
    assert transform is not None
    return ValidationResult(session=str(session.source), simulation=config.is_simulation, plan=plan, runs=runs,
                            registration_source=source, transform=transform, fiducials=fiducials, lab=lab_name,
                            started=started, wall_s=time.perf_counter() - wall_start, calibration=calibration)
