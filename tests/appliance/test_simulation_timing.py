"""The harness's timing: each step of the loop acts on the pair exposed for it, never on an older one."""
from __future__ import annotations

import copy

import pytest

from appliance.config_io import config_path, read_yaml
from appliance.session_config import session_from_mapping
from appliance.simulation import Simulation


def test_every_step_recognises_the_pair_exposed_for_it_and_the_renderer_is_another_process() -> None:
    data = copy.deepcopy(read_yaml(config_path("sim.yaml")))
    data["imaging"]["image_size"] = [256, 224]
    data["recording"]["enabled"] = False
    data["simulation"] = {"seed": 2, "settle_ms": 100}
    # Not a test of the link's timing: on a loaded 2-core machine the simulated lab's process answers later
    # than sim.yaml's 3 x 50 ms ack time-out.
    data["devices"]["amplifier"] = {**data["devices"]["amplifier"], "ack_timeout_ms": 1000.0}
    session = session_from_mapping(data, config_path("sim.yaml"))
    fps, latency_s = data["imaging"]["fps"], data["simulation"].get("loop_latency_ms", 25) / 1000.0
    with Simulation(session) as sim:
        renderer = sim.bench.scene.renderer
        assert renderer.process.pid is not None and renderer.process.poll() is None
        result = sim.run(1.0)
    assert renderer.process.poll() is not None                    # closing the simulation ended it
    frames = [r for r in result.reports if r.frame is not None]
    assert len(frames) >= 25
    for report in frames:
        # The step at n / fps + latency acts on pair n (a pair older by one frame period would mean the
        # loop runs a frame behind the latency the session models).
        assert report.t_s == pytest.approx(report.frame / fps + latency_s, abs=1e-6)
    assert [r.frame for r in frames] == list(range(frames[0].frame, frames[0].frame + len(frames)))
