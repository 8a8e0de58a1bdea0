"""Build every device of a session from its config: real ports on a bench, loopback fakes in simulation.

This is the one production module allowed to import ``drivers.loopback``. Real kinds open real ports
(``drivers.transport.open_serial`` for the amplifier and the optical tracker, ``open_source`` for the
X-ray grabbers). ``kind: loopback`` builds the fakes over REAL transports - the amplifier fake and the
NDI tracker fake each on a pseudo-terminal (or a loopback TCP port), both X-ray planes rendered from
the simulated world and streamed through the fake pyusb backend into the real USB grabber driver (or
the in-process loopback grabber) - and the :class:`~appliance.sim_bench.SimBench` that ties them to one
simulated world on one simulated clock. By default (``separate_lab``) the world, the amplifier and
tracker fakes and the renderer run in one child process, as a bench's devices are other machines (on a
CPU core of its own where there are two or more, ``simulation.lab_own_core``: :mod:`appliance.core_placement`);
otherwise in this process, the renderer alone in a child unless ``separate_renderer`` is False. The
appliance side (drivers, orchestrator) is the same in every case.

Clocks in simulation: the world, the fakes and the frame loop run on :class:`~appliance.sim_bench.SimClock`, which only the
simulation harness advances. The host drivers keep the real monotonic clock for their link timeouts
and heartbeats (a lost reply is a real-time event on a real transport); the wall-clock loop latency is
measured on the host as on a bench.
"""
from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from appliance.config_io import read_yaml
from appliance.core_placement import give_lab_its_own_core
from appliance.errors import ConfigError
from appliance.geometry import Calibration, View
from appliance.robots import RobotSpec
from appliance.session_config import AmplifierDevice, OtsDevice, Session
from appliance.sim_bench import SimBench, SimClock
from drivers.amplifier import Amplifier, AmplifierLimits
from drivers.biplane_pairing import BiplanePairer, BiplaneStream
from drivers.frame_source import FrameSource, open_source
from drivers.ndi_tracker import NDITracker
from drivers.transport import open_serial
from firmware_protocol.amplifier import State

log = logging.getLogger(__name__)

#: USB identity of the loopback grabbers (the protocol's default VID:PID, serials XRG-P / XRG-Q).
_LOOPBACK_USB = "usb://{vid:04x}:{pid:04x}?serial=XRG-{plane_upper}&plane={plane}"
#: The loopback grabbers' link rate: a USB 3.0 SuperSpeed bulk endpoint's sustained rate (5 Gbit/s signalling,
#: ~350 MB/s of payload in practice), so a 768 x 672 mono16 frame takes ~3 ms on the wire and reaches the host
#: transfer by transfer, as from a real grabber, instead of all at once.
_LOOPBACK_USB_LINK_BYTES_PER_S = 350e6


@dataclass
class Devices:
    """Everything the frame loop talks to, opened and ready; ``close`` releases it all (idempotent)."""

    amplifier: Amplifier
    frames: BiplaneStream
    calibration: Calibration
    ots: NDITracker | None = None
    sim: SimBench | None = None
    names: dict[str, str] = field(default_factory=dict)   # device -> where it is (for messages and records)
    _closers: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)

    def close(self) -> None:
        self._closers.close()

    def __enter__(self) -> Devices:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- calibration --------------------------------------------------------------------------------------
def perturbed_calibration(true_views: dict[str, Any], rotation_deg: float, translation_mm: float,
                          seed: int, dark_level: float | None = None) -> Calibration:
    """The simulated views as the appliance believes them: each view's pose turned by ``rotation_deg``
    about a random axis and moved by ``translation_mm`` in a random direction (seeded)."""
    rng = np.random.default_rng(seed)
    views = {}
    for name, view in true_views.items():
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rotation_deg)).as_matrix()
        shift = rng.normal(size=3)
        shift *= translation_mm / np.linalg.norm(shift)
        views[name] = View(name, view.K, view.dist, turn @ view.R, view.t + shift, view.image_size)
    metadata: dict[str, Any] = {
        "source": "nominal views of the simulated biplane system",
        "perturbation": {"rotation_deg": rotation_deg, "translation_mm": translation_mm, "seed": seed}}
    if dark_level is not None:
        metadata["detector"] = {"dark_level": float(dark_level)}   # as a dark-frame calibration would give
    return Calibration.from_views(views["p"], views["q"], metadata)


