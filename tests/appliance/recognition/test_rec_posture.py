"""The posture record (Posture.to_record) and the deferred posture (Posture.deferred) the steady state builds:
the record's numbers are numpy's definition of them (every value finite, else None; rounded per number), and
a deferred posture reads, copies and pickles like one built by its __init__."""
from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest

from appliance.recognition.posture import DEFERRABLE, Posture, ViewObservation, _rows, _vec


def _vec_by_numpy(value: object, digits: int) -> list[float] | None:
    """The record's vector as numpy defines it (what _vec replaced, per number in Python)."""
    if value is None:
        return None
    array = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        return None
    return [round(float(x), digits) for x in array.ravel()]


@pytest.mark.parametrize("value", [
    np.array([1.234567891, -2.5e-5, 3.0]), np.array([1.0, np.nan, 2.0]), np.array([np.inf, 0.0]),
    np.array([0.123456789, 7.0], dtype=np.float32), (1.0000049, 2), [3, 4.5], np.float64(2.718281828),
    np.arange(6, dtype=np.int64).reshape(2, 3) * 0.3333333, np.empty(0), np.array([1.0, 2.0, 3.0])[::2], None,
])
def test_record_vectors_are_numpys_definition(value: object) -> None:
    for digits in (3, 4, 6):
        assert _vec(value, digits) == _vec_by_numpy(value, digits)  # type: ignore[arg-type]


@pytest.mark.parametrize("value", [
    np.array([[1.23456, 2.0], [np.nan, 1.0]]), np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]) / 7.0,
    np.array([[1.5, 2.5]], dtype=np.float32), [np.array([1.0, 2.0]), np.array([np.inf, 3.0])],
])
def test_record_rows_are_each_rows_vector(value: object) -> None:
    assert _rows(value, 4) == [_vec_by_numpy(row, 4) for row in value]  # type: ignore[arg-type, union-attr]


def _fields_and_views() -> tuple[dict[str, object], dict[str, ViewObservation | None]]:
    views = {name: ViewObservation(np.array([10.0 + k, 20.0]), np.array([[1.0, 2.0], [3.0, 4.0 + k]]),
                                   np.array([0.6, 0.8]), 40 + k, (9.0, 2.0), 0) for k, name in enumerate("pq")}
    fields = {"frame": 7, "t": 0.25, "ok": True, "ambiguous": False, "centroid_mm": np.array([1.0, 2.0, 3.0]),
              "direction": np.array([0.0, 0.6, 0.8]), "head_identified": True, "length_mm": 5.0,
              "reprojection_px": 0.2, "reason": None, "direction_candidates": None, "pairing_rms_px": (0.1, 9.0),
              "plane_angle_deg": 80.0, "timings_us": {"segmentation": 1.0}}
    return fields, views


class _Rest:
    """The deferred fields, counting how often they are made."""

    def __init__(self, tips: np.ndarray, views: dict[str, ViewObservation | None]) -> None:
        self.tips, self.views, self.calls = tips, views, 0

    def __call__(self) -> dict[str, object]:
        self.calls += 1
        return {"tips_mm": self.tips, "views": self.views}


def test_a_deferred_posture_reads_as_the_one_its_init_builds() -> None:
    fields, views = _fields_and_views()
    tips = np.array([[1.0, 2.0, 5.5], [1.0, 2.0, 0.5]])
    built = Posture(**fields, tips_mm=tips, views=views)  # type: ignore[arg-type]
    rest = _Rest(tips, views)
    deferred = Posture.deferred(dict(fields), rest)
    assert rest.calls == 0 and not DEFERRABLE & deferred.__dict__.keys()
    assert deferred.frame == 7 and deferred.centroid_mm is fields["centroid_mm"] and rest.calls == 0
    assert deferred.views is views and deferred.tips_mm is tips and rest.calls == 1
    assert deferred.to_record() == built.to_record() and rest.calls == 1
    assert repr(deferred) == repr(built)


def test_a_deferred_posture_copies_and_pickles_with_its_fields() -> None:
    fields, views = _fields_and_views()
    tips = np.array([[1.0, 2.0, 5.5], [1.0, 2.0, 0.5]])
    for take in (copy.copy, copy.deepcopy, lambda p: pickle.loads(pickle.dumps(p))):
        posture = take(Posture.deferred(dict(fields), _Rest(tips, views)))
        assert type(posture) is Posture
        assert posture.to_record() == Posture(**fields, tips_mm=tips, views=views).to_record()  # type: ignore[arg-type]


def test_posture_defaults_and_missing_attributes_are_unchanged() -> None:
    lost = Posture.lost(3, 0.1, "gone")
    assert lost.tips_mm is None and lost.views == {"p": None, "q": None} and lost.timings_us == {}
    assert Posture(frame=1, t=0.0, ok=False).tips_mm is None
    with pytest.raises(AttributeError):
        lost.no_such_field  # noqa: B018
    assert not hasattr(lost, "_rest") and math.isclose(lost.to_record()["t"], 0.1)


def test_a_field_assigned_before_the_deferred_ones_are_made_keeps_its_value() -> None:
    fields, views = _fields_and_views()
    tips = np.array([[1.0, 2.0, 5.5], [1.0, 2.0, 0.5]])
    posture = Posture.deferred(dict(fields), _Rest(tips, views))
    other = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    posture.tips_mm = other
    assert posture.views is views and posture.tips_mm is other
