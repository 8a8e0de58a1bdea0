"""The simulated lab in a child process: the same world as in-process, reached through real transports; its
death seen by the parent; no orphan child."""
from __future__ import annotations

import copy
import os
import time

import numpy as np
import pytest

from appliance.config_io import config_path, read_yaml
from drivers.amplifier import Amplifier
from drivers.errors import DeviceError
from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig
from drivers.loopback.lab import LabClock, LoopbackLab
from drivers.loopback.lab_process import LabProcess, LabProcessError
from drivers.loopback.serve import PtyServer
from drivers.loopback.world import SimWorld
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody, biplane_views
from drivers.transport import open_serial

AMPLIFIER = FakeAmplifierConfig(channels=8, rated_current_a=12.0, max_current_a=12.0, slew_a_per_s=120.0,
                                coil_resistance_ohm=1.95, coil_inductance_h=0.052)
SMALL = {"fov_mm": (40.0, 35.0), "image_size": (64, 56)}


def make_world() -> SimWorld:
    vessel = read_yaml(config_path("vessel.yaml"))
    return SimWorld.from_config(read_yaml(config_path("coils.yaml")), vessel["vessel"], world=vessel.get("world"),
                                seed=4)


def make_renderer() -> BiplaneRenderer:
    return BiplaneRenderer(biplane_views(**SMALL), RobotBody(10.0, 2.0, 20.0, 1.0), seed=5)


def drive(lab: object, url: str) -> list[np.ndarray]:
    """Enable the amplifier behind ``url``, command 2 A on coil 0, step the lab 1/6 s in frame steps (inside
    the 200 ms watchdog: no heartbeat here); the measured currents and the robot's centroid after each step."""
    amplifier = Amplifier(open_serial(url, timeout=0.005), heartbeat_period_s=0.0)
    try:
        amplifier.enable()
        time.sleep(0.05)      # the driver's slew limit runs on the wall clock: let it allow the 2 A at once
        amplifier.set_currents([2.0] + [0.0] * 7)
        seen = []
        for _ in range(5):
            pose = lab.step(1.0 / 30.0)                     # type: ignore[attr-defined]
            seen.append(np.concatenate([lab.measured_currents_a(), pose.centroid_mm]))   # type: ignore[attr-defined]
        return seen
    finally:
        amplifier.close()


def test_the_child_lab_moves_the_same_world_as_the_lab_in_process() -> None:
    world = make_world()
    in_process = LoopbackLab(LabClock(), copy.deepcopy(world), FakeAmplifier(AMPLIFIER),
                             None, substep_s=0.005)
    in_process.amplifier_server = PtyServer(in_process.amplifier_fake, clock=in_process.clock)
    try:
        mine = drive(in_process, in_process.amplifier_server.path)
    finally:
        in_process.close()
    clock = LabClock()      # the harness's clock: now() and advance_to() are all the proxy needs
    with LabProcess(clock=clock, world=world, amplifier_config=AMPLIFIER, amplifier_link="pty",
                    renderer=make_renderer(), substep_s=0.005) as lab:
        assert lab.process is not None and lab.process.pid != os.getpid()
        assert lab.amplifier_url.startswith("/dev/pts/") and lab.ots_url is None
        theirs = drive(lab, lab.amplifier_url)
        assert clock.now() == pytest.approx(1 / 6) and lab.call("", "pose").t_s == pytest.approx(1 / 6)
        # The proxies read and call in the child.
        np.testing.assert_allclose(lab.world.last_field_t,
                                   lab.world.field_at(lab.pose().centroid_mm, lab.measured_currents_a()), rtol=0.02)
        assert lab.amplifier_fake.snapshot().output_on
        assert lab.current_trace and lab.current_trace[-1][0] == pytest.approx(1 / 6)
    assert mine[-1][0] == pytest.approx(2.0, abs=0.02)
    np.testing.assert_allclose(np.array(theirs), np.array(mine), rtol=1e-9, atol=1e-12)


def test_the_child_renders_the_exposure_at_a_time_as_the_world_was_then() -> None:
    world = make_world()
    local = LoopbackLab(LabClock(), copy.deepcopy(world), FakeAmplifier(AMPLIFIER), None, substep_s=0.005)
    local.amplifier_server = PtyServer(local.amplifier_fake, clock=local.clock)
    renderer = make_renderer()
    with LabProcess(clock=LabClock(), world=world, amplifier_config=AMPLIFIER, amplifier_link="pty",
                    renderer=copy.deepcopy(renderer), substep_s=0.005) as lab:
        for _ in range(3):
            local.step(0.05)
            lab.step(0.05)
        try:
            for t in (0.02, 0.11, 0.15):
                mine = renderer.render(local.exposure_pose(t))
                theirs = lab.exposures.render(t)
                for plane in ("p", "q"):
                    np.testing.assert_array_equal(theirs.images[plane], mine.images[plane])   # noise included
                np.testing.assert_allclose(theirs.pose.centroid_mm, mine.pose.centroid_mm)
            lab.hide_robot(True)
            assert lab.exposures.render(0.15).pose is None and not lab.exposures.render(0.15).truth
        finally:
            local.close()


def test_the_parent_sees_the_child_die_and_so_does_the_amplifier_driver() -> None:
    with LabProcess(clock=LabClock(), world=make_world(), amplifier_config=AMPLIFIER, amplifier_link="pty",
                    renderer=make_renderer(), substep_s=0.005) as lab:
        amplifier = Amplifier(open_serial(lab.amplifier_url, timeout=0.005), heartbeat_period_s=0.0)
        try:
            amplifier.enable()
            lab.step(0.1)
            assert lab.process is not None
            lab.process.kill()
            with pytest.raises(LabProcessError, match="ended .killed by signal 9.: world, amplifier and tracker"):
                lab.step(0.1)
            assert isinstance(LabProcessError("x"), DeviceError)    # the harness stops on a device error
            with pytest.raises(DeviceError):
                amplifier.set_currents([1.0] + [0.0] * 7)           # the pty went with the child
        finally:
            amplifier.close()
        assert lab.current_trace and lab.current_trace[-1][0] == pytest.approx(0.1)   # kept by the parent
    assert not os.path.exists(lab.shm_path)


@pytest.mark.parametrize("how", ["sigint", "sigkill"])
def test_the_child_does_not_outlive_its_parent(child_outlives_no_parent, how: str) -> None:
    """Ctrl-C (SIGINT to the process group) or a killed parent: the lab child ends with it, ptys and frames
    file gone."""
    child_outlives_no_parent(f"""
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_lab_process import AMPLIFIER, make_renderer, make_world
        from drivers.loopback.lab import LabClock
        from drivers.loopback.lab_process import LabProcess
        device = LabProcess(clock=LabClock(), world=make_world(), amplifier_config=AMPLIFIER, amplifier_link="pty",
                            renderer=make_renderer(), substep_s=0.005, ots={{"link": "pty", "seed": 1}})
        device.step(0.05)
    """, how, "lab")