def turned_views(views: dict[str, Any], azimuth_deg: float) -> dict[str, Any]:
    """The biplane system turned about the world's vertical axis by ``azimuth_deg`` (sources and detectors
    move together around the isocentre: ``R' = R Rz^T``, ``t`` unchanged)."""
    if azimuth_deg == 0.0:
        return views
    from drivers.loopback.xray_render import TrueView

    turn = Rotation.from_euler("z", azimuth_deg, degrees=True).as_matrix()
    return {name: TrueView(name, v.K, v.dist, v.R @ turn.T, v.t, v.image_size) for name, v in views.items()}


# -- amplifier ----------------------------------------------------------------------------------------
def amplifier_limits(device: AmplifierDevice, coils: Any) -> AmplifierLimits:
    """Per-channel limits set on the amplifier: the coils' limits, lowered by the device section's."""
    cap = device.max_current_a if device.max_current_a is not None else float("inf")
    slew = device.slew_a_per_s if device.slew_a_per_s is not None else coils.limits.max_slew_a_per_s
    return AmplifierLimits(tuple(min(c.max_current_a, cap) for c in coils.coils), (slew,) * len(coils.coils),
                           device.watchdog_ms)


def _connect_amplifier(url: str, device: AmplifierDevice, coils: Any) -> Amplifier:
    port = open_serial(url, baudrate=device.baudrate, timeout=0.005)
    amplifier = Amplifier(port, ack_timeout_s=device.ack_timeout_ms / 1000.0, retries=device.retries)
    try:
        if amplifier.info.channels != len(coils.coils):
            raise ConfigError(f"the amplifier on {url} has {amplifier.info.channels} channels but the coils file "
                              f"configures {len(coils.coils)} coils")
        if amplifier.state is State.ENABLED:
            log.warning("amplifier on %s was left enabled by a previous session: disabling it", url)
            amplifier.disable()
        try:
            amplifier.configure_limits(amplifier_limits(device, coils))
        except ValueError as err:
            raise ConfigError(f"devices.amplifier: limits do not fit the amplifier on {url}: {err}") from err
    except BaseException:
        amplifier.close()
        raise
    return amplifier


def _amplifier_fake_config(device: AmplifierDevice, coils: Any) -> Any:
    """The amplifier fake's ratings and coil physics for the configured coils."""
    from drivers.loopback.amplifier_fake import FakeAmplifierConfig

    resistance = float(np.mean([c.resistance_ohm for c in coils.coils]))
    inductance = float(np.mean([c.inductance_h for c in coils.coils]))
    max_current = min(max(c.max_current_a for c in coils.coils), device.rated_current_a)
    return FakeAmplifierConfig(
        channels=len(coils.coils), rated_current_a=device.rated_current_a, max_current_a=max_current,
        slew_a_per_s=coils.limits.max_slew_a_per_s, watchdog_ms=device.watchdog_ms,
        coil_resistance_ohm=resistance, coil_inductance_h=max(inductance, 1e-6),
        thermal_resistance_k_per_w=device.thermal_resistance_k_per_w)


def _served(fake: Any, link: str, clock: SimClock) -> Any:
    from drivers.loopback.serve import PtyServer, TcpServer

    return TcpServer(fake, clock=clock) if link == "tcp" else PtyServer(fake, clock=clock)


def _server_url(server: Any, link: str) -> str:
    return server.path if link == "pty" else server.address


def _shutdown_in_real_time(bench_sim: SimBench, amplifier: Amplifier) -> None:
    with bench_sim.real_time():
        amplifier.shutdown()


# -- optical tracker ----------------------------------------------------------------------------------
def _connect_ots(url: str, device: OtsDevice, rom: bytes | str, rom_name: str) -> NDITracker:
    port = open_serial(url, baudrate=9600, timeout=0.05)
    tracker = NDITracker(port)
    try:
        tracker.connect(baudrate=device.baudrate)
        tracker.load_tool(rom, rom_name)
        tracker.start()
        tracker.start_streaming(device.mode, device.rate_hz)
    except BaseException:
        tracker.close()
        raise
    return tracker


# -- the whole session --------------------------------------------------------------------------------
def open_devices(session: Session, robot: RobotSpec, coils: Any, *, separate_lab: bool = True,
                 separate_renderer: bool = True) -> Devices:
    """Open (or, in simulation, build and open) every device of ``session``; the frame stream is started.

    In simulation ``separate_lab`` puts the simulated lab - world, amplifier fake, tracker fake and the
    X-ray renderer - in one child process (:mod:`drivers.loopback.lab_process`), as a bench's devices are
    other machines; this process keeps what a bench's host has: the amplifier's and the tracker's ptys
    and the grabbers' USB backend (the frames rendered in the child, through shared memory). The factory
    starts the child and the devices' close ends it. False keeps the lab in this process (for tests and
    comparisons), and then ``separate_renderer`` runs the X-ray renderer in a child process
    (:mod:`drivers.loopback.render_process`; same images), False in this one."""
    config = session.config
    stack = contextlib.ExitStack()
    try:
        if config.is_simulation:
            devices = _open_simulation(session, robot, coils, stack, separate_lab, separate_renderer)
        else:
            devices = _open_bench(session, coils, stack)
    except BaseException:
        stack.close()
        raise
    devices._closers = stack
    return devices


