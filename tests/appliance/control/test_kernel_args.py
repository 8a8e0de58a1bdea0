"""The control kernels' vector arguments: passed through when they fit, copied when they do not, and
the per-frame results immutable."""
from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.control import (
    ActuationModel,
    CurrentAllocator,
    PathFollower,
    SafetySupervisor,
    load_coils,
)
from appliance.control.allocation import _allocate_at
from appliance.control.kernel_args import float_vector
from appliance.control.path_follower import _follow

PATH = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 1.0, 0.0]]


def test_a_fitting_vector_goes_through_and_anything_else_is_copied() -> None:
    fits = np.array([1.0, 2.0, 3.0])
    assert float_vector(fits, 3, "v") is fits
    read_only = fits.copy()
    read_only.flags.writeable = False
    strided = np.arange(6.0)[::2]
    for value in (read_only, strided, [1, 2, 3], np.array([1, 2, 3]), np.array([1.0, 2.0, 3.0], np.float32),
                  np.array([[1.0, 2.0, 3.0]])):
        out = float_vector(value, 3, "v")
        assert out is not value
        assert out.dtype == np.float64 and out.shape == (3,) and out.flags.c_contiguous and out.flags.writeable
        np.testing.assert_array_equal(out, np.ravel(value))
    with pytest.raises(ValueError, match="v needs 3 values, got 4"):
        float_vector([1.0, 2.0, 3.0, 4.0], 3, "v")


def test_views_into_a_posture_give_the_same_command_and_compile_nothing() -> None:
    """A read-only or strided centroid (a view into a posture) is copied, not given to the kernel
    (which would compile a variant at that frame); the command equals the one from plain arrays."""
    reference, follower = PathFollower(PATH), PathFollower(PATH)
    p, axis = np.array([1.0, 0.1, 0.0]), np.array([1.0, 0.0, 0.0])
    reference.command(p, axis, 0.0)
    follower.command(p, axis, 0.0)
    signatures = len(_follow.signatures)
    posture = np.array([[1.2, 0.12, 0.0], [9.0, 9.0, 9.0]])
    posture.flags.writeable = False
    strided_axis = np.array([[1.0, 7.0], [0.0, 7.0], [0.0, 7.0]])[:, 0]
    expected = reference.command(np.array([1.2, 0.12, 0.0]), axis, 0.1)
    got = follower.command(posture[0], strided_axis, 0.1)
    assert len(_follow.signatures) == signatures
    for a, b in zip(expected, got):
        np.testing.assert_array_equal(a, b)


def test_the_inputs_are_not_written_and_the_results_are_immutable() -> None:
    follower, safety = PathFollower(PATH), SafetySupervisor()
    allocator = CurrentAllocator(ActuationModel(load_coils()))
    p, axis = np.array([1.0, 0.1, 0.0]), np.array([1.0, 0.0, 0.0])
    inputs = (p.copy(), axis.copy())
    command = follower.command(p, axis, 0.0)
    decision = safety.update(0.0, True, command.field_T, command.force_N)
    previous = np.full(allocator.model.n, 0.1)
    moment = 1e-3 * command.moment_direction
    allocation = allocator.allocate(p, decision.field_T, decision.force_N, moment, previous, 1 / 30)
    np.testing.assert_array_equal(p, inputs[0])
    np.testing.assert_array_equal(axis, inputs[1])
    np.testing.assert_array_equal(previous, np.full(allocator.model.n, 0.1))
    for result, name in ((command, "field_T"), (decision, "mode"), (allocation, "currents_a")):
        with pytest.raises(AttributeError):
            setattr(result, name, None)
    assert math.isclose(float(np.linalg.norm(command.moment_direction)), 1.0)


def test_a_position_that_is_not_finite_is_refused_before_any_current_is_computed() -> None:
    allocator = CurrentAllocator(ActuationModel(load_coils()))
    n = allocator.model.n
    field, force, moment = np.array([0.0, 0.0, 5e-4]), np.zeros(3), np.array([0.0, 0.0, 1e-3])
    for position in ([math.nan, 0.0, 0.0], [0.0, math.inf, 0.0]):
        with pytest.raises(ValueError, match="must be finite"):
            allocator.allocate(position, field, force, moment, np.zeros(n), 1 / 30)
    with pytest.raises(ValueError, match="3 values each"):
        allocator.allocate([0.0, 0.0], field, force, moment, np.zeros(n), 1 / 30)
    with pytest.raises(ValueError, match="previous_a needs"):
        allocator.allocate([0.0, 0.0, 0.0], field, force, moment, np.zeros(n + 1), 1 / 30)
    allocator.allocate(np.zeros(3), field, force, moment, np.zeros(n), 1 / 30)
    signatures = len(_allocate_at.signatures)
    strided = np.zeros((n, 2))[:, 0]   # strided previous currents: copied, not compiled for
    expected = allocator.allocate(np.zeros(3), field, force, moment, np.zeros(n), 1 / 30)
    got = allocator.allocate(np.zeros(3), field, force, moment, strided, 1 / 30)
    assert len(_allocate_at.signatures) == signatures
    np.testing.assert_array_equal(expected.currents_a, got.currents_a)
