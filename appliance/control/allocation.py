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
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from appliance.control.actuation import ActuationModel

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_FIELD_UNIT_T = 1e-3
_GRADIENT_UNIT_T_M = 1e-2


@dataclass(frozen=True)
class Allocation:
    """Currents to command and what they achieve according to the configured model."""

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

    def matrices(self, position_mm: ArrayLike, moment_am2: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(3 x n field per ampere, 3 x n force per ampere) at ``position_mm`` for ``moment_am2``."""
        return self.model.field_per_amp(position_mm), self.model.force_per_amp(position_mm, moment_am2)

    def solve(self, b_per_amp: FloatArray, f_per_amp: FloatArray, field_t: FloatArray, force_n: FloatArray,
              moment_norm: float) -> tuple[FloatArray, float, FloatArray]:
        """Unlimited minimum-norm solution, its relative residual, and the normalised 6 x n matrix."""
        force_unit = max(moment_norm, 1e-12) * _GRADIENT_UNIT_T_M
        a = np.vstack([b_per_amp / _FIELD_UNIT_T, f_per_amp / force_unit])
        y = np.concatenate([field_t / _FIELD_UNIT_T, force_n / force_unit])
        size = float(np.linalg.norm(y))
        if size < 1e-12:   # below 1 pT and 1e-14 |m| T/m: nothing to do
            return np.zeros(self.model.n), 0.0, a
        currents, *_ = np.linalg.lstsq(a, y, rcond=self.rcond)
        residual = float(np.linalg.norm(a @ currents - y) / size)
        return currents, residual, a

    def allocate(self, position_mm: ArrayLike, field_T: ArrayLike, force_N: ArrayLike, moment_Am2: ArrayLike,
                 previous_a: ArrayLike, dt_s: float) -> Allocation:
        """Currents for the requested field (T) and force (N) on a dipole ``moment_Am2`` at ``position_mm``.

        ``previous_a`` are the currents now commanded and ``dt_s`` the time until the new ones take
        effect (slew budget = max_slew_a_per_s * dt_s).
        """
        n = self.model.n
        field_t = np.asarray(field_T, float).reshape(3)
        force_n = np.asarray(force_N, float).reshape(3)
        moment = np.asarray(moment_Am2, float).reshape(3)
        previous = np.asarray(previous_a, float).reshape(n)
        if not (np.all(np.isfinite(field_t)) and np.all(np.isfinite(force_n)) and np.all(np.isfinite(moment))):
            raise ValueError("field, force and moment must be finite")
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        b_per_amp, f_per_amp = self.matrices(position_mm, moment)
        ideal, residual, normalised = self.solve(b_per_amp, f_per_amp, field_t, force_n, float(np.linalg.norm(moment)))

        scale, limited_by = 1.0, None
        magnitude = np.abs(ideal)
        with np.errstate(divide="ignore"):
            s_current = float(np.min(np.where(magnitude > 0.0, self.max_current_a / magnitude, np.inf)))
        power = float(np.sum(self.resistance_ohm * ideal**2))
        s_power = float(np.sqrt(self.max_power_w / power)) if power > 0.0 else np.inf
        if s_current < scale:
            scale, limited_by = s_current, "current"
        if s_power < scale:
            scale, limited_by = s_power, "power"

        budget = self.max_slew_a_per_s * dt_s
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
                limited_by = "slew"
            scale = high
            currents = scale * ideal
        else:
            # Ramp straight toward the amplitude-feasible request; the segment between two points
            # inside the (convex) current and power limits stays inside them.
            target = scale * ideal
            step = target - previous
            # A channel with (almost) no step allows any fraction: +inf, also when budget/step overflows.
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                fractions = np.where(np.abs(step) > 0.0, budget / np.abs(step), np.inf)
            fraction = float(min(1.0, np.min(fractions)))
            currents = previous + fraction * step
            limited_by = "slew-ramp"
            scale = min(max(_projection(normalised, currents, ideal), 0.0), 1.0)
        # Rounding guard only (s was chosen so that these hold exactly in real arithmetic).
        currents = np.clip(currents, -self.max_current_a, self.max_current_a)
        achieved_field = b_per_amp @ currents
        achieved_force = f_per_amp @ currents
        if limited_by is not None:
            logger.debug("allocation limited by %s (scale %.3f)", limited_by, scale)
        return Allocation(currents, float(scale), limited_by, achieved_field, achieved_force, residual)


def _projection(normalised: FloatArray, currents: FloatArray, ideal: FloatArray) -> float:
    """How much of the request the ramped currents deliver (projection in normalised units)."""
    wanted = normalised @ ideal
    norm2 = float(np.dot(wanted, wanted))
    return float(np.dot(normalised @ currents, wanted) / norm2) if norm2 > 0.0 else 0.0
