"""Trace one cold frame through the tracker's stages: trace.py SEED ROBOT POSE [SEED ROBOT POSE ...]."""
import sys, math
sys.path.insert(0, '.')
import numpy as np
from benchmarks import accuracy as A
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.recognition import tracker as T, reconstruction as R

robots, views, cal, phantom, imaging = A.benchmark_scene()
args = list(map(int, sys.argv[1:]))
def ang(d, t):
    if d is None: return float('nan')
    return math.degrees(math.acos(min(1, abs(float(np.dot(d, t)) / np.linalg.norm(d)))))
for j in range(0, len(args), 3):
    seed, rid, k = args[j:j + 3]
    spec = robots[rid]
    poses = A.random_poses(np.random.default_rng([seed, rid]), 30)
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    r = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + rid)
    for i in range(k + 1):
        pair = r.render(poses[i])
    truth = poses[k].direction
    print(f'=== seed {seed} robot {rid} pose {k}; truth dir {truth}, L {spec.length_mm} D {spec.diameter_mm}')
    for name in 'pq':
        v = cal.views[name]
        hp, tp = v.project(np.array([pair.head_mm]))[0], v.project(np.array([pair.tail_mm]))[0]
        cen = v.project(np.array([poses[k].centroid_mm]))[0]
        a = (hp - tp) / np.linalg.norm(hp - tp)
        print(f'  truth {name}: head {hp.round(2)} tail {tp.round(2)} len {np.linalg.norm(hp-tp):.1f}px axis {a.round(4)} c {cen.round(2)}')
    import os, json
    over = json.loads(os.environ.get('OVER', '{}'))
    tr = PostureTracker(cal, RecognitionSettings(dark_level=imaging.dark_level, **over), body=spec)
    stages = ['_head_by_clean_view', '_head_in_doubt', '_head_by_body', '_mirror_by_body', '_axis_by_length']
    def wrap(nm, f):
        def g(rec, *a, **kw):
            out = f(rec, *a, **kw)
            print(f'  {nm:22s} err {ang(out.direction, truth):6.2f} deg amb {out.ambiguous} sigma {math.degrees(out.axis_sigma_rad or 0):.2f} reasons {out.reasons}')
            return out
        return g
    for nm in stages:
        setattr(tr, nm, wrap(nm, getattr(tr, nm)))
    orig_rw = R._reconstruct_weighted
    def rw(cal_, fp, fq, s, prev):
        out = orig_rw(cal_, fp, fq, s, prev)
        print(f'  reconstruct(mve {s.min_view_elongation}) err {ang(out.direction, truth):6.2f} sigma {math.degrees(out.axis_sigma_rad or 0):.2f} plane {out.plane_angle_deg:.2f} amb {out.ambiguous} {out.reasons}')
        for name, f in (('p', fp), ('q', fq)):
            print(f'     {name}: c {f.centroid.round(2)} axis {f.axis.round(4)} elong {f.eigenvalues[0]/f.eigenvalues[1]:.3f} eig {np.round(f.eigenvalues,2)} sig {math.degrees(f.axis_sigma_rad or 0):.2f} tips {f.tips.round(2).tolist()} head {f.head_index}')
        return out
    R._reconstruct_weighted = rw
    odc = T.declutter
    def dc(*a, **kw):
        out = odc(*a, **kw)
        print(f'  declutter              err {ang(out.direction, truth):6.2f}')
        return out
    T.declutter = dc
    post = tr.process(pair.images['p'], pair.images['q'], frame=0, t=0.0)
    R._reconstruct_weighted = orig_rw; T.declutter = odc
    rec = post.to_record()
    print('  FINAL', A.score(rec, poses[k], pair.head_mm, pair.tail_mm))
    print('  tips', np.round(post.tips_mm, 2).tolist(), 'truth', np.round(pair.head_mm, 2).tolist(), np.round(pair.tail_mm, 2).tolist())
