"""Allocations of a fixed set of requests, saved for a per-request comparison between two trees (round 14).

    cd TREE && NUMBA_CACHE_DIR=... python /path/to/benchmarks/allocation_dump.py OUT.npz
    python benchmarks/allocation_dump.py --compare A.npz B.npz

Imports the tree of the working directory (so one copy of this script serves a base checkout too). The
requests: the follower's own commands along the shipped path (the loop's case), and random positions in the
workspace (+-60 mm) with random fields, forces and previous currents, some of them beyond the current, power
and slew limits. Saved per request: field and gradient per ampere, currents, scale, limited_by code.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.getcwd())


def dump(out: str) -> None:
    from appliance.benchmarking import _control_chain
    from appliance.control.allocation import _LIMITED_BY

    follower, safety, allocator = _control_chain()
    model = allocator.model
    rng = np.random.default_rng(14)
    rows: dict[str, list] = {k: [] for k in ("position", "field_pa", "gradient_pa", "currents", "scale", "code")}
    commanded = np.zeros(model.n)
    dt = 1.0 / 30
    requests = []
    for n in range(300):
        t = n * dt
        centroid = follower.points[5] + np.array([0.5 * np.sin(n), 0.3, 0.2]) + follower.tangent_at(0.0) * 0.3 * n
        command = follower.command(centroid, np.array([1.0, 0.1, 0.0]), t)
        decision = safety.update(t, True, command.field_T, command.force_N, 1.0)
        requests.append((centroid, decision.field_T, decision.force_N, 1e-3, None))
    for _ in range(300):
        position = rng.uniform(-60.0, 60.0, 3)
        field = rng.normal(0.0, 1.5e-3, 3) * rng.choice([0.3, 1.0, 5.0])
        force = rng.normal(0.0, 2e-4, 3) * rng.choice([0.0, 1.0, 10.0])
        previous = rng.normal(0.0, 3.0, model.n)
        requests.append((position, field, force, 1e-3, previous))
    requests.append((np.zeros(3), np.array([0.0, 0.0, 1.5e-3]), np.zeros(3), 1e-3, None))
    for position, field, force, moment, previous in requests:
        prev = commanded if previous is None else previous
        allocation = allocator.allocate_aligned(tuple(position.tolist()), tuple(field.tolist()),
                                                tuple(force.tolist()), moment, prev, dt)
        if previous is None:
            commanded = allocation.currents_a
        b, g = model.field_and_gradient_per_amp(position)
        rows["position"].append(position)
        rows["field_pa"].append(b)
        rows["gradient_pa"].append(g)
        rows["currents"].append(allocation.currents_a)
        rows["scale"].append(allocation.scale)
        rows["code"].append(_LIMITED_BY.index(allocation.limited_by))
    np.savez(out, **{k: np.asarray(v) for k, v in rows.items()})


def compare(a_path: str, b_path: str) -> None:
    a, b = np.load(a_path), np.load(b_path)
    assert np.array_equal(a["position"], b["position"])
    for key in ("field_pa", "gradient_pa", "currents"):
        x, y = a[key], b[key]
        scale = np.abs(x).reshape(len(x), -1).max(axis=1)
        rel = np.abs(x - y).reshape(len(x), -1).max(axis=1) / np.where(scale > 0, scale, 1.0)
        print(f"{key:<12} identical {int((rel == 0).sum())}/{len(x)}  max |diff|/max|value| per request: "
              f"median {np.median(rel):.2e}  max {rel.max():.2e}  (request {int(rel.argmax())})")
    ds = np.abs(a["scale"] - b["scale"])
    print(f"scale        identical {int((ds == 0).sum())}/{len(ds)}  max |diff| {ds.max():.2e}")
    print(f"limited_by   equal {int((a['code'] == b['code']).sum())}/{len(ds)}; codes {np.bincount(a['code'], minlength=5)}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("out", nargs="?")
    ap.add_argument("--compare", nargs=2)
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
    else:
        dump(args.out)