def _open_bench(session: Session, coils: Any, stack: contextlib.ExitStack) -> Devices:
    config = session.config
    assert config.calibration.file is not None
    calibration = Calibration.load(session.resolve(config.calibration.file))
    amp = config.devices.amplifier
    assert amp.port is not None
    amplifier = _connect_amplifier(amp.port, amp, coils)
    stack.callback(amplifier.shutdown)
    xray = config.devices.xray
    assert xray.sources is not None
    sources = {plane: open_source(url) for plane, url in xray.sources.items()}
    frames = _stream(sources, config)
    stack.callback(frames.stop)
    names = {"amplifier": amp.port, "xray_p": xray.sources["p"], "xray_q": xray.sources["q"]}
    ots = None
    if config.devices.ots.kind == "serial":
        device = config.devices.ots
        assert device.port is not None and device.rom is not None
        rom = session.resolve(device.rom)
        ots = _connect_ots(device.port, device, str(rom), rom.name)
        stack.callback(ots.close)
        names["ots"] = device.port
    return Devices(amplifier, frames, calibration, ots, None, names)


def _stream(sources: dict[str, FrameSource], config: Any) -> BiplaneStream:
    xray = config.devices.xray
    pairer = BiplanePairer(match=xray.match, mode="latest", max_skew_s=xray.max_skew_ms / 1000.0)
    stream = BiplaneStream(sources, pairer, poll_s=0.05)
    stream.start()
    return stream


def _robot_mapping(robot: RobotSpec) -> dict[str, float]:
    return {"length_mm": robot.length_mm, "diameter_mm": robot.diameter_mm, "remanence_t": robot.remanence_t,
            "magnet_volume_mm3": robot.magnet_volume_mm3, "density_kg_m3": robot.density_kg_m3}


