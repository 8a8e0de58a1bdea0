"""Safety state machine: hold, zero, resume, latched stops, speed limit; every transition recorded."""
from __future__ import annotations

import numpy as np
import pytest

from appliance.control import Mode, SafetySettings, SafetySupervisor
from appliance.errors import ConfigError
from appliance.config_io import validate_model

FIELD = np.array([0.0, 1.5e-3, 0.0])
FORCE = np.array([0.0, 4e-6, 0.0])


def _frames(supervisor: SafetySupervisor, tracked: list[bool], start: int = 0) -> list[Mode]:
    return [supervisor.update((start + i) / 30, ok, FIELD, FORCE).mode for i, ok in enumerate(tracked)]


def test_tracking_loss_holds_then_zeroes_then_resumes() -> None:
    supervisor = SafetySupervisor(SafetySettings(hold_after_lost_frames=2, zero_after_lost_frames=5,
                                                 resume_after_frames=2, hold_field_t=0.4e-3))
    assert _frames(supervisor, [True, True]) == [Mode.RUN, Mode.RUN]
    modes = _frames(supervisor, [False] * 7, start=2)
    assert modes == [Mode.RUN, Mode.RUN, Mode.HOLD, Mode.HOLD, Mode.HOLD, Mode.ZERO, Mode.ZERO]
    held = SafetySupervisor(SafetySettings(hold_after_lost_frames=0, hold_field_t=0.4e-3))
    held.update(0.0, True, FIELD, FORCE)
    decision = held.update(0.1, False, None, None)
    assert decision.mode is Mode.HOLD and not np.any(decision.force_N)
    assert np.allclose(decision.field_T, [0.0, 0.4e-3, 0.0])   # gentle field along the last direction
    zero = supervisor.update(0.5, False, FIELD, FORCE)
    assert not np.any(zero.field_T) and not np.any(zero.force_N) and not zero.immediate
    # Zero is left only after resume_after_frames tracked frames in a row.
    assert _frames(supervisor, [True, False, True, True, True], start=20) == [
        Mode.ZERO, Mode.ZERO, Mode.ZERO, Mode.RUN, Mode.RUN]
    reasons = [(e.previous, e.mode) for e in supervisor.events]
    assert reasons == [(Mode.RUN, Mode.HOLD), (Mode.HOLD, Mode.ZERO), (Mode.ZERO, Mode.RUN)]
    assert all(event.reason for event in supervisor.events)


def test_hold_recovers_as_soon_as_tracking_returns() -> None:
    supervisor = SafetySupervisor(SafetySettings(hold_after_lost_frames=1, zero_after_lost_frames=10))
    assert _frames(supervisor, [True, False, False, True]) == [Mode.RUN, Mode.RUN, Mode.HOLD, Mode.RUN]
    decision = supervisor.update(1.0, True, FIELD, FORCE)
    assert np.allclose(decision.field_T, FIELD) and np.allclose(decision.force_N, FORCE)


def test_fault_and_operator_stop_latch_until_reset() -> None:
    supervisor = SafetySupervisor()
    supervisor.update(0.0, True, FIELD, FORCE)
    decision = supervisor.fault("amplifier link lost", t_s=0.1)
    assert decision.mode is Mode.STOP and decision.immediate and not np.any(decision.field_T)
    assert supervisor.update(0.2, True, FIELD, FORCE).mode is Mode.STOP
    supervisor.reset(t_s=0.3)
    assert supervisor.update(0.4, True, FIELD, FORCE).mode is Mode.RUN
    supervisor.operator_stop(t_s=0.5)
    assert supervisor.update(0.6, True, FIELD, FORCE).mode is Mode.STOP
    assert [e.reason for e in supervisor.events] == ["amplifier link lost", "reset by operator", "operator stop"]
    assert supervisor.events[0].t_s == pytest.approx(0.1)


def test_overspeed_holds_without_push() -> None:
    supervisor = SafetySupervisor(SafetySettings(max_robot_speed_mm_s=10.0))
    fast = supervisor.update(0.0, True, FIELD, FORCE, robot_speed_mm_s=25.0)
    assert fast.mode is Mode.HOLD and not np.any(fast.force_N) and "speed" in (fast.reason or "")
    assert supervisor.update(0.1, True, FIELD, FORCE, robot_speed_mm_s=3.0).mode is Mode.RUN


def test_settings_are_validated() -> None:
    with pytest.raises(ConfigError, match="zero_after_lost_frames"):
        validate_model(SafetySettings, {"hold_after_lost_frames": 5, "zero_after_lost_frames": 5}, "sim.yaml",
                       key_prefix="safety")


def test_hold_keeps_the_direction_of_the_last_non_zero_field_whatever_its_form() -> None:
    supervisor = SafetySupervisor(SafetySettings(hold_after_lost_frames=0, hold_field_t=0.5e-3))
    oblique = [3e-4, 0.0, -4e-4]   # a list: taken as float64, direction (0.6, 0, -0.8)
    run = supervisor.update(0.0, True, oblique, [0, 0, 0])
    assert run.field_T.dtype == np.float64 and run.force_N.dtype == np.float64
    supervisor.update(0.1, True, np.zeros(3), np.zeros(3))   # a zero field leaves the direction as it was
    held = supervisor.update(0.2, False)
    assert held.mode is Mode.HOLD
    np.testing.assert_allclose(held.field_T, [0.3e-3, 0.0, -0.4e-3], rtol=1e-12)
