"""``appliance replay RECORDING``: re-run recognition on a session's recorded frames and compare.

The recognition core (:class:`appliance.recognition.PostureTracker`) runs again, with the calibration
the session used (the recording's ``/calibration``), on every recorded biplane pair, and each new
posture is compared with the posture the live loop recorded for that frame: centroid distance (mm),
axis angle (degrees, between the axes as lines; a head-to-tail flip is reported separately when
both postures identified the head) and the frame's state (``ok``, ``ambiguous`` or ``lost``).

Out: one JSON object per replayed frame (JSON Lines, stdout or ``--out FILE``) with the recorded
state, the full new posture record and the differences; then a summary on stderr (``--summary FILE``
also writes it as JSON): frames compared, max and RMS differences, frames whose state changed and
how. ``--max-centroid-mm``, ``--max-axis-deg`` and ``--max-state-changes`` turn the comparison into a
check: exit status 1 when one is exceeded. A missing, unreadable or frameless recording exits with
status 2 and a message naming the file. A recording cut off by a crash is replayed up to its last
complete frame, and the summary says so.

The session's robot (its config's ``robot.id``) is given to the tracker, as the live loop gave it, so its
known body places the centroid and tips in the replay too (a recording that names none is replayed
model-free).

What makes a replay differ from the live loop even with unchanged code: a session that kept only
every n-th pair (``recording.frames_every``) replays a tracker that saw fewer frames, so its region
of interest prediction and its resolution of epipolar-plane ambiguities from history can differ.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any
from appliance.commands._common import output_stream

NAME = "replay"
HELP = "re-run recognition on a session recording's frames and compare with the recorded postures"

log = logging.getLogger(__name__)


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be zero or more, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="RECORDING", type=Path, help="session recording (.mcap)")
    parser.add_argument("--out", metavar="FILE", type=Path,
                        help="write the per-frame comparison here (JSON Lines; default: stdout)")
    parser.add_argument("--summary", metavar="FILE", type=Path, help="also write the summary here (JSON)")
    parser.add_argument("--estimator", choices=("weighted", "paper"),
                        help="feature estimator (default: the recognition settings' default, as in the loop)")
    parser.add_argument("--max-centroid-mm", type=_non_negative, metavar="MM",
                        help="exit with status 1 when any frame's centroid moved more than this")
    parser.add_argument("--max-axis-deg", type=_non_negative, metavar="DEG",
                        help="exit with status 1 when any frame's axis turned more than this")
    parser.add_argument("--max-state-changes", type=int, metavar="N",
                        help="exit with status 1 when more than N frames changed state (ok/ambiguous/lost)")


# ------------------------------------------------------------------------------------ comparison
def state_of(record: dict[str, Any]) -> str:
    """``ok``, ``ambiguous`` or ``lost``: what the loop made of a posture record."""
    if not record.get("ok"):
        return "lost"
    return "ambiguous" if record.get("ambiguous") else "ok"


def _vector(value: Any) -> list[float] | None:
    if not isinstance(value, list) or len(value) != 3 or any(v is None for v in value):
        return None
    return [float(v) for v in value]


def compare(recorded: dict[str, Any] | None, replayed: dict[str, Any]) -> dict[str, Any]:
    """One frame's comparison line: recorded state, the replayed record, and the differences
    (``null`` where either side does not know the quantity)."""
    out: dict[str, Any] = {"frame": replayed["frame"], "t": replayed.get("t")}
    new_state = state_of(replayed)
    out["replayed_state"] = new_state
    if recorded is None:
        out.update(recorded_state=None, state_changed=None, centroid_diff_mm=None, axis_diff_deg=None,
                   direction_flipped=None, recorded=None, replayed=replayed)
        return out
    old_state = state_of(recorded)
    out.update(recorded_state=old_state, state_changed=old_state != new_state)
    a, b = _vector(recorded.get("centroid_mm")), _vector(replayed.get("centroid_mm"))
    out["centroid_diff_mm"] = None if a is None or b is None else round(math.dist(a, b), 6)
    u, v = _vector(recorded.get("direction")), _vector(replayed.get("direction"))
    if u is None or v is None or not math.hypot(*u) > 0 or not math.hypot(*v) > 0:
        out["axis_diff_deg"] = out["direction_flipped"] = None
    else:
        cosine = sum(x * y for x, y in zip(u, v)) / (math.hypot(*u) * math.hypot(*v))
        # An axis is a line: the angle between the lines is the difference; the sign only means
        # something when both sides identified the head.
        out["axis_diff_deg"] = round(math.degrees(math.acos(min(1.0, abs(cosine)))), 6)
        both_heads = bool(recorded.get("head_identified")) and bool(replayed.get("head_identified"))
        out["direction_flipped"] = (cosine < 0) if both_heads else None
    out["recorded"] = {key: recorded.get(key) for key in
                       ("ok", "ambiguous", "centroid_mm", "direction", "head_identified", "reason")}
    out["replayed"] = replayed
    return out


@dataclass
class ReplaySummary:
    """Accumulates the per-frame comparisons."""

    recording: str
    frames_replayed: int = 0
    frames_without_posture: list[int] = field(default_factory=list)
    centroid: list[tuple[int, float]] = field(default_factory=list)
    axis: list[tuple[int, float]] = field(default_factory=list)
    state_changed_frames: list[int] = field(default_factory=list)
    transitions: Counter[str] = field(default_factory=Counter)
    states: Counter[str] = field(default_factory=Counter)
    direction_flips: list[int] = field(default_factory=list)

    def add(self, line: dict[str, Any]) -> None:
        frame = line["frame"]
        self.frames_replayed += 1
        self.states[line["replayed_state"]] += 1
        if line["recorded_state"] is None:
            self.frames_without_posture.append(frame)
            return
        if line["centroid_diff_mm"] is not None:
            self.centroid.append((frame, line["centroid_diff_mm"]))
        if line["axis_diff_deg"] is not None:
            self.axis.append((frame, line["axis_diff_deg"]))
        if line["state_changed"]:
            self.state_changed_frames.append(frame)
            self.transitions[f"{line['recorded_state']}->{line['replayed_state']}"] += 1
        if line["direction_flipped"]:
            self.direction_flips.append(frame)

    @staticmethod
    def _stats(values: list[tuple[int, float]]) -> dict[str, Any]:
        if not values:
            return {"n": 0, "max": None, "rms": None, "max_frame": None}
        frame, largest = max(values, key=lambda item: item[1])
        rms = math.sqrt(sum(v * v for _, v in values) / len(values))
        return {"n": len(values), "max": round(largest, 6), "rms": round(rms, 6), "max_frame": frame}

    def to_dict(self) -> dict[str, Any]:
        return {"recording": self.recording, "frames_replayed": self.frames_replayed,
                "frames_compared": self.frames_replayed - len(self.frames_without_posture),
                "frames_without_posture": self.frames_without_posture,
                "replayed_states": dict(self.states),
                "centroid_diff_mm": self._stats(self.centroid), "axis_diff_deg": self._stats(self.axis),
                "state_changes": len(self.state_changed_frames), "state_changed_frames": self.state_changed_frames,
                "transitions": dict(self.transitions), "direction_flips": self.direction_flips}


def _text(summary: dict[str, Any]) -> str:
    def stat(name: str, unit: str) -> str:
        s = summary[name]
        if not s["n"]:
            return f"{name.split('_')[0]}: not compared (no frame with both known)"
        return (f"{name.split('_')[0]} difference over {s['n']} frames: max {s['max']:.4g} {unit} "
                f"(frame {s['max_frame']}), RMS {s['rms']:.4g} {unit}")
    lines = [f"replayed {summary['frames_replayed']} recorded frame pairs of {summary['recording']}; "
             f"compared {summary['frames_compared']} with their recorded posture",
             "  " + stat("centroid_diff_mm", "mm"), "  " + stat("axis_diff_deg", "deg"),
             f"  state changed (ok/ambiguous/lost) in {summary['state_changes']} frames"
             + (f": {summary['transitions']}" if summary["transitions"] else "")]
    if summary["direction_flips"]:
        lines.append(f"  head and tail swapped in {len(summary['direction_flips'])} frames")
    if summary["frames_without_posture"]:
        lines.append(f"  {len(summary['frames_without_posture'])} frames had no recorded posture")
    if summary.get("recording_cut_off"):
        lines.append(f"  the recording was not closed ({summary['recording_cut_off']}); "
                     "replayed up to its last complete frame")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- the command


def replay(reader: Any, tracker: Any, out: IO[str]) -> dict[str, Any]:
    """Run ``tracker`` over ``reader.frames()``, write comparison lines to ``out``; returns the summary."""
    from appliance.errors import InputDataError
    from appliance.recording_schemas import TOPIC_POSTURE

    recorded: dict[int, dict[str, Any]] = {}
    for _, _, record in reader.messages(TOPIC_POSTURE):
        if isinstance(record.get("frame"), int):
            recorded[record["frame"]] = record
    summary = ReplaySummary(str(reader.path))
    progress_on, last_shown = sys.stderr.isatty(), 0.0
    for frame, t_s, image_p, image_q in reader.frames():
        old = recorded.get(frame)
        # The loop's own time stamp keeps the tracker's velocity prediction as it was live.
        t = old["t"] if old is not None and isinstance(old.get("t"), (int, float)) else t_s
        posture = tracker.process(image_p, image_q, frame=frame, t=t)
        line = compare(old, posture.to_record())
        summary.add(line)
        out.write(json.dumps(line, allow_nan=False) + "\n")
        if progress_on and time.monotonic() - last_shown > 0.1:
            last_shown = time.monotonic()
            sys.stderr.write(f"\rreplay: frame {frame} ({summary.frames_replayed} replayed, "
                             f"{len(summary.state_changed_frames)} changed state)   ")
            sys.stderr.flush()
    if progress_on:
        sys.stderr.write("\n")
    result = summary.to_dict()
    if reader.stop_reason:
        result["recording_cut_off"] = reader.stop_reason
    if summary.frames_replayed == 0:
        every = reader.session.get("frames_every")
        raise InputDataError(f"{reader.path}: the recording has no frames to replay"
                             + (f" (it keeps every {every}th pair; the session ended before the first)"
                                if every and every > 1 else "")
                             + (f"; {reader.stop_reason}" if reader.stop_reason else ""))
    return result


def _recorded_robot(reader: Any) -> Any:
    """The robot the session tracked (its config's ``robot.id``), whose body the live tracker placed the
    centroid and tips by, so the replay does too; None (model-free) where the recording does not name one
    the catalogue has."""
    from appliance.errors import ConfigError
    from appliance.robots import load_robots, select_robot

    robot = (reader.config or {}).get("robot")
    robot_id = robot.get("id") if isinstance(robot, dict) else None
    if not isinstance(robot_id, int):
        return None
    try:
        return select_robot(load_robots(), robot_id)
    except ConfigError as err:
        log.warning("%s: %s; replaying without the robot's body", reader.path, err)
        return None


def run(args: argparse.Namespace) -> int:
    from appliance.errors import InputDataError
    from appliance.geometry import Calibration
    from appliance.recognition import PostureTracker, RecognitionSettings
    from appliance.recording import RecordingReader

    reader = RecordingReader(args.recording)
    if reader.calibration is None:
        raise InputDataError(f"{args.recording}: the recording has no /calibration (cut off before it?)")
    calibration = Calibration.from_dict(reader.calibration, source=f"{args.recording}: /calibration")
    settings = RecognitionSettings(estimator=args.estimator) if args.estimator else RecognitionSettings()
    tracker = PostureTracker(calibration, settings=settings, body=_recorded_robot(reader))
    with output_stream(args.out, "comparison") as out:
        summary = replay(reader, tracker, out)
    if args.summary is not None:
        try:
            args.summary.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        except OSError as err:
            raise InputDataError(f"{args.summary}: cannot write the summary ({err.strerror or err})") from err
    print(_text(summary), file=sys.stderr)
    return _check(summary, args)


def _check(summary: dict[str, Any], args: argparse.Namespace) -> int:
    failures = []
    for key, limit, unit in (("centroid_diff_mm", args.max_centroid_mm, "mm"),
                             ("axis_diff_deg", args.max_axis_deg, "deg")):
        largest = summary[key]["max"]
        if limit is not None and largest is not None and largest > limit:
            failures.append(f"{key.split('_')[0]} difference {largest:.4g} {unit} at frame "
                            f"{summary[key]['max_frame']} exceeds {limit:g} {unit}")
    if args.max_state_changes is not None and summary["state_changes"] > args.max_state_changes:
        failures.append(f"{summary['state_changes']} frames changed state (allowed: {args.max_state_changes})")
    for failure in failures:
        print(f"appliance replay: {failure}", file=sys.stderr)
    return 1 if failures else 0
