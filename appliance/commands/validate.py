"""``appliance validate``: an OTS validation session (the seed paper's Table 1 and Fig. 4) for one or all robots.

    appliance validate --config config/sim.yaml --robot all --postures 3 --samples 30 --out validation/

For each robot and posture, ``--samples`` biplane pairs come through the session's frame stream and the
holder tool's poses through the NDI tracker driver; the tracker's reference is mapped into the X-ray
frame with the X-ray <-> OTS registration (saved with the calibration, or measured at the start with the
fiducial phantom and the tracked pointer) and the holder calibration (``--holder``). The report goes to
``--out``: ``table.md`` / ``table.csv`` (Table 1), ``boxplots.png`` (Fig. 4), ``samples.csv`` (every
sample) and ``summary.json``. Progress goes to stderr.

In simulation (every device ``kind: loopback``) the lab's hands are the simulated world's
(:class:`SimulatedLab` below): it pivots and touches with a simulated pointer seen by the loopback NDI
tracker, puts a fiducial phantom of steel beads in the rendered field of view, and clamps the robot in
postures along the vessel phantom, tilted from its centreline by seeded angles. The holder is then
built exactly as designed (``world.tool_in_robot`` of the vessel file). On a bench an operator is
prompted for each step; the pointer's tool definition is ``--pointer-rom`` and the fiducial count
``--fiducials`` (unless the calibration file carries a registration).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
from appliance.commands._common import count

NAME = "validate"
HELP = "OTS validation session: per robot and posture, errors of the recognised posture against the tracker"

#: Simulated fiducial phantom: steel beads (radius, attenuation /mm) in an asymmetric layout (mm, phantom
#: frame), so that every bead has its own set of distances to the others.
BEAD_RADIUS_MM = 1.0
BEAD_ATTENUATION_PER_MM = 2.0
FIDUCIAL_LAYOUT_MM = np.array([
    [0.0, 0.0, 0.0], [31.0, 6.0, -9.0], [-24.0, 13.0, 7.0], [9.0, -27.0, 14.0],
    [-13.0, -21.0, -23.0], [19.0, 26.0, 21.0], [-33.0, -4.0, 26.0], [23.0, -14.0, -28.0]])
#: The simulated pointer: tip in the pointer's frame (mm) and how far it is swung while pivoting.
POINTER_TIP_MM = np.array([1.2, -0.7, -151.5])
PIVOT_SWING_DEG = 25.0


class SimulatedLab:
    """The lab's hands in simulation: act on the loopback world behind the devices (see the module docstring),
    through the simulation bench (the world and the tracker fake may be in the simulated lab's own process:
    what is handed over is data, the pointer's motion included)."""

    name = "simulation (loopback world)"

    def __init__(self, devices: Any, robot: Any, seed: int, max_tilt_deg: float = 35.0) -> None:
        from scipy.spatial.transform import Rotation

        bench = devices.sim
        if bench is None or devices.ots is None or not devices.names.get("ots", "").startswith("loopback"):
            raise ValueError("SimulatedLab needs a simulation session with a loopback tracker")
        self.bench = bench
        self.world = bench.world
        self.robot = robot
        self.rng = np.random.default_rng([seed, robot.id])
        self.max_tilt_deg = max_tilt_deg
        self._rotation = Rotation
        self._vessel = self.world.vessel            # geometry only (a copy when the world is in another process)
        self._fiducials_world: np.ndarray | None = None
        ots_from_world = self.world.ots_from_world
        self._to_ots = lambda x: ots_from_world.apply(x)
        self._ots_rotation = ots_from_world.rotation
        bench.use_pointer()          # the tracker sees the pointer as tool 1 (put away for now)

    def _hold_pointer(self, tip_ots: np.ndarray, rotation: np.ndarray) -> None:
        from drivers.loopback.ots_poses import HeldPose

        self.bench.set_pointer(HeldPose(rotation, tip_ots - rotation @ POINTER_TIP_MM))

    # -- Lab ---------------------------------------------------------------------------------------------
    def wait(self, seconds: float) -> None:
        # The robot is clamped in its holder: the world's dynamics do not act on it, only time passes.
        self.bench.pass_time(seconds)

    def pointer_rom(self) -> tuple[bytes | str, str]:
        from drivers.loopback.ots_fake import synthetic_rom
        return synthetic_rom("POINTER"), "pointer (synthetic)"

    def start_pivoting(self) -> None:
        from drivers.loopback.ots_poses import PivotingPose

        pivot = self._to_ots(self._vessel.point_at(0.5 * self._vessel.length_mm) + [0.0, 0.0, -40.0])
        self.bench.set_pointer(PivotingPose(pivot, self._ots_rotation, math.radians(PIVOT_SWING_DEG), POINTER_TIP_MM,
                                            self.bench.clock.now()))

    def place_fiducials(self) -> int:
        from drivers.loopback.xray_render import BiplaneRenderer

        centre = self._vessel.sample(1.0).mean(axis=0)
        turn = self._rotation.from_euler("xyz", [12.0, -8.0, 25.0], degrees=True).as_matrix()
        self._fiducials_world = FIDUCIAL_LAYOUT_MM @ turn.T + centre
        # The fiducial phantom takes the vessel phantom's place on the table (bead detection wants a smooth
        # background, as with a calibration cube); the robot leaves the field of view first, as the
        # phantom's renderer draws no robot.
        self.bench.hide_robot(True)
        self.bench.replace_renderer(BiplaneRenderer(
            self.bench.true_views, None, vessel=None,
            beads=(self._fiducials_world, BEAD_RADIUS_MM, BEAD_ATTENUATION_PER_MM),
            settings=self.bench.renderer_settings, seed=1))
        self.bench.set_pointer(None)
        return len(FIDUCIAL_LAYOUT_MM)

    def touch_fiducial(self, index: int) -> None:
        assert self._fiducials_world is not None
        tilt = self._rotation.from_rotvec(self.rng.normal(0.0, math.radians(10.0), 3)).as_matrix()
        self._hold_pointer(self._to_ots(self._fiducials_world[index]), self._ots_rotation @ tilt)

    def clear_fiducials(self) -> None:
        self.bench.restore_renderer()
        self.bench.hide_robot(False)
        self.bench.set_pointer(None)
        self._fiducials_world = None

    def place_robot(self, posture: int, count: int) -> None:
        vessel = self._vessel
        margin = min(self.robot.length_mm, 0.25 * vessel.length_mm)
        s = margin + (vessel.length_mm - 2.0 * margin) * (posture + 0.5) / count
        tangent = vessel.tangent_at(s)
        # Tilt the axis off the centreline about a random perpendicular axis; either end may lead.
        normal = np.cross(tangent, self.rng.normal(size=3))
        normal /= np.linalg.norm(normal)
        tilt = math.radians(self.rng.uniform(0.3, 1.0) * self.max_tilt_deg)
        direction = self._rotation.from_rotvec(normal * tilt).apply(tangent) * self.rng.choice([-1.0, 1.0])
        # Frames exposed before now show the old pose, frames after it the new one.
        self.bench.place_robot(vessel.point_at(s), direction)

    def true_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        pose = self.bench.pose()
        return pose.centroid_mm, pose.direction


def session_for_robot(session: Any, robot: Any, folder: Path) -> Any:
    """The simulation session with a vessel phantom the robot fits in: the simulated world refuses a robot as
    wide as the lumen (robot #6 is 5 mm across, the default lumen 5 mm). The robot is clamped in its holder,
    so the phantom is only the images' background; its lumen is widened to 1.6 diameters when needed."""
    import yaml

    from appliance.config_io import read_yaml
    from appliance.session_config import Session

    data = read_yaml(session.vessel_path)
    vessel = data.get("vessel") if isinstance(data, dict) else None
    if not isinstance(vessel, dict) or 2.0 * float(vessel.get("radius_mm", 0.0)) > 1.2 * robot.diameter_mm:
        return session
    vessel["radius_mm"] = 0.8 * robot.diameter_mm
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"vessel_robot{robot.id}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return Session(session.config.model_copy(update={"vessel": str(path)}), session.source)


def _robot_choice(text: str) -> str:
    if text == "all" or all(part.strip().isdigit() for part in text.split(",")):
        return text
    raise argparse.ArgumentTypeError(f"expected a robot number, numbers separated by commas, or 'all', got {text!r}")





def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, metavar="YAML", help="session file (default: config/sim.yaml)")
    parser.add_argument("--robot", type=_robot_choice, metavar="N|all",
                        help="robot number of the catalogue (or several: 1,4), or 'all' (default: all in simulation, "
                             "the session's robot on a bench)")
    parser.add_argument("--postures", type=count, default=3, metavar="K", help="postures per robot (default 3)")
    parser.add_argument("--samples", type=count, default=30, metavar="N",
                        help="biplane pairs per posture (default 30, the protocol's minimum)")
    parser.add_argument("--out", type=Path, default=Path("validation"), metavar="DIR",
                        help="report folder (default ./validation)")
    parser.add_argument("--holder", type=Path, metavar="YAML",
                        help="holder calibration: tool_in_robot (default in simulation: the holder as designed)")
    parser.add_argument("--pointer-rom", type=Path, metavar="ROM", help="bench: the tracked pointer's tool definition")
    parser.add_argument("--fiducials", type=count, metavar="N", help="bench: fiducials on the registration phantom")


