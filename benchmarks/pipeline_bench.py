"""Real-time performance of the frame step (issue 8): the same table as ``appliance bench``.

Per stage p50/p99 (us) for steady-state ROI tracking and cold full-frame detection, the plain OpenCV
baseline and the memory floor with their ratios, the in-process loop (frame available -> amplifier
command written) and the closed loop in simulation. Asserts nothing; the figures depend on the machine
and its load, which the table's first line states.

    .venv/bin/python benchmarks/pipeline_bench.py [--json FILE] [--frames N] [--size 1024] [--sim-seconds S]

The measuring code lives in ``appliance/benchmarking.py`` (and the scene in ``appliance/commands/bench.py``)
so that the installed CLI has it; this script is the same command for those who run benchmarks/.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands import bench  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    bench.add_arguments(parser)
    return bench.run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
