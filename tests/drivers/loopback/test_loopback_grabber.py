"""Loopback grabber: rendered frames on an injected clock, drops/corrupt/jitter, ring-buffer overrun, USB feed."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.biplane_pairing import BiplanePairer
from drivers.errors import DeviceTimeoutError, InputDataError
from drivers.frame_source import open_source
from drivers.loopback.loopback_grabber import (
    LoopbackFrameSource,
    LoopbackScene,
    fixed_pose,
    make_usb_backend,
    scripted_trajectory,
)
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, RobotPose, biplane_views

RATE = 30.0


class SimClock:
    """A clock the test advances; sleeping advances it too, as in a simulation harness."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture(scope="module")
def renderer() -> BiplaneRenderer:
    views = biplane_views(image_size=(64, 48), fov_mm=(40.0, 30.0))
    body = RobotBody(length_mm=10.0, diameter_mm=2.0, tip_angle_deg=20.0, attenuation_per_mm=0.5)
    return BiplaneRenderer(views, body, settings=ImagingSettings(noise=False), seed=1)


def moving(t: float) -> RobotPose:
    return RobotPose(centroid_mm=np.array([0.0, 20.0 * t, 0.0]), direction=np.array([0.0, 0.0, 1.0]))


def test_frames_are_renders_of_the_scene_at_their_exposure_time(renderer: BiplaneRenderer) -> None:
    clock = SimClock()
    scene = LoopbackScene(renderer, moving, rate_hz=RATE, exposure_s=0.004)
    sources = {plane: LoopbackFrameSource(scene, plane, clock=clock, sleep=clock.sleep) for plane in "pq"}
    for source in sources.values():
        source.open()
    frames: dict[str, list] = {"p": [], "q": []}
    for _ in range(5):
        for plane, source in sources.items():
            frames[plane].append(source.read(1.0))
    for plane, got in frames.items():
        assert [f.number for f in got] == [0, 1, 2, 3, 4]
        assert [f.device_time_s for f in got] == pytest.approx([n / RATE for n in range(5)])
        assert all(f.host_time_s > f.device_time_s and f.exposure_s == 0.004 for f in got)
        assert (sources[plane].width, sources[plane].height) == (64, 48)
    # The robot moves, so consecutive frames differ; both planes of one frame come from one render.
    assert not np.array_equal(frames["p"][0].image, frames["p"][4].image)
    expected = renderer.render(moving(2 / RATE + 0.002)).images
    assert np.array_equal(frames["p"][2].image, expected["p"])
    assert np.array_equal(frames["q"][2].image, expected["q"])
    assert scene.renders <= 6


def test_drops_and_corrupt_frames_are_counted_and_never_handed_on(renderer: BiplaneRenderer) -> None:
    clock = SimClock()
    scene = LoopbackScene(renderer, fixed_pose(moving(0.0)), rate_hz=RATE)
    source = LoopbackFrameSource(scene, "p", drop_probability=0.1, corrupt_probability=0.1, jitter_s=0.002,
                                 seed=5, buffer_frames=1000, clock=clock, sleep=clock.sleep)
    with source:
        got = [source.read(1.0) for _ in range(100)]
    numbers = [f.number for f in got]
    assert numbers == sorted(numbers) and len(set(numbers)) == 100
    counters = source.counters
    missing = numbers[-1] + 1 - len(numbers)
    assert counters.frames == 100 and counters.dropped == missing
    assert 0 < counters.corrupt < missing      # some of the missing numbers were corrupt, the rest dropped


def test_a_slow_reader_loses_the_oldest_frames_to_the_ring_buffer(renderer: BiplaneRenderer) -> None:
    clock = SimClock()
    scene = LoopbackScene(renderer, fixed_pose(None), rate_hz=RATE)
    source = LoopbackFrameSource(scene, "q", buffer_frames=3, clock=clock, sleep=clock.sleep)
    with source:
        assert source.read(1.0).number == 0
        clock.now += 10 / RATE          # the host looks away for ten frame periods
        numbers = [source.read(1.0).number for _ in range(4)]
    assert numbers[0] > 1 and numbers == list(range(numbers[0], numbers[0] + 4))
    assert source.counters.dropped == numbers[0] - 1


