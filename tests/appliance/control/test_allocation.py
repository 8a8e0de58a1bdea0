"""Current allocation: exact when reachable, scaled (never clipped) when not, always within limits."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.control import ActuationModel, CurrentAllocator, load_coils

MOMENT = 0.03  # A m^2, robot #1


@pytest.fixture(scope="module")
def model() -> ActuationModel:
    return ActuationModel(load_coils())


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def test_reachable_request_is_met_exactly_with_minimum_norm(model: ActuationModel) -> None:
    alloc = CurrentAllocator(model)
    d = np.array([0.48, 0.6, 0.64])
    position = np.array([10.0, -5.0, 3.0])
    field, force = 1.5e-3 * d, 2e-5 * np.array([0.0, 0.6, -0.8])
    result = alloc.allocate(position, field, force, MOMENT * d, np.zeros(8), 1.0)
    assert result.scale == 1.0 and result.limited_by is None
    assert np.allclose(result.achieved_field_T, field, rtol=0, atol=1e-12)
    assert np.allclose(result.achieved_force_N, force, rtol=0, atol=1e-14)
    # Independent check of what the currents do, and of minimum norm: any null-space move is longer.
    assert np.allclose(model.field(position, result.currents_a), field, atol=1e-12)
    a = np.vstack([model.field_per_amp(position), model.force_per_amp(position, MOMENT * d)])
    null = np.linalg.svd(a)[2][6:]
    for v in null:
        assert abs(float(np.dot(v, result.currents_a))) < 1e-9
    assert result.residual < 1e-9


def test_unreachable_request_is_scaled_keeping_both_directions(model: ActuationModel) -> None:
    alloc = CurrentAllocator(model)
    d = np.array([0.0, 0.6, 0.8])
    field, force = 40e-3 * d, 5e-4 * np.array([1.0, 0.0, 0.0])
    alloc = CurrentAllocator(model, max_power_w=1e5)
    result = alloc.allocate([0, 0, 0], field, force, MOMENT * d, np.zeros(8), 10.0)
    assert result.limited_by == "current" and 0.0 < result.scale < 1.0
    assert np.max(np.abs(result.currents_a)) == pytest.approx(12.0)
    assert _angle_deg(result.achieved_field_T, field) < 0.1
    assert _angle_deg(result.achieved_force_N, force) < 0.1
    assert np.linalg.norm(result.achieved_field_T) == pytest.approx(result.scale * np.linalg.norm(field), rel=1e-9)
    # Clipping each coil instead would have turned the field: the property the scaling protects.
    ideal, _, _ = alloc.solve(model.field_per_amp([0, 0, 0]), model.force_per_amp([0, 0, 0], MOMENT * d),
                              field, force, MOMENT)
    clipped_field = model.field([0, 0, 0], np.clip(ideal, -12, 12))
    assert _angle_deg(clipped_field, field) > 1.0


def test_power_and_slew_limits_scale_the_request(model: ActuationModel) -> None:
    d = np.array([1.0, 0.0, 0.0])
    power_limited = CurrentAllocator(model, max_power_w=20.0).allocate([0, 0, 0], 2e-3 * d, np.zeros(3), MOMENT * d,
                                                                       np.zeros(8), 1.0)
    assert power_limited.limited_by == "power"
    assert float(np.sum(model.resistance_ohm * power_limited.currents_a**2)) == pytest.approx(20.0)
    slew_limited = CurrentAllocator(model, max_slew_a_per_s=30.0).allocate([0, 0, 0], 2e-3 * d, np.zeros(3),
                                                                           MOMENT * d, np.zeros(8), 1 / 30)
    assert slew_limited.limited_by == "slew"
    assert np.max(np.abs(slew_limited.currents_a)) == pytest.approx(1.0)
    assert _angle_deg(slew_limited.achieved_field_T, d) < 1e-6


def test_zero_request_ramps_down_at_the_slew_limit(model: ActuationModel) -> None:
    alloc = CurrentAllocator(model, max_slew_a_per_s=60.0)
    previous = np.array([6.0, -3.0, 0.0, 1.0, 0.5, -6.0, 2.0, 0.0])
    currents, steps = previous, 0
    while np.any(currents) and steps < 20:
        result = alloc.allocate([0, 0, 0], np.zeros(3), np.zeros(3), np.zeros(3), currents, 1 / 30)
        assert np.max(np.abs(result.currents_a - currents)) <= 2.0 + 1e-12
        assert result.limited_by in ("slew-ramp", None)
        currents, steps = result.currents_a, steps + 1
    assert steps == 3 and not np.any(currents)   # 6 A at 2 A per step


def test_bad_arguments_are_rejected(model: ActuationModel) -> None:
    with pytest.raises(ValueError, match="max_current_a"):
        CurrentAllocator(model, max_current_a=-1.0)
    alloc = CurrentAllocator(model)
    with pytest.raises(ValueError, match="dt_s"):
        alloc.allocate([0, 0, 0], np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(8), 0.0)
    with pytest.raises(ValueError, match="finite"):
        alloc.allocate([0, 0, 0], [np.nan, 0, 0], np.zeros(3), np.zeros(3), np.zeros(8), 0.1)


_vec = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: float(np.linalg.norm(v)) > 0.05)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(direction=_vec, force_dir=_vec, field_mt=st.sampled_from([0.0]) | st.floats(0.01, 30.0), force_un=st.floats(0.0, 3000.0),
       position=st.tuples(*[st.floats(-50.0, 50.0)] * 3),
       previous_fraction=st.lists(st.floats(-1.0, 1.0), min_size=8, max_size=8),
       max_current=st.floats(0.5, 12.0), slew=st.floats(5.0, 300.0), power=st.floats(5.0, 2000.0),
       dt=st.floats(0.005, 0.2))
def test_currents_never_exceed_current_slew_or_power_limits(
        model: ActuationModel, direction: tuple[float, float, float], force_dir: tuple[float, float, float],
        field_mt: float, force_un: float, position: tuple[float, float, float], previous_fraction: list[float],
        max_current: float, slew: float, power: float, dt: float) -> None:
    alloc = CurrentAllocator(model, max_current_a=max_current, max_slew_a_per_s=slew, max_power_w=power)
    d = np.asarray(direction) / np.linalg.norm(direction)
    previous = np.asarray(previous_fraction) * max_current
    # The previous currents were themselves allowed: scale them into the power limit.
    previous_power = float(np.sum(model.resistance_ohm * previous**2))
    if previous_power > power:
        previous *= math.sqrt(power / previous_power)
    f = np.asarray(force_dir) / np.linalg.norm(force_dir)
    result = alloc.allocate(position, field_mt * 1e-3 * d, force_un * 1e-6 * f, MOMENT * d, previous, dt)
    currents = result.currents_a
    assert np.all(np.abs(currents) <= max_current * (1 + 1e-12))
    assert np.all(np.abs(currents - previous) <= slew * dt * (1 + 1e-9) + 1e-12)
    assert float(np.sum(model.resistance_ohm * currents**2)) <= power * (1 + 1e-9)
    assert 0.0 <= result.scale <= 1.0 + 1e-12
    if result.limited_by != "slew-ramp" and result.scale > 1e-6 and field_mt > 0.0:
        assert _angle_deg(result.achieved_field_T, d) < 0.1


def test_qr_minimum_norm_solution_equals_lstsq_also_when_it_hands_over() -> None:
    """The allocation's QR solve against numpy's SVD-based lstsq: wide full-rank (QR), rank-deficient
    (a zero row, two parallel rows: lstsq decides) and tall matrices."""
    from appliance.control.allocation import _min_norm_solution

    rng = np.random.default_rng(5)
    for case in range(300):
        a = rng.normal(size=(6, (6, 8, 8, 5)[case % 4])) * np.exp(rng.uniform(-2.0, 2.0, size=(6, 1)))
        if case % 5 == 1:
            a[3] = 0.0
        if case % 5 == 2:
            a[4] = -3.0 * a[1]
        y = rng.normal(size=6)
        expected = np.linalg.lstsq(a, y, rcond=1e-9)[0]
        assert np.abs(_min_norm_solution(a, y, 1e-9) - expected).max() < 1e-8 * np.abs(expected).max()


def test_allocate_aligned_is_allocate_with_the_moment_along_the_field() -> None:
    """The loop's moment (magnitude along the requested field, a given direction when the field is
    zero) normalised inside the kernel: the same currents as the explicit moment."""
    allocator = CurrentAllocator(ActuationModel(load_coils()))
    n = allocator.model.n
    rng = np.random.default_rng(5)
    previous = np.zeros(n)
    for _ in range(20):
        position = rng.uniform(-10.0, 10.0, 3)
        field = rng.normal(size=3) * 4e-4
        force = rng.normal(size=3) * 3e-6
        moment = 2e-3 * (field / math.sqrt(float(field @ field)))
        expected = allocator.allocate(position, field, force, moment, previous, 1 / 30)
        got = allocator.allocate_aligned(position, field, force, 2e-3, previous, 1 / 30)
        np.testing.assert_allclose(got.currents_a, expected.currents_a, rtol=1e-12, atol=1e-15)
        assert (got.scale, got.limited_by) == pytest.approx((expected.scale, expected.limited_by))
        previous = got.currents_a
    # A zero field: the moment along the given direction (the force still needs one).
    direction = np.array([0.0, 0.6, 0.8])
    force = np.array([0.0, 0.0, 2e-6])
    expected = allocator.allocate(np.zeros(3), np.zeros(3), force, 2e-3 * direction, np.zeros(n), 1 / 30)
    got = allocator.allocate_aligned(np.zeros(3), np.zeros(3), force, 2e-3, np.zeros(n), 1 / 30, direction)
    np.testing.assert_array_equal(got.currents_a, expected.currents_a)
    assert np.any(got.currents_a)
    with pytest.raises(ValueError, match="moment_am2 must be finite"):
        allocator.allocate_aligned(np.zeros(3), np.zeros(3), force, math.nan, np.zeros(n), 1 / 30)
    with pytest.raises(ValueError, match="must be finite"):
        allocator.allocate_aligned(np.zeros(3), [math.inf, 0.0, 0.0], force, 2e-3, np.zeros(n), 1 / 30)
