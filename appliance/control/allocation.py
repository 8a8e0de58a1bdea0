"""Current allocation: the coil currents that produce a desired field and force on the robot.

At the robot's position the configured actuation model is linear in the currents I (n coils):

    [B; F] = [B_per_amp(p); F_per_amp(p, m)] I = A I        (A is 6 x n)

where F_per_amp holds grad(m . B) per ampere for the robot's moment m. The allocator takes the
minimum-norm least-squares solution I* (``lstsq`` with a relative cut-off, so it stays defined
when A loses rank, e.g. m = 0 or fewer coils than constraints), with the field rows in mT and the
force rows in units of |m| x 10 mT/m so neither dominates when the request cannot be met exactly.

Limits: per-coil current, total power sum(R I^2), and per-coil slew over the step. A request that
breaks a limit is SCALED as a whole, I = s I* with the largest feasible s in [0, 1]: the field's
direction and the force's direction are kept (clipping one coil would turn them). If no scaled
request is reachable within one step's slew (currents must first come down from elsewhere), the
currents move from the previous ones straight toward the (amplitude-feasible) request as far as the
slew allows; that is reported as ``limited_by == "slew-ramp"``.

The per-frame work (actuation matrices, the least-squares solution and the limit scaling) runs as
compiled kernels (:mod:`appliance.compiled`): the same arithmetic as the numpy form, without ~60
small numpy calls of ~2 us each (issue 8: control and allocation p99 within 300 us).
"""
from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from appliance.compiled import kernel, register_warm_up
from appliance.control.actuation import (
    ActuationModel,
    _field_and_gradient,
    _force_rows,
)
from appliance.control.kernel_args import float_vector

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_FIELD_UNIT_T = 1e-3
_GRADIENT_UNIT_T_M = 1e-2
#: ``Allocation.limited_by`` by the code the allocation kernel returns.
_LIMITED_BY: tuple[str | None, ...] = (None, "current", "power", "slew", "slew-ramp")


class Allocation(NamedTuple):
    """Currents to command and what they achieve according to the configured model (an immutable
    named tuple: built every frame, and cheaper to build than a frozen dataclass)."""

    currents_a: FloatArray
    scale: float                  # 1.0 = request fully met; < 1: the whole request was scaled by it
                                  # ("slew-ramp": share of the request delivered, projected, in 0..1)
    limited_by: str | None        # None, "current", "power", "slew" or "slew-ramp"
    achieved_field_T: FloatArray
    achieved_force_N: FloatArray
    residual: float = 0.0         # relative residual of the unscaled solution (0 when reachable)


def _as_limits(value: float | ArrayLike | None, default: FloatArray, n: int, name: str) -> FloatArray:
    if value is None:
        return default.astype(float).copy()
    limits = np.broadcast_to(np.asarray(value, float), (n,)).copy()
    if np.any(limits <= 0.0) or not np.all(np.isfinite(limits)):
        raise ValueError(f"{name} must be positive and finite, got {value}")
    return limits


