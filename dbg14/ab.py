"""In-process A/B on accuracy.py's frames: ab.py SEEDS ROBOTS cold|tracked OUT.json  (env A, B: settings JSON).
Prints per-frame changes (axis, centroid, tips, flag) and both variants' summaries (weighted)."""
import sys, os, json
sys.path.insert(0, '.')
import numpy as np
from benchmarks import accuracy as A
from appliance.compiled import warm_up_all
from appliance.robots import load_robots

def parse(s):
    out = []
    for part in s.split(','):
        if '-' in part:
            a, b = map(int, part.split('-')); out += list(range(a, b + 1))
        else:
            out.append(int(part))
    return out
seeds, rids, mode, path = parse(sys.argv[1]), parse(sys.argv[2]), sys.argv[3], sys.argv[4]
V = json.loads(os.environ['V'])  # {name: settings}, the first the reference
warm_up_all()
robots = load_robots()
views = A.biplane_views()
cal = A.true_calibration(views)
phantom = A.VesselPhantom(A.smooth_centreline(A.S_BEND_CENTRELINE_MM), A.VESSEL_RADIUS_MM, A.VESSEL_ATTENUATION_PER_MM)
imaging = A.ImagingSettings()
res = {}
def tipr(x):
    t = x.get('tips_mm')
    return max(t) if t else None
for seed in seeds:
    for rid in rids:
        poses = A.random_poses(np.random.default_rng([seed, rid]), 30)
        scores, _ = A.run_robot(rid, robots[rid], poses, seed, cal, views, phantom, imaging, tracked=(mode == 'tracked'),
                                variants=V)
        res[f'{seed}/{rid}'] = {k: v for k, v in scores.items()}
        names = list(V)
        for other in names[1:]:
            for i, (x, y) in enumerate(zip(scores[names[0]], scores[other])):
                if (x['ok'] != y['ok'] or x['ambiguous'] != y['ambiguous'] or x.get('axis_deg') != y.get('axis_deg')
                        or x.get('centroid_mm') != y.get('centroid_mm')):
                    f = lambda v: 'None' if v is None else f'{v:.3f}'
                    print(f"[{other}] {mode} {seed} r{rid} p{i}: amb {x['ambiguous']}->{y['ambiguous']} axis {f(x.get('axis_deg'))}->{f(y.get('axis_deg'))} "
                          f"c {f(x.get('centroid_mm'))}->{f(y.get('centroid_mm'))} tipmax {f(tipr(x))}->{f(tipr(y))} | {(y.get('reason') or '')[:110]}", flush=True)
            sa, sb = A.summarise(scores[names[0]]), A.summarise(scores[other])
            keys = ['centroid_rms_mm', 'centroid_clean_rms_mm', 'axis_median_deg', 'tips_rms_mm', 'silent_failures', 'ambiguous']
            if any(sa.get(k) != sb.get(k) for k in keys):
                print(f"  [{other}] summary {mode} {seed} r{rid}: " + ' '.join(f"{k} {sa.get(k):.4g}->{sb.get(k):.4g}" if isinstance(sa.get(k), float) else f"{k} {sa.get(k)}->{sb.get(k)}" for k in keys), flush=True)
json.dump(res, open(path, 'w'))
