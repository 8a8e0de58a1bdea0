"""``appliance track DIR``: recognise the robot's posture in every frame pair of a biplane frame folder.

Writes one posture record (architecture.md contract) per frame pair as JSON Lines, to stdout or
``--out FILE``. Progress goes to stderr, and only when stderr is a terminal, so piped output and logs
stay clean. A missing or unreadable frame, a frame whose size is not the calibration's, a missing or
invalid calibration, or an empty folder ends the command with exit status 2 and a message naming the
file (and the frame number); the records written before it stay valid JSON Lines.

Frame folders carry no timestamps, so ``t`` is the frame number divided by ``--fps``.

With ``--robot N`` the tracker knows the robot: its catalogue body (length, where its volume centroid lies
from the tail) places the centroid and both tips on the reconstructed axis (:mod:`appliance.recognition.body_prior`);
an id the catalogue does not have ends the command with a message listing the ids there are. Without it the
centroid and tips are model-free.

Attenuation is a ratio of photon counts, so the detector's dark level (its gray level with no X-rays)
must come off every pixel first; left in, it compresses the robot's dense parts and biases the
weighted moments. It is a property of the detector, measured by its dark-frame calibration, so it
travels with the calibration file as ``metadata.detector.dark_level`` (``appliance demo`` writes it);
``--dark-level`` overrides it, and without either it is 0. It is not estimated from the image: the
darkest pixels of a frame are the robot's, not the offset, and the offset is not observable from an
exposed frame without a model of the field.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections import Counter
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any
from appliance.commands._common import non_negative_float, output_stream, positive_float
from appliance.geometry import dark_level_of

if TYPE_CHECKING:
    from appliance.geometry import Calibration
    from drivers.biplane_folder import BiplaneFolder

NAME = "track"
HELP = "recognise the robot's 3D posture in every frame pair of a biplane frame folder (JSON Lines out)"

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", metavar="DIR", type=Path,
                        help="biplane frame folder: DIR/p/NNNNNN.png|tif and DIR/q/NNNNNN.png|tif")
    parser.add_argument("--calibration", metavar="FILE", type=Path,
                        help="calibration YAML (default: DIR/calibration.yaml)")
    parser.add_argument("--out", metavar="FILE", type=Path,
                        help="write the posture records here (JSON Lines; default: stdout)")
    parser.add_argument("--robot", metavar="N", type=int,
                        help="robot number in config/robots.yaml (Table 1 of the seed paper): its known body "
                             "places the centroid and tips, and records carry its nominal length for comparison")
    parser.add_argument("--estimator", choices=("weighted", "paper"),
                        help="feature estimator (default: the recognition settings' default, 'weighted')")
    parser.add_argument("--fps", type=positive_float, default=DEFAULT_FPS, metavar="HZ",
                        help=f"frame rate for the records' t = frame / fps (default {DEFAULT_FPS:g})")
    parser.add_argument("--dark-level", type=non_negative_float, metavar="DN",
                        help="detector gray level with no X-rays, subtracted before taking attenuation "
                             "(default: the calibration's metadata.detector.dark_level, else 0)")


def load_inputs(folder: Path, calibration: Path | None) -> tuple[BiplaneFolder, Calibration]:
    """Open the folder and its calibration and check they fit together; errors name the file."""
    from appliance.errors import CalibrationError, InputDataError
    from appliance.geometry import Calibration
    from drivers.biplane_folder import BiplaneFolder

    listing = BiplaneFolder(folder)
    path = calibration or listing.calibration_path
    if path is None:
        raise CalibrationError(f"{folder / 'calibration.yaml'}: file not found "
                               "(put the calibration there or pass --calibration FILE)")
    cal = Calibration.load(path)
    # Re-list with the calibration's image sizes so that every frame read is checked against them.
    frames = BiplaneFolder(folder, expected_sizes={name: view.image_size for name, view in cal.views.items()})
    if not frames.frame_numbers:
        counts = ", ".join(f"{plane}/: {len(numbers)} unpaired" for plane, numbers in frames.unpaired.items())
        raise InputDataError(f"{folder}: no frame pairs to track ({counts}; "
                             "a pair is DIR/p/NNNNNN.png and DIR/q/NNNNNN.png with the same number)")
    return frames, cal


class _Progress:
    """One overwriting status line on stderr, at most ~10 updates a second, only on a terminal."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.enabled = sys.stderr.isatty()
        self._last = 0.0

    def update(self, done: int, number: int, counts: Counter[str], force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (not force and now - self._last < 0.1):
            return
        self._last = now
        sys.stderr.write(f"\rtrack: frame {number} ({done}/{self.total})  ok {counts['ok']}  "
                         f"ambiguous {counts['ambiguous']}  lost {counts['lost']}   ")
        sys.stderr.flush()

    def finish(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _robot(robot: int) -> Any:
    """The catalogue's robot ``robot`` (a ConfigError that lists the ids there are if there is none)."""
    from appliance.robots import load_robots, select_robot

    return select_robot(load_robots(), robot)


def track_folder(frames: BiplaneFolder, tracker: Any, out: IO[str], *, fps: float,
                 extra: dict[str, Any] | None = None) -> Counter[str]:
    """Run ``tracker.process`` on every pair of ``frames`` and write records to ``out``; returns counts."""
    counts: Counter[str] = Counter()
    progress = _Progress(len(frames))
    try:
        for done, (number, image_p, image_q) in enumerate(frames.pairs(), start=1):
            posture = tracker.process(image_p, image_q, frame=number, t=number / fps)
            record = posture.to_record()
            if extra:
                record.update(extra)
            out.write(json.dumps(record, allow_nan=False) + "\n")
            out.flush()  # a consumer tailing the file sees every frame as soon as it is done
            counts["ok" if record["ok"] and not record["ambiguous"] else
                   "ambiguous" if record["ok"] else "lost"] += 1
            progress.update(done, number, counts, force=done == len(frames))
    finally:
        progress.finish()
    return counts


def run(args: argparse.Namespace) -> int:
    frames, calibration = load_inputs(args.folder, args.calibration)
    from appliance.recognition import PostureTracker, RecognitionSettings

    dark_level = dark_level_of(calibration, args.dark_level)
    settings = (RecognitionSettings(estimator=args.estimator, dark_level=dark_level) if args.estimator
                else RecognitionSettings(dark_level=dark_level))
    extra = {}
    robot = None
    if args.robot is not None:
        robot = _robot(args.robot)
        extra = {"robot": args.robot, "nominal_length_mm": robot.length_mm}
    # With the robot named, its known body places the centroid and tips (recognition settings' body_prior).
    tracker = PostureTracker(calibration, settings=settings, body=robot)
    log.info("tracking %d frame pairs of %s (dark level %g)", len(frames), frames.root, dark_level)
    try:
        with output_stream(args.out, "posture records") as out:
            counts = track_folder(frames, tracker, out, fps=args.fps, extra=extra)
    except BrokenPipeError:
        # e.g. `appliance track DIR | head`: the reader has what it wanted; not an error.
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - the interpreter's final flush would fail again
        return 0
    summary = (f"tracked {len(frames)} frame pairs of {frames.root}: ok {counts['ok']}, "
               f"ambiguous {counts['ambiguous']}, lost {counts['lost']}")
    log.info(summary)
    if sys.stderr.isatty():
        print(summary, file=sys.stderr)
    return 0
