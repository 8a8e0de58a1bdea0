"""Loopback X-ray grabbers: frames rendered from a scene, served as frame sources or through the fake USB device.

- :class:`LoopbackScene` is the shared "fluoroscope": a renderer (``BiplaneRenderer`` of
  ``drivers.loopback.xray_render``, or anything with ``render(pose) -> .images``), a scene provider
  ``provider(t) -> RobotPose | None`` (a fixed pose, a scripted trajectory, later the simulated world), a
  frame rate, an exposure time and optional interleaving (q exposes half a period after p). Frame ``n`` of
  plane p starts its exposure at ``n / rate_hz``; both planes of one frame come from one render unless
  interleaved, when each plane is rendered at its own exposure time. Renders are cached so two planes
  read from two threads cost one render.
- :class:`LoopbackFrameSource` is one plane of the scene as a :class:`FrameSource` (one instance per
  plane; pairing works on two sources as with real grabbers). It models a free-running grabber with a
  small ring buffer on an injected clock: frame ``n`` arrives at exposure start + exposure + latency +
  jitter; a reader that falls behind loses the oldest buffered frames (counted as dropped). Injected
  faults: random drops (never delivered) and corrupt frames (the grabber detects the CRC error and
  discards the frame: counted as corrupt, never handed on). With the real clock it paces in real time;
  a simulation passes its own clock and gets every frame whose time has come at once.
- :class:`SceneFeed` is one plane of the scene as a :class:`~drivers.loopback.usb_backend.FrameFeed`,
  so the fake USB grabber streams rendered frames; :func:`make_usb_backend` builds that fake for both planes.

Not modelled: detector lag/ghosting, dark-frame offsets drifting over time, the grabber's own clock drift.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from drivers.errors import InputDataError
from drivers.frame_source import Frame, FrameSource
from drivers.loopback.usb_backend import DeviceFrame, FakeGrabberBackend, FakeGrabberDevice

log = logging.getLogger(__name__)

SceneProvider = Callable[[float], Any]  # t (s) -> RobotPose | None


class Renderer(Protocol):
    def render(self, pose: Any) -> Any: ...   # -> object with .images {"p","q": uint16 (h, w)}


def fixed_pose(pose: Any) -> SceneProvider:
    """A scene provider that always shows ``pose`` (None: an empty field)."""
    return lambda t: pose


def scripted_trajectory(times_s: Sequence[float], centroids_mm: Sequence[Sequence[float]],
                        directions: Sequence[Sequence[float]], pose_type: Callable[..., Any] | None = None
                        ) -> SceneProvider:
    """Piecewise-linear trajectory through keyframes (centroid linear, direction normalised-linear),
    held at the ends. ``pose_type`` defaults to ``xray_render.RobotPose``."""
    ts = np.asarray(times_s, dtype=float)
    cs = np.asarray(centroids_mm, dtype=float)
    ds = np.asarray(directions, dtype=float)
    if ts.ndim != 1 or len(ts) < 1 or cs.shape != (len(ts), 3) or ds.shape != (len(ts), 3):
        raise InputDataError("a trajectory needs N times, N centroids (N,3) and N directions (N,3)")
    if np.any(np.diff(ts) <= 0):
        raise InputDataError("trajectory times must increase")
    if pose_type is None:
        from drivers.loopback.xray_render import RobotPose
        pose_type = RobotPose

    def provider(t: float) -> Any:
        centroid = np.array([np.interp(t, ts, cs[:, k]) for k in range(3)])
        direction = np.array([np.interp(t, ts, ds[:, k]) for k in range(3)])
        return pose_type(centroid_mm=centroid, direction=direction / np.linalg.norm(direction))

    return provider


class LoopbackScene:
    """The simulated fluoroscope both loopback planes expose from (see the module docstring)."""

    def __init__(self, renderer: Renderer, provider: SceneProvider, *, rate_hz: float = 30.0,
                 exposure_s: float = 0.005, interleaved: bool = False, cache_frames: int = 8) -> None:
        if rate_hz <= 0:
            raise InputDataError(f"loopback frame rate must be > 0 Hz, got {rate_hz}")
        if exposure_s < 0 or (interleaved and exposure_s > 0.5 / rate_hz):
            raise InputDataError(f"exposure {exposure_s * 1e3:.1f} ms does not fit the frame period"
                                 f"{' (interleaved: half period)' if interleaved else ''} at {rate_hz} Hz")
        self.renderer = renderer
        self.provider = provider
        self.rate_hz = rate_hz
        self.exposure_s = exposure_s
        self.interleaved = interleaved
        self._cache: OrderedDict[float, dict[str, np.ndarray]] = OrderedDict()
        self._cache_frames = cache_frames
        self._lock = threading.Lock()
        self._origin: float | None = None
        self.renders = 0

    def origin(self, clock: Callable[[], float]) -> float:
        """The clock reading at which frame 0 was triggered: set by the first grabber to start, shared by
        all (one trigger generator drives both planes, so equal numbers mean simultaneous exposures)."""
        with self._lock:
            if self._origin is None:
                self._origin = clock()
            return self._origin

    def first_frame_after(self, elapsed_s: float) -> int:
        """The first frame whose exposure starts at or after ``elapsed_s`` since the origin."""
        return max(0, int(np.ceil(elapsed_s * self.rate_hz - 1e-6)))

    def exposure_start(self, plane: str, number: int) -> float:
        """Start of the exposure of frame ``number`` of ``plane`` on the scene clock (s)."""
        offset = 0.5 / self.rate_hz if (self.interleaved and plane == "q") else 0.0
        return number / self.rate_hz + offset

    def image(self, plane: str, number: int) -> np.ndarray:
        """The rendered image of ``plane`` for frame ``number`` (uint16, shared: do not modify)."""
        t = self.exposure_start(plane, number)
        with self._lock:
            images = self._cache.get(t)
            if images is None:
                # The pose at mid-exposure stands for the (unmodelled) motion blur.
                rendered = self.renderer.render(self.provider(t + 0.5 * self.exposure_s))
                images = rendered.images
                self.renders += 1
                self._cache[t] = images
                while len(self._cache) > self._cache_frames:
                    self._cache.popitem(last=False)
            return images[plane]

    def image_size(self, plane: str) -> tuple[int, int]:
        image = self.image(plane, 0)
        return int(image.shape[1]), int(image.shape[0])


class LoopbackFrameSource(FrameSource):
    """One plane of a :class:`LoopbackScene` as a free-running grabber (see the module docstring)."""

    def __init__(self, scene: LoopbackScene, plane: str, *, latency_s: float = 0.002, jitter_s: float = 0.0,
                 drop_probability: float = 0.0, corrupt_probability: float = 0.0, buffer_frames: int = 4,
                 seed: int | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, name: str | None = None) -> None:
        super().__init__(plane=plane, name=name or f"loopback-{plane}", pixel_format="mono16")
        for label, value in (("drop_probability", drop_probability), ("corrupt_probability", corrupt_probability)):
            if not 0.0 <= value < 1.0:
                raise InputDataError(f"{self.name}: {label} must be in [0, 1), got {value}")
        if buffer_frames < 1:
            raise InputDataError(f"{self.name}: buffer_frames must be >= 1, got {buffer_frames}")
        self.scene = scene
        self.latency_s = latency_s
        self.jitter_s = jitter_s
        self.drop_probability = drop_probability
        self.corrupt_probability = corrupt_probability
        self.buffer_frames = buffer_frames
        self._rng = np.random.default_rng(seed)
        self._clock = clock
        self._sleep = sleep
        self._t0 = 0.0
        self._next = 0            # next frame number the device will expose
        self._fate: dict[int, tuple[float, float, str]] = {}   # number -> (device time, arrival, fate)

    def _open_internal(self) -> None:
        self.width, self.height = self.scene.image_size(self.plane)
        # Device time 0 is the shared trigger's frame 0; a grabber started later begins with the next exposure.
        self._t0 = self.scene.origin(self._clock)
        self._next = self.scene.first_frame_after(self._clock() - self._t0)
        self._fate.clear()

    def _close_internal(self) -> None:
        self._fate.clear()

    def _plan(self, number: int) -> tuple[float, float, str]:
        """When frame ``number`` starts exposing, when it arrives on the host and what happens to it."""
        planned = self._fate.get(number)
        if planned is None:
            start = self.scene.exposure_start(self.plane, number)
            jitter = abs(float(self._rng.normal(0.0, self.jitter_s))) if self.jitter_s > 0 else 0.0
            arrival = start + self.scene.exposure_s + self.latency_s + jitter
            roll = float(self._rng.random())
            fate = ("drop" if roll < self.drop_probability
                    else "corrupt" if roll < self.drop_probability + self.corrupt_probability else "ok")
            planned = (start, arrival, fate)
            self._fate[number] = planned
        return planned

    def _read_internal(self, deadline: float) -> Frame | None:
        while True:
            # A nanosecond of slack: clock readings near 1e5 s cannot resolve smaller differences.
            now = self._clock() - self._t0 + 1e-9
            # Frames that arrived but were overwritten in the grabber's ring buffer are lost.
            while True:
                newest = self._next
                while self._plan(newest + 1)[1] <= now:
                    newest += 1
                if newest - self._next < self.buffer_frames:
                    break
                lost = newest - self.buffer_frames + 1 - self._next
                for number in range(self._next, self._next + lost):
                    self._fate.pop(number, None)
                self._next += lost
                log.debug("%s: host too slow, %d frame(s) overwritten in the grabber buffer", self.name, lost)
            start, arrival, fate = self._plan(self._next)
            if arrival <= now:
                number = self._next
                self._next += 1
                self._fate.pop(number, None)
                if fate == "drop":
                    continue
                if fate == "corrupt":
                    self._count_corrupt()
                    log.debug("%s: frame %d failed its CRC, discarded", self.name, number)
                    continue
                image = self.scene.image(self.plane, number)
                return Frame(image=image, plane=self.plane, number=number, device_time_s=start,
                             host_time_s=self._t0 + arrival, exposure_s=self.scene.exposure_s,
                             pixel_format="mono16")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            # With the real clock this sleeps until the arrival; with a simulated clock it polls.
            self._sleep(max(1e-6, min(arrival - now, remaining, 0.05)))


class SceneFeed:
    """One plane of a :class:`LoopbackScene` as the fake USB grabber's frame feed."""

    def __init__(self, scene: LoopbackScene, plane: str) -> None:
        self.scene = scene
        self.plane = plane
        self.width, self.height = scene.image_size(plane)
        self.pixel_format = "mono16"

    @property
    def rate_hz(self) -> float:
        return self.scene.rate_hz

    @rate_hz.setter
    def rate_hz(self, value: float) -> None:
        # Both planes share the generator's trigger, so a rate set on one grabber applies to both.
        self.scene.rate_hz = value

    @property
    def exposure_s(self) -> float:
        return self.scene.exposure_s

    @exposure_s.setter
    def exposure_s(self, value: float) -> None:
        self.scene.exposure_s = value

    def origin(self, clock: Callable[[], float]) -> float:
        return self.scene.origin(clock)

    def first_frame_after(self, elapsed_s: float) -> int:
        return self.scene.first_frame_after(elapsed_s)

    def frame(self, number: int) -> DeviceFrame:
        return DeviceFrame(number=number, device_time_s=self.scene.exposure_start(self.plane, number),
                           exposure_s=self.scene.exposure_s, image=self.scene.image(self.plane, number))


def make_usb_backend(scene: LoopbackScene, *, planes: Sequence[str] = ("p", "q"), realtime: bool = True,
                     seed: int | None = None, **device_options: Any) -> FakeGrabberBackend:
    """A fake pyusb backend presenting one USB grabber per plane, streaming the scene's renders.
    Serial numbers are ``XRG-P`` and ``XRG-Q``."""
    devices = [FakeGrabberDevice(SceneFeed(scene, plane), serial=f"XRG-{plane.upper()}", realtime=realtime,
                                 seed=None if seed is None else seed + i, **device_options)
               for i, plane in enumerate(planes)]
    return FakeGrabberBackend(devices)
