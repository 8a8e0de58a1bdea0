"""Cold-path kernels of ``background_kernels`` against another version of that file, in one process (issue 8).

The other version (``--base``, e.g. ``git show 3f0ba5c:appliance/recognition/background_kernels.py > base.py``)
is loaded as its own module on this tree's other kernels, so only that file differs. On ``appliance bench``'s
frames (robot 1, 1024^2), each call follows ``np.copyto`` of the pair into the host buffers (the cold regime:
the frame is where the copy left it) and runs on view p; base and this alternate per call, their order swapped
every frame and repetition. Thread CPU time per call; prints p50 / min and how many outputs differ bit for bit.
Asserts nothing.

* ``block_mean_log_4``: the block mean and log of the whole frame, and its halving (OpenCV's resize for a
  version that does not give it);
* ``window_attenuation``: the attenuation and noise of each detection window ``coarse_windows`` finds;
* ``log_background``: the view's whole background stage, the ``background.py`` beside ``--base`` (a checkout's,
  e.g. ``git archive 3f0ba5c | tar -x -C /tmp/base``) on that ``background_kernels.py``, against this tree's
  (thread CPU: OpenCV's work on its own worker threads is not in it).

    .venv/bin/python benchmarks/cold_kernel_ab.py --base base.py [--kernel block_mean_log_4] [--frames 30]
    .venv/bin/python benchmarks/cold_kernel_ab.py --base /tmp/base/appliance/recognition/background_kernels.py \
        --kernel log_background
"""
from __future__ import annotations

import argparse
import inspect
import sys
import time
import types
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from steady_ab import _load  # noqa: E402

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import RecognitionSettings, background, background_kernels  # noqa: E402
from appliance.recognition.background import _log_table, log_background  # noqa: E402
from appliance.recognition.detection import coarse_windows  # noqa: E402


def _block_mean_calls(module, image: np.ndarray, table: np.ndarray,  # type: ignore[no-untyped-def]
                      settings: RecognitionSettings):
    out = np.empty((image.shape[0] // 4, image.shape[1] // 4), dtype=np.float32)
    half = np.empty((out.shape[0] // 2, out.shape[1] // 2), dtype=np.float32)
    fused = "half" in inspect.signature(module.block_mean_log_4.py_func).parameters

    def call() -> list[np.ndarray]:
        if fused:
            module.block_mean_log_4(image.view(np.uint64), table, out, half)
        else:   # (a version without the halving: the resize the background then calls)
            module.block_mean_log_4(image.view(np.uint64), table, out)
            half[:] = cv2.resize(out, (half.shape[1], half.shape[0]), interpolation=cv2.INTER_AREA)
        return [out, half]
    return call


def _window_calls(module, image: np.ndarray, table: np.ndarray,  # type: ignore[no-untyped-def]
                  settings: RecognitionSettings):
    background = log_background(image, settings.background_scale_px, settings.dark_level)
    rois = coarse_windows(background, settings)

    def call() -> list[np.ndarray]:
        results = []
        for roi in rois:
            a, sigma = module.window_attenuation(image, roi.y0, roi.y1, roi.x0, roi.x1, background.coarse,
                                                 background.fy, background.fx, table)
            results += [a, np.array([sigma])]
        return results
    return call


def _background_calls(module, image: np.ndarray, table: np.ndarray,  # type: ignore[no-untyped-def]
                      settings: RecognitionSettings):
    def call() -> list[np.ndarray]:
        b = module.log_background(image, settings.background_scale_px, settings.dark_level)
        return [b.coarse_log, b.coarse, b.coarse_attenuation]
    return call


CALLS = {"block_mean_log_4": _block_mean_calls, "window_attenuation": _window_calls,
         "log_background": _background_calls}

_IMPORT = "from appliance.recognition import background_kernels\n"


def _base_background(kernels_path: Path) -> types.ModuleType:
    """The ``background.py`` beside ``kernels_path``, its ``background_kernels`` that file."""
    path = kernels_path.parent / "background.py"
    source = path.read_text()
    assert _IMPORT in source, "the base background.py imports its kernels as this tool expects"
    module = types.ModuleType("background_base")
    module.__dict__["background_kernels"] = _load(kernels_path, "background_kernels_base")
    exec(compile(source.replace(_IMPORT, ""), str(path), "exec"), module.__dict__)
    return module


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, required=True)
    parser.add_argument("--kernel", choices=sorted(CALLS), default="block_mean_log_4")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--reps", type=int, default=6)
    args = parser.parse_args(argv)
    warm_up_all()
    if args.kernel == "log_background":
        modules = {"base": _base_background(args.base), "this": background}
    else:
        modules = {"base": _load(args.base, "background_kernels_base"), "this": background_kernels}
    scene = RenderedScene(1024, robot_id=1)
    settings = RecognitionSettings(dark_level=scene.dark_level)
    table = _log_table(float(settings.dark_level))
    source = scene.pairs()
    frames = [tuple(np.array(image) for image in next(source)) for _ in range(args.frames)]
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    times: dict[str, list[float]] = {name: [] for name in modules}
    differ = 0
    thread = time.thread_time_ns
    for r in range(args.reps):
        for n, pair in enumerate(frames):
            order = list(modules) if (r + n) % 2 == 0 else list(modules)[::-1]
            outputs = {}
            for name in order:
                np.copyto(host[0], pair[0])
                np.copyto(host[1], pair[1])
                call = CALLS[args.kernel](modules[name], host[0], table, settings)
                np.copyto(host[0], pair[0])   # (the set-up read the frame: arrive again)
                np.copyto(host[1], pair[1])
                began = thread()
                outputs[name] = call()
                times[name].append((thread() - began) / 1e3)
            a, b = outputs["base"], outputs["this"]
            differ += len(a) != len(b) or not all(np.array_equal(x.view(np.uint8), y.view(np.uint8))
                                                  for x, y in zip(a, b))
    print(f"{args.kernel}: {args.frames} frames x {args.reps} reps (robot 1, 1024^2, view p), after the pair's copy, "
          f"thread CPU us")
    for name, values in times.items():
        v = np.asarray(values)
        print(f"  {name:<5} p50 {np.percentile(v, 50):7.1f}  min {v.min():7.1f}")
    print(f"  calls whose outputs differ (bit for bit): {differ} of {args.frames * args.reps}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