def test_interleaved_planes_pair_by_number_and_are_flagged(renderer: BiplaneRenderer) -> None:
    clock = SimClock()
    scene = LoopbackScene(renderer, moving, rate_hz=RATE, exposure_s=0.005, interleaved=True)
    p = LoopbackFrameSource(scene, "p", clock=clock, sleep=clock.sleep)
    q = LoopbackFrameSource(scene, "q", clock=clock, sleep=clock.sleep)
    pairer = BiplanePairer(match="number", mode="all", clock="device")
    with p, q:
        for _ in range(4):
            pairer.push(p.read(1.0))
            pairer.push(q.read(1.0))
    pairs = [pairer.pop() for _ in range(pairer.ready)]
    assert [pair.number for pair in pairs] == [0, 1, 2, 3]
    assert all(pair.interleaved and pair.skew_s == pytest.approx(0.5 / RATE) for pair in pairs)
    assert scene.renders >= 8          # each plane rendered at its own exposure time


def test_real_time_pacing_and_deadline(renderer: BiplaneRenderer) -> None:
    scene = LoopbackScene(renderer, fixed_pose(moving(0.0)), rate_hz=200.0, exposure_s=0.001)
    # A deep buffer: on a loaded machine the reader may lag, and this test is not about overruns.
    with LoopbackFrameSource(scene, "p", buffer_frames=10_000) as source:
        got = [source.read(5.0) for _ in range(5)]
        assert [f.number for f in got] == list(range(got[0].number, got[0].number + 5))
        assert all(b.host_time_s > a.host_time_s for a, b in zip(got, got[1:]))
    # A world whose clock stands still delivers nothing: the read ends at its deadline.
    frozen = SimClock()
    with LoopbackFrameSource(scene, "p", clock=frozen, sleep=lambda s: None) as stalled:
        with pytest.raises(DeviceTimeoutError, match="no frame within 50 ms"):
            stalled.read(0.05)
    assert stalled.counters.timeouts == 1


def test_bad_settings_are_refused(renderer: BiplaneRenderer) -> None:
    with pytest.raises(InputDataError, match="frame rate"):
        LoopbackScene(renderer, fixed_pose(None), rate_hz=0.0)
    with pytest.raises(InputDataError, match="half period"):
        LoopbackScene(renderer, fixed_pose(None), rate_hz=30.0, exposure_s=0.02, interleaved=True)
    scene = LoopbackScene(renderer, fixed_pose(None))
    with pytest.raises(InputDataError, match="drop_probability"):
        LoopbackFrameSource(scene, "p", drop_probability=1.5)


def test_scripted_trajectory_interpolates_and_holds() -> None:
    provider = scripted_trajectory([0.0, 1.0], [[0, 0, 0], [10, 0, 0]], [[1, 0, 0], [0, 1, 0]])
    assert provider(0.5).centroid_mm == pytest.approx([5, 0, 0])
    assert provider(0.5).direction == pytest.approx([np.sqrt(0.5), np.sqrt(0.5), 0])
    assert provider(3.0).centroid_mm == pytest.approx([10, 0, 0])


def test_the_scene_feeds_the_fake_usb_grabbers(renderer: BiplaneRenderer) -> None:
    scene = LoopbackScene(renderer, moving, rate_hz=RATE)
    backend = make_usb_backend(scene, realtime=False)
    with open_source("usb://1209:0001?serial=XRG-Q", backend=backend) as source:
        assert source.plane == "q" and (source.width, source.height) == (64, 48)
        got = [source.read(2.0) for _ in range(3)]
    assert [f.number for f in got] == [0, 1, 2]
    for f in got:
        assert np.array_equal(f.image, scene.image("q", f.number))
        assert f.device_time_s == pytest.approx(f.number / RATE, abs=1e-6)  # microsecond clock
