"""The device factory: loopback devices on real transports tied to one simulated world; real kinds open ports."""
from __future__ import annotations

import copy
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from appliance.config_io import config_path, read_yaml
from appliance.control import load_coils
from appliance.device_factory import amplifier_limits, open_devices, perturbed_calibration, turned_views
from appliance.errors import DeviceNotFoundError
from appliance.robots import load_robots
from appliance.session_config import AmplifierDevice, session_from_mapping
from appliance.sim_bench import SimClock
from drivers.loopback.lab import PoseHistory
from drivers.amplifier import Amplifier
from drivers.loopback.xray_render import biplane_views
from drivers.usb_grabber import UsbGrabber


def sim_mapping() -> dict[str, Any]:
    data = copy.deepcopy(read_yaml(config_path("sim.yaml")))
    data["imaging"]["image_size"] = [256, 224]
    return data


def test_sim_clock_moves_forward_only_and_wakes_sleepers() -> None:
    clock = SimClock()
    assert clock() == 0.0 and clock.advance(0.25) == 0.25
    with pytest.raises(ValueError, match="forward"):
        clock.advance(-0.1)
    woke: list[float] = []
    sleeper = threading.Thread(target=lambda: (clock.sleep(10.0), woke.append(clock())))
    sleeper.start()
    time.sleep(0.05)
    clock.advance(10.0)
    sleeper.join(timeout=2.0)
    assert woke == [10.25]            # woken by the simulated clock, not after 10 s of real time


