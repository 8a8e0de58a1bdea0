"""Per-sample errors and summaries of a validation session, on data whose answers can be worked out by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.validation.statistics import (
    axis_angle_deg,
    direction_angle_deg,
    fraction,
    mean_sd_text,
    position_error_mm,
    summarise,
    tip_errors_mm,
)


def test_position_error_is_the_euclidean_distance() -> None:
    assert position_error_mm([1.0, 2.0, 3.0], [4.0, 6.0, 3.0]) == pytest.approx(5.0)


@pytest.mark.parametrize(("a", "b", "expected"), [
    ([1, 0, 0], [0, 1, 0], 90.0),
    ([1, 0, 0], [1, 1, 0], 45.0),
    ([1, 0, 0], [-1, 1, 0], 45.0),      # a line: the sign of either direction does not matter
    ([0, 0, 2], [0, 0, -5], 0.0),
    ([1, 0, 0], [1, math.tan(math.radians(1.0)), 0], 1.0),
])
def test_axis_angle_is_between_lines(a: list[float], b: list[float], expected: float) -> None:
    assert axis_angle_deg(a, b) == pytest.approx(expected, abs=1e-9)


def test_axis_angle_keeps_its_digits_near_zero() -> None:
    # acos(dot) would give 0 or ~1e-6 deg here; atan2 of cross and dot gives the right 1e-7 rad.
    assert axis_angle_deg([1, 0, 0], [1, 1e-7, 0]) == pytest.approx(np.degrees(1e-7), rel=1e-6)


def test_direction_angle_sees_a_flipped_head() -> None:
    assert direction_angle_deg([0, 0, 1], [0, 0, -1]) == pytest.approx(180.0)
    assert direction_angle_deg([1, 0, 0], [-1, 1, 0]) == pytest.approx(135.0)


def test_zero_directions_are_refused() -> None:
    with pytest.raises(ValueError, match="non-zero"):
        axis_angle_deg([0, 0, 0], [1, 0, 0])


def test_tips_follow_the_head_identification_when_there_is_one() -> None:
    head, tail = [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    tips = [[0.0, 0.3, 0.0], [10.0, 0.0, 0.4]]      # recognised tail first: the head was called wrongly
    wrong = tip_errors_mm(tips, head, tail, head_identified=True)
    assert (wrong.head_mm, wrong.tail_mm, wrong.matched_by_head) == pytest.approx((10.0 + 0.0045, 10.008, True),
                                                                                   abs=0.01)
    free = tip_errors_mm(tips, head, tail, head_identified=False)
    assert (free.head_mm, free.tail_mm, free.matched_by_head) == pytest.approx((0.4, 0.3, False))
    assert free.mean_mm == pytest.approx(0.35)


def test_summary_of_one_to_four() -> None:
    s = summarise([1.0, 2.0, None, 3.0, 4.0, float("nan")])
    assert (s.n, s.missing) == (4, 2)
    assert s.mean == pytest.approx(2.5)
    assert s.sd == pytest.approx(math.sqrt(5.0 / 3.0))          # sum of squared deviations 5, n - 1 = 3
    assert s.rms == pytest.approx(math.sqrt(7.5))               # (1 + 4 + 9 + 16) / 4
    assert (s.median, s.q1, s.q3) == pytest.approx((2.5, 1.75, 3.25))
    assert (s.min, s.max, s.p95) == pytest.approx((1.0, 4.0, 3.85))
    assert mean_sd_text(s, 2) == "2.50 ± 1.29"


def test_summary_without_values_is_nan_and_prints_na() -> None:
    s = summarise([None, None])
    assert (s.n, s.missing) == (0, 2) and math.isnan(s.mean)
    assert mean_sd_text(s) == "n/a"
    assert s.to_dict()["mean"] is None and s.to_dict()["n"] == 0
    one = summarise([0.25])
    assert math.isnan(one.sd) and mean_sd_text(one, 2) == "0.25"


def test_fraction() -> None:
    assert fraction([True, False, True, True]) == pytest.approx(0.75)
    assert math.isnan(fraction([]))
