"""ab.py OUT MODE SEED [ROBOTS]: the weighted estimator's variants v1 (this tree) and v2 (min_view_elongation 1.15)
on accuracy.py's frames of one seed (MODE cold or tracked), scores as accuracy.py's per-frame JSON."""
import sys, json
sys.path.insert(0, '.')
import numpy as np
from benchmarks import accuracy as A
out, mode, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
robots_sel = [int(r) for r in sys.argv[4].split(',')] if len(sys.argv) > 4 else None
robots, views, cal, phantom, imaging = A.benchmark_scene()
res = {}
for rid, spec in robots.items():
    if robots_sel and rid not in robots_sel:
        continue
    poses = A.random_poses(np.random.default_rng([seed, rid]), 30)
    scores, _ = A.run_robot(rid, spec, poses, seed, cal, views, phantom, imaging, tracked=(mode == 'tracked'),
                            variants={'v3': {}})
    res[str(rid)] = scores
json.dump(res, open(out, 'w'), default=float)