def test_pose_history_interpolates_and_holds_at_the_ends() -> None:
    history = PoseHistory()
    history.append(0.0, np.zeros(3), np.array([1.0, 0.0, 0.0]))
    history.append(1.0, np.array([2.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    centroid, direction = history.at(0.5)
    np.testing.assert_allclose(centroid, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(direction, np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0))
    np.testing.assert_allclose(history.at(-1.0)[0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(history.at(5.0)[0], [2.0, 0.0, 0.0])


def test_perturbed_calibration_is_off_by_exactly_what_was_asked() -> None:
    views = biplane_views(image_size=(256, 224))
    calibration = perturbed_calibration(views, 0.1, 0.5, seed=3)
    for name, view in views.items():
        believed = calibration.views[name]
        turn = Rotation.from_matrix(believed.R @ view.R.T).magnitude()
        assert np.degrees(turn) == pytest.approx(0.1, abs=1e-9)
        assert np.linalg.norm(believed.t - view.t) == pytest.approx(0.5)
    exact = perturbed_calibration(views, 0.0, 0.0, seed=3)
    np.testing.assert_allclose(exact.views["p"].R, views["p"].R, atol=1e-12)


def test_turned_views_keep_the_isocentre_and_turn_the_sources() -> None:
    views = biplane_views(image_size=(256, 224))
    turned = turned_views(views, 90.0)
    for name in views:
        source = -views[name].R.T @ views[name].t
        turned_source = -turned[name].R.T @ turned[name].t
        np.testing.assert_allclose(turned_source, Rotation.from_euler("z", 90, degrees=True).apply(source), atol=1e-9)
        np.testing.assert_allclose(turned[name].project(np.zeros((1, 3))), views[name].project(np.zeros((1, 3))),
                                   atol=1e-9)


def test_amplifier_limits_come_from_the_coils_lowered_by_the_device_section() -> None:
    coils = load_coils()
    limits = amplifier_limits(AmplifierDevice(kind="loopback"), coils)
    assert limits.max_current_a == (12.0,) * 8 and limits.slew_a_per_s == (120.0,) * 8
    lowered = amplifier_limits(AmplifierDevice(kind="loopback", max_current_a=5.0, slew_a_per_s=50.0,
                                               watchdog_ms=100), coils)
    assert lowered.max_current_a == (5.0,) * 8 and lowered.slew_a_per_s == (50.0,) * 8
    assert lowered.watchdog_ms == 100


@pytest.mark.parametrize("separate_lab", [True, False], ids=["lab in a child process", "lab in process"])
def test_loopback_devices_sit_on_real_transports_and_share_one_world(separate_lab: bool) -> None:
    session = session_from_mapping(sim_mapping(), config_path("sim.yaml"))
    coils = load_coils()
    cores = os.sched_getaffinity(0)
    with open_devices(session, load_robots()[1], coils, separate_lab=separate_lab) as devices:
        sim = devices.sim
        assert sim is not None
        if separate_lab and len(cores) >= 2:
            # The lab's process on a core of its own (config simulation.lab_own_core), this one on the others.
            assert os.sched_getaffinity(sim.lab.process.pid) == {max(cores)}
            assert os.sched_getaffinity(0) == cores - {max(cores)}
        else:
            assert os.sched_getaffinity(0) == cores
        assert isinstance(devices.amplifier, Amplifier)
        assert devices.names["amplifier"].startswith("loopback amplifier on /dev/pts/")
        assert devices.names["ots"].startswith("loopback NDI tracker on /dev/pts/")
        assert all(isinstance(source, UsbGrabber) for source in devices.frames.sources.values())
        assert devices.amplifier.limits.watchdog_ms == 200
        # Frames flow only as simulated time passes; both planes come through pyusb and pair by number.
        sim.step(0.1)
        pair = devices.frames.next_pair(2.0)
        assert pair.p.image.shape == (224, 256) and pair.p.number == pair.q.number
        # Each plane streams over its modelled link in the driver's transfers: a 256 x 224 mono16 frame
        # (115 kB) is more than one, so the host checks the first while the second is on the wire.
        for plane, source in devices.frames.sources.items():
            assert sim.grabber_devices[plane].link_bytes_per_s is not None
            assert isinstance(source, UsbGrabber)
            assert source.link_stats.transfers >= 2 * source.counters.frames > 0
        # The world moves with the amplifier's MEASURED currents: none yet, so no field at the robot.
        np.testing.assert_allclose(sim.world.last_field_t, 0.0)
        with sim.real_time():
            devices.amplifier.enable()
        period = 1.0 / 30.0
        for _ in range(8):
            # A command every 33 ms of simulated time, as the loop does: the host's heartbeat runs in real
            # time and cannot feed the 200 ms watchdog across a jump of simulated time. The driver's slew
            # limit runs on the host's (real) clock too, so the commands are 33 ms apart in real time as
            # well: back to back (a world step takes 1-7 ms of wall time) the host ramps 2 A at 120 A/s of
            # WALL time and sends ~1.8 A by the eighth command on a quiet machine.
            sent = time.monotonic()
            result = devices.amplifier.set_currents([2.0] + [0.0] * 7)
            sim.step(period)
            time.sleep(max(0.0, sent + period - time.monotonic()))
        assert result.commanded_a[0] == 2.0 and result.slew_scale == 1.0   # the host's ramp is done
        np.testing.assert_allclose(sim.measured_currents_a()[0], 2.0, atol=0.02)
        expected = sim.world.field_at(sim.world.pose.centroid_mm, sim.measured_currents_a())
        np.testing.assert_allclose(sim.world.last_field_t, expected, rtol=0.02)
        assert np.linalg.norm(expected) > 1e-4
        samples = devices.ots.wait_for_frame(timeout_s=2.0) if devices.ots else []
        assert samples and not samples[0].missing
    # Closing shut the amplifier down (a lab in a child process keeps the fake's last state as it ends).
    final = sim.lab.final_amplifier_state if separate_lab else sim.amplifier_fake.snapshot()
    assert final is not None and not final.output_on
    if separate_lab:
        assert sim.lab.process.poll() is not None              # and ended the lab's process
    assert os.sched_getaffinity(0) == cores                    # this process's cores given back


def test_the_lab_keeps_the_scheduler_s_placement_when_the_config_says_so() -> None:
    data = sim_mapping()
    data["simulation"]["lab_own_core"] = False
    session = session_from_mapping(data, config_path("sim.yaml"))
    cores = os.sched_getaffinity(0)
    with open_devices(session, load_robots()[1], load_coils()) as devices:
        assert devices.sim is not None
        assert os.sched_getaffinity(devices.sim.lab.process.pid) == cores
        assert os.sched_getaffinity(0) == cores


def test_real_kinds_name_the_port_that_is_missing(tmp_path: Path) -> None:
    data = read_yaml(config_path("bench.yaml"))
    perturbed_calibration(biplane_views(), 0.0, 0.0, 0).save(tmp_path / "calibration.yaml")
    data["calibration"]["file"] = str(tmp_path / "calibration.yaml")
    data["devices"]["amplifier"]["port"] = str(tmp_path / "ttyNOPE")
    session = session_from_mapping(data, config_path("bench.yaml"))
    with pytest.raises(DeviceNotFoundError, match="ttyNOPE"):
        open_devices(session, load_robots()[1], load_coils())