class CurrentAllocator:
    """Minimum-norm currents for a field and a force, within current, power and slew limits."""

    def __init__(self, model: ActuationModel, max_current_a: float | ArrayLike | None = None,
                 max_slew_a_per_s: float | ArrayLike | None = None, max_power_w: float | None = None,
                 rcond: float = 1e-9) -> None:
        self.model = model
        n = model.n
        limits = model.config.limits
        self.max_current_a = _as_limits(max_current_a, model.max_current_a, n, "max_current_a")
        self.max_slew_a_per_s = _as_limits(max_slew_a_per_s, np.full(n, limits.max_slew_a_per_s), n,
                                           "max_slew_a_per_s")
        self.max_power_w = float(max_power_w if max_power_w is not None else limits.max_power_w)
        if self.max_power_w <= 0.0:
            raise ValueError(f"max_power_w must be positive, got {max_power_w}")
        self.resistance_ohm = model.resistance_ohm
        self.rcond = rcond
        self._limits = np.vstack([self.max_current_a, self.max_slew_a_per_s, self.resistance_ohm])
        #: allocate_aligned's request (position, field, force, zero-field direction), rewritten every call
        #: through a memoryview: the kernel only reads it and nothing keeps it.
        self._aligned_request = np.zeros(12)
        self._aligned_stores = memoryview(self._aligned_request)

    def matrices(self, position_mm: ArrayLike, moment_am2: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(3 x n field per ampere, 3 x n force per ampere) at ``position_mm`` for ``moment_am2``."""
        return self.model.field_per_amp(position_mm), self.model.force_per_amp(position_mm, moment_am2)

    def solve(self, b_per_amp: FloatArray, f_per_amp: FloatArray, field_t: FloatArray, force_n: FloatArray,
              moment_norm: float) -> tuple[FloatArray, float, FloatArray]:
        """Unlimited minimum-norm solution, its relative residual, and the normalised 6 x n matrix."""
        return _solve(np.ascontiguousarray(b_per_amp, dtype=np.float64),
                      np.ascontiguousarray(f_per_amp, dtype=np.float64), np.asarray(field_t, dtype=np.float64),
                      np.asarray(force_n, dtype=np.float64), float(moment_norm), self.rcond)

    def allocate(self, position_mm: ArrayLike, field_T: ArrayLike, force_N: ArrayLike, moment_Am2: ArrayLike,
                 previous_a: ArrayLike, dt_s: float) -> Allocation:
        """Currents for the requested field (T) and force (N) on a dipole ``moment_Am2`` at ``position_mm``.

        ``previous_a`` are the currents now commanded and ``dt_s`` the time until the new ones take
        effect (slew budget = max_slew_a_per_s * dt_s).
        """
        # One array of position, field, force and moment, the previous currents as they are when they
        # fit the kernel (a read-only or strided argument would make it compile again), and one kernel
        # call from the actuation matrices to the currents: after a frame's recognition has cycled the
        # caches, every Python-level or numpy call here costs ~10-20 us, not the ~1 us of a warm loop.
        request = np.concatenate((position_mm, field_T, force_N, moment_Am2), axis=None, dtype=np.float64)
        if request.size != 12:
            raise ValueError(f"position, field, force and moment need 3 values each, got {request.size} in all")
        return self._allocate(request, False, 0.0, previous_a, dt_s)

    def allocate_aligned(self, position_mm: ArrayLike, field_T: ArrayLike, force_N: ArrayLike, moment_am2: float,
                         previous_a: ArrayLike, dt_s: float,
                         zero_field_direction: ArrayLike = (0.0, 0.0, 1.0)) -> Allocation:
        """:meth:`allocate` for a robot whose moment (``moment_am2``, A m^2) lies along the requested field,
        as the loop assumes (the robot aligns with the field within microseconds, see the path follower),
        or along the unit ``zero_field_direction`` when the field is zero.

        The same as ``allocate(position_mm, field_T, force_N, moment_am2 * field_T / |field_T|, ...)``, with
        the normalisation inside the kernel: the loop's three numpy calls on three numbers cost it
        10-20 us each after a frame's recognition has cycled the caches (issue 8). Plain floats (tuples,
        lists) are stored into a request array kept for the purpose, without a numpy call; anything
        that is not three values each goes through ``np.concatenate``. Not thread-safe (the loop's).
        """
        request = self._aligned_request
        stores = self._aligned_stores
        try:
            # Three values each into the request kept for this call, a float per store (the loop passes tuples
            # of floats: no numpy call at all; an array's three values unpack as numpy floats).
            stores[0], stores[1], stores[2] = position_mm
            stores[3], stores[4], stores[5] = field_T
            stores[6], stores[7], stores[8] = force_N
            stores[9], stores[10], stores[11] = zero_field_direction
        except (TypeError, ValueError):
            # Not three plain values each (another shape, a nested sequence): numpy's flattening decides.
            request = np.concatenate((position_mm, field_T, force_N, zero_field_direction), axis=None,
                                     dtype=np.float64)
            if request.size != 12:
                raise ValueError(
                    f"position, field, force and direction need 3 values each, got {request.size} in all") from None
        if not math.isfinite(moment_am2):
            raise ValueError(f"moment_am2 must be finite, got {moment_am2}")
        return self._allocate(request, True, float(moment_am2), previous_a, dt_s)

    def _allocate(self, request: FloatArray, aligned: bool, moment_am2: float, previous_a: ArrayLike,
                  dt_s: float) -> Allocation:
        previous = float_vector(previous_a, self.model.n, "previous_a")
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        finite, currents, scale, code, achieved_field, achieved_force, residual = _allocate_at(
            *self.model.loops, request, aligned, moment_am2, previous, float(dt_s), self._limits, self.max_power_w,
            self.rcond)
        if not finite:
            raise ValueError("position, field, force and moment must be finite")
        limited_by = _LIMITED_BY[code]
        if limited_by is not None:
            logger.debug("allocation limited by %s (scale %.3f)", limited_by, scale)
        return Allocation(currents, scale, limited_by, achieved_field, achieved_force, residual)


@kernel
def _allocate_at(centres: FloatArray, axes: FloatArray, radii: FloatArray, turns: FloatArray,
                 owner: NDArray[np.int64], request: FloatArray, aligned: bool, moment_am2: float,
                 previous: FloatArray, dt_s: float, limits: FloatArray, max_power_w: float, rcond: float
                 ) -> tuple[bool, FloatArray, float, int, FloatArray, FloatArray, float]:
    """:meth:`CurrentAllocator.allocate` in one call: ``request`` is position (mm), field (T), force (N),
    moment (A m^2); with ``aligned`` its last three values are the unit direction to take for a zero
    field, and the moment is ``moment_am2`` along the field (:meth:`CurrentAllocator.allocate_aligned`).
    ``limits`` rows are max current, max slew and resistance. The first value is False (and nothing
    computed) when the request is not finite."""
    n = limits.shape[1]
    for value in request:
        if not math.isfinite(value):
            return False, np.zeros(n), 0.0, 0, np.zeros(3), np.zeros(3), 0.0
    moment = request[9:12].copy()
    if aligned:
        field_norm = math.sqrt(request[3] * request[3] + request[4] * request[4] + request[5] * request[5])
        for k in range(3):
            moment[k] = moment_am2 * (request[3 + k] / field_norm if field_norm > 0.0 else request[9 + k])
    b_per_amp, gradient = _field_and_gradient(centres, axes, radii, turns, owner, n, request[0:3] * 1e-3)
    currents, scale, code, achieved_field, achieved_force, residual = _allocate(
        b_per_amp, gradient, request[3:6], request[6:9], moment, previous, dt_s, limits[0], limits[1],
        max_power_w, limits[2], rcond)
    return True, currents, scale, code, achieved_field, achieved_force, residual


@kernel
def _solve(b_per_amp: FloatArray, f_per_amp: FloatArray, field_t: FloatArray, force_n: FloatArray,
           moment_norm: float, rcond: float) -> tuple[FloatArray, float, FloatArray]:
    """:meth:`CurrentAllocator.solve`: field rows in mT, force rows in |m| x 10 mT/m, then ``lstsq``."""
    n = b_per_amp.shape[1]
    force_unit = max(moment_norm, 1e-12) * _GRADIENT_UNIT_T_M
    a = np.empty((6, n))
    y = np.empty(6)
    for i in range(3):
        for k in range(n):
            a[i, k] = b_per_amp[i, k] / _FIELD_UNIT_T
            a[3 + i, k] = f_per_amp[i, k] / force_unit
        y[i] = field_t[i] / _FIELD_UNIT_T
        y[3 + i] = force_n[i] / force_unit
    size = math.sqrt(_dot(y, y))
    if size < 1e-12:   # below 1 pT and 1e-14 |m| T/m: nothing to do
        return np.zeros(n), 0.0, a
    currents = _min_norm_solution(a, y, rcond)
    error = _matvec(a, currents) - y
    return currents, math.sqrt(_dot(error, error)) / size, a


@kernel
def _matvec(a: FloatArray, x: FloatArray) -> FloatArray:
    """``a @ x`` for the allocator's 3 x n and 6 x n matrices, by loops: numba's ``@`` calls BLAS (gemv),
    whose first call after a frame's recognition has cycled the caches costs tens of microseconds."""
    out = np.zeros(a.shape[0])
    for i in range(a.shape[0]):
        total = 0.0
        for k in range(a.shape[1]):
            total += a[i, k] * x[k]
        out[i] = total
    return out


@kernel
def _dot(x: FloatArray, y: FloatArray) -> float:
    total = 0.0
    for k in range(x.shape[0]):
        total += x[k] * y[k]
    return total


@kernel
def _min_norm_solution(a: FloatArray, y: FloatArray, rcond: float) -> FloatArray:
    """``np.linalg.lstsq(a, y, rcond)[0]`` for a wide matrix (rows <= columns), the common case by QR.

    With A^T = Q R (Householder), x = Q R^-T y solves A x = y and lies in the row space of A: the
    minimum-norm solution, which is what ``lstsq`` returns while no singular value falls under
    ``rcond`` times the largest. R's diagonal bounds the singular values within a factor of ~2^rows,
    so when its smallest entry is under 1e-6 of its largest (or A is tall) the SVD-based ``lstsq``
    decides instead. QR is a few dozen lines of loops; LAPACK's gelsd is a large routine whose first
    call after a frame's recognition costs ~100 us of cache misses.
    """
    m, n = a.shape
    if m > n:
        return np.linalg.lstsq(a, y, rcond=rcond)[0]
    work = a.T.copy()                     # n x m, becomes R in its top m rows
    reflectors = np.zeros((n, m))
    betas = np.zeros(m)
    for j in range(m):
        norm = 0.0
        for i in range(j, n):
            norm += work[i, j] * work[i, j]
        norm = math.sqrt(norm)
        if norm == 0.0:
            return np.linalg.lstsq(a, y, rcond=rcond)[0]
        alpha = -norm if work[j, j] >= 0.0 else norm
        vv = 0.0
        for i in range(j, n):
            reflectors[i, j] = work[i, j]
        reflectors[j, j] -= alpha
        for i in range(j, n):
            vv += reflectors[i, j] * reflectors[i, j]
        betas[j] = 2.0 / vv
        for k in range(j, m):
            dot = 0.0
            for i in range(j, n):
                dot += reflectors[i, j] * work[i, k]
            dot *= betas[j]
            for i in range(j, n):
                work[i, k] -= dot * reflectors[i, j]
    largest, smallest = 0.0, math.inf
    for j in range(m):
        largest = max(largest, abs(work[j, j]))
        smallest = min(smallest, abs(work[j, j]))
    if smallest <= 1e-6 * largest or 1e-6 < rcond:
        return np.linalg.lstsq(a, y, rcond=rcond)[0]
    z = np.zeros(n)                        # R^T z = y, forward substitution
    for j in range(m):
        total = y[j]
        for k in range(j):
            total -= work[k, j] * z[k]
        z[j] = total / work[j, j]
    for j in range(m - 1, -1, -1):         # x = Q z, the reflectors in reverse order
        dot = 0.0
        for i in range(j, n):
            dot += reflectors[i, j] * z[i]
        dot *= betas[j]
        for i in range(j, n):
            z[i] -= dot * reflectors[i, j]
    return z


@kernel
def _allocate(b_per_amp: FloatArray, gradient: FloatArray, field_t: FloatArray, force_n: FloatArray,
              moment: FloatArray, previous: FloatArray, dt_s: float, max_current_a: FloatArray,
              max_slew_a_per_s: FloatArray, max_power_w: float, resistance_ohm: FloatArray,
              rcond: float) -> tuple[FloatArray, float, int, FloatArray, FloatArray, float]:
    """The allocation of one frame (see the module docstring): ``(currents, scale, code of limited_by,
    achieved field, achieved force, residual)``."""
    n = b_per_amp.shape[1]
    f_per_amp = _force_rows(gradient, moment)
    ideal, residual, normalised = _solve(b_per_amp, f_per_amp, field_t, force_n,
                                         math.sqrt(_dot(moment, moment)), rcond)

    scale, code = 1.0, 0
    s_current, power = math.inf, 0.0
    for k in range(n):
        magnitude = abs(ideal[k])
        if magnitude > 0.0:
            s_current = min(s_current, max_current_a[k] / magnitude)
        power += resistance_ohm[k] * ideal[k] ** 2
    s_power = math.sqrt(max_power_w / power) if power > 0.0 else math.inf
    if s_current < scale:
        scale, code = s_current, 1
    if s_power < scale:
        scale, code = s_power, 2

    budget = max_slew_a_per_s * dt_s
    low, high = 0.0, scale
    for k in range(n):
        if ideal[k] == 0.0:
            if abs(previous[k]) > budget[k]:
                low, high = 1.0, 0.0   # this coil cannot reach 0 in one step: no s works
            continue
        a_k = (previous[k] - budget[k]) / ideal[k]
        b_k = (previous[k] + budget[k]) / ideal[k]
        low, high = max(low, min(a_k, b_k)), min(high, max(a_k, b_k))
    if low <= high:
        if high < scale:
            code = 3
        scale = high
        currents = scale * ideal
    else:
        # Ramp straight toward the amplitude-feasible request; the segment between two points
        # inside the (convex) current and power limits stays inside them.
        step = scale * ideal - previous
        # A channel with (almost) no step allows any fraction (also when budget/step overflows).
        fraction = 1.0
        for k in range(n):
            if abs(step[k]) > 0.0:
                fraction = min(fraction, budget[k] / abs(step[k]))
        currents = previous + fraction * step
        code = 4
        scale = min(max(_projection(normalised, currents, ideal), 0.0), 1.0)
    # Rounding guard only (s was chosen so that these hold exactly in real arithmetic).
    for k in range(n):
        currents[k] = min(max(currents[k], -max_current_a[k]), max_current_a[k])
    return currents, scale, code, _matvec(b_per_amp, currents), _matvec(f_per_amp, currents), residual


@kernel
def _projection(normalised: FloatArray, currents: FloatArray, ideal: FloatArray) -> float:
    """How much of the request the ramped currents deliver (projection in normalised units)."""
    wanted = _matvec(normalised, ideal)
    norm2 = _dot(wanted, wanted)
    return _dot(_matvec(normalised, currents), wanted) / norm2 if norm2 > 0.0 else 0.0


def warm_up() -> None:
    """Compile the kernels of this module on one- and two-coil problems (see :mod:`appliance.compiled`)."""
    ones, unit = np.ones(2), np.array([0.0, 0.0, 1e-3])
    b_per_amp = np.array([[1e-3, 0.0], [0.0, 1e-3], [0.0, 0.0]])
    loops = (np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0.05]), np.array([1.0]),
             np.array([0], dtype=np.int64))
    _allocate_at(*loops, np.concatenate((np.array([0.0, 0.0, 1.0]), unit, np.zeros(3), unit)), True, 1e-3,
                 np.zeros(1), 0.01, np.ones((3, 1)), 1.0, 1e-9)
    _solve(b_per_amp, np.zeros((3, 2)), unit, np.zeros(3), 1e-3, 1e-9)
    _projection(np.ones((6, 2)), ones, ones)
    _min_norm_solution(np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]]), np.ones(2), 1e-9)


register_warm_up(__name__)