def _holder(args: argparse.Namespace, session: Any) -> Any:
    from appliance.config_io import read_yaml
    from appliance.errors import ConfigError
    from appliance.validation.reference import load_holder, transform_from_mapping

    if args.holder is not None:
        return load_holder(args.holder)
    if not session.config.is_simulation:
        raise ConfigError("a bench session needs --holder YAML (the tracked tool in the robot frame)")
    world = (read_yaml(session.vessel_path) or {}).get("world") or {}
    return transform_from_mapping(world.get("tool_in_robot") or {}, f"{session.vessel_path.name}: world.tool_in_robot")


def run(args: argparse.Namespace) -> int:
    from appliance.control import load_coils
    from appliance.errors import ConfigError
    from appliance.robots import load_robots, select_robot
    from appliance.session_config import load_session
    from appliance.validation.lab import OperatorLab
    from appliance.validation.report import write_report
    from appliance.validation.session import Plan, run_validation

    def say(message: str) -> None:
        print(f"validate: {message}", file=sys.stderr, flush=True)

    session = load_session(args.config)
    config = session.config
    catalogue = load_robots(session.robots_path)
    choice = args.robot or ("all" if config.is_simulation else str(config.robot.id))
    robots = [catalogue[k] for k in sorted(catalogue)] if choice == "all" else \
        [select_robot(catalogue, int(part)) for part in dict.fromkeys(choice.split(","))]
    plan = Plan(postures=args.postures, samples=args.samples)
    holder = _holder(args, session)
    coils = load_coils(session.coils_path)

    if config.is_simulation:
        def lab_factory(devices: Any, robot: Any) -> Any:
            return SimulatedLab(devices, robot, seed=config.simulation.seed)
    else:
        def lab_factory(devices: Any, robot: Any) -> Any:
            from appliance.registration import registration_from_calibration
            if registration_from_calibration(devices.calibration) is None and not (args.pointer_rom and args.fiducials):
                raise ConfigError("the calibration has no X-ray -> OTS registration: give --pointer-rom and "
                                  "--fiducials to register with the fiducial phantom")
            return OperatorLab(str(args.pointer_rom), args.fiducials or 0)

    say(f"{len(robots)} robot(s) x {plan.postures} postures x {plan.samples} samples from {session.source}")
    adapt = None
    widened: list[int] = []
    if config.is_simulation:
        def adapt(robot: Any) -> Any:
            adapted = session_for_robot(session, robot, args.out / "sim")
            if adapted is not session:
                widened.append(robot.id)
            return adapted
    result = run_validation(session, robots, plan, lab_factory, holder, coils, progress=say, session_for=adapt)
    if widened:
        result.notes.append(f"robots {widened}: the simulated vessel phantom was widened to 1.6 robot diameters "
                            f"(the robot is as wide as its lumen; files in sim/)")
    paths = write_report(args.out, result)
    print(paths["table_md"].read_text(encoding="utf-8"))
    for key in ("table_md", "table_csv", "boxplots", "samples", "summary"):
        print(f"{key:>10}: {paths[key]}")
    return 0