def _open_simulation(session: Session, robot: RobotSpec, coils: Any, stack: contextlib.ExitStack,
                     separate_lab: bool = False, separate_renderer: bool = True) -> Devices:
    from drivers.loopback.loopback_grabber import LoopbackFrameSource, LoopbackScene, make_usb_backend
    from drivers.loopback.world import SimWorld
    from drivers.loopback.xray_render import (
        BiplaneRenderer,
        ImagingSettings,
        RobotBody,
        VesselPhantom,
        biplane_views,
    )
    from firmware_protocol import usb_grabber as usb_proto

    config = session.config
    sim, imaging = config.simulation, config.imaging
    clock = SimClock()
    coils_data = read_yaml(session.coils_path)
    vessel_data = read_yaml(session.vessel_path)
    if not isinstance(vessel_data, dict) or "vessel" not in vessel_data:
        raise ConfigError(f"{session.vessel_path}: simulation needs a 'vessel' section (the phantom)")
    try:
        world = SimWorld.from_config(coils_data, vessel_data["vessel"], robot=_robot_mapping(robot),
                                     world=vessel_data.get("world") or {}, seed=sim.seed)
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"{session.vessel_path}: cannot build the simulated world: {err}") from err

    true_views = turned_views(biplane_views(sod_mm=imaging.sod_mm, sdd_mm=imaging.sdd_mm, fov_mm=imaging.fov_mm,
                                            image_size=imaging.image_size, separation_deg=imaging.separation_deg,
                                            elevation_deg=imaging.elevation_deg), imaging.azimuth_deg)
    body = RobotBody(robot.length_mm, robot.diameter_mm, robot.tip_angle_deg, robot.attenuation_per_mm)
    phantom = VesselPhantom(world.vessel.sample(1.0), world.vessel.radius_mm, imaging.vessel_attenuation_per_mm)
    detector = ImagingSettings(photons_per_pixel=imaging.photons_per_pixel)
    renderer: Any = BiplaneRenderer(true_views, body, vessel=phantom, seed=sim.seed, settings=detector)
    amp_device, ots_device = config.devices.amplifier, config.devices.ots
    amp_config = _amplifier_fake_config(amp_device, coils)
    lab: Any
    if separate_lab:
        from drivers.loopback.lab_process import LabProcess

        lab = LabProcess(clock=clock, world=world, amplifier_config=amp_config, amplifier_link=amp_device.link,
                         renderer=renderer, substep_s=sim.substep_ms / 1000.0,
                         ots={"link": ots_device.link, "seed": sim.seed} if ots_device.kind == "loopback" else None)
        stack.callback(lab.close)
        if sim.lab_own_core:
            placement = give_lab_its_own_core(lab.process.pid)
            if placement is not None:
                stack.callback(placement.restore)
                log.info("simulated lab on core %d, the appliance on cores %s", placement.lab_core,
                         sorted(placement.host_cores))
        amp_url, ots_url = lab.amplifier_url, lab.ots_url
    else:
        from drivers.loopback.amplifier_fake import FakeAmplifier
        from drivers.loopback.lab import LoopbackLab

        if separate_renderer:
            from drivers.loopback.render_process import RenderProcess

            # The fluoroscope is another device on a bench: its rendering must not take the loop's GIL.
            renderer = RenderProcess(renderer)
            stack.callback(renderer.close)
        fake = FakeAmplifier(amp_config)
        server = _served(fake, amp_device.link, clock)
        stack.callback(server.close)
        # The servers are closed by the stack (each once: a pty's descriptors must not be closed twice).
        lab = LoopbackLab(clock, world, fake, server, sim.substep_ms / 1000.0, renderer=renderer)
        amp_url, ots_url = _server_url(server, amp_device.link), None
        if ots_device.kind == "loopback":
            from drivers.loopback.ots_fake import NdiTrackerFake, NoiseModel

            ots_fake = NdiTrackerFake(lab.tool_poses, noise=NoiseModel(seed=sim.seed))
            ots_server = _served(ots_fake, ots_device.link, clock)
            stack.callback(ots_server.close)
            lab.attach_tracker(ots_fake, ots_server)
            ots_url = _server_url(ots_server, ots_device.link)
    bench_sim = SimBench(clock, lab, true_views)
    if config.calibration.source == "nominal":
        p = config.calibration.perturbation
        calibration = perturbed_calibration(true_views, p.rotation_deg, p.translation_mm, p.seed,
                                            detector.dark_level)
    else:
        assert config.calibration.file is not None
        calibration = Calibration.load(session.resolve(config.calibration.file))

    # The scene hands the exposure's time to the lab, which renders the robot as it was then.
    scene = LoopbackScene(lab.exposures, float, rate_hz=imaging.fps, exposure_s=imaging.exposure_ms / 1000.0)
    bench_sim.scene = scene
    xray = config.devices.xray
    if xray.link == "usb":
        backend = make_usb_backend(scene, realtime=True, seed=sim.seed, clock=clock.released, sleep=clock.sleep,
                                   link_bytes_per_s=_LOOPBACK_USB_LINK_BYTES_PER_S)
        urls = {plane: _LOOPBACK_USB.format(vid=usb_proto.VENDOR_ID, pid=usb_proto.PRODUCT_ID,
                                            plane=plane, plane_upper=plane.upper()) for plane in ("p", "q")}
        sources = {plane: open_source(url, backend=backend) for plane, url in urls.items()}
        bench_sim.grabber_devices = {plane: backend.device(f"XRG-{plane.upper()}") for plane in ("p", "q")}
    else:
        urls = {plane: f"loopback grabber, plane {plane}" for plane in ("p", "q")}
        # Each plane its own random stream: drops and jitter must not be identical on p and q.
        sources = {plane: LoopbackFrameSource(scene, plane, clock=clock.released, sleep=clock.sleep,
                                              seed=sim.seed + index)
                   for index, plane in enumerate(("p", "q"))}
    bench_sim.frame_sources = sources
    # Started at simulated t = 0, so the grabbers' exposure clock is the world's clock.
    frames = _stream(sources, config)
    stack.callback(frames.stop)

    with bench_sim.real_time():
        amplifier = _connect_amplifier(amp_url, amp_device, coils)
    # Shut down (ramp to zero, output off) before the servers close: the stack unwinds in reverse.
    stack.callback(_shutdown_in_real_time, bench_sim, amplifier)
    names = {"amplifier": f"loopback amplifier on {amp_url}", "xray_p": urls["p"], "xray_q": urls["q"]}

    ots = None
    if ots_url is not None:
        from drivers.loopback.ots_fake import synthetic_rom

        ots = _connect_ots(ots_url, ots_device, synthetic_rom("ROBOT-HOLDER"), "robot-holder (synthetic)")
        stack.callback(ots.close)
        names["ots"] = f"loopback NDI tracker on {ots_url}"
    log.info("simulated bench: %s", ", ".join(f"{k}: {v}" for k, v in names.items()))
    return Devices(amplifier, frames, calibration, ots, bench_sim, names)
