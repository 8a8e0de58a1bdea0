"""Per view with elongation < 1.3 (cold frames): 2D axis error vs the truth's projection, and its sigma.
study.py SEEDS(1-12 or a,b) ROBOTS(1,2,..) OUT.json"""
import sys, math, json, time
sys.path.insert(0, '.')
import numpy as np
from benchmarks import accuracy as A
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.recognition import reconstruction as R

def parse(s):
    out = []
    for part in s.split(','):
        if '-' in part:
            a, b = map(int, part.split('-')); out += list(range(a, b + 1))
        else:
            out.append(int(part))
    return out
seeds, rids, path = parse(sys.argv[1]), parse(sys.argv[2]), sys.argv[3]
robots, views, cal, phantom, imaging = A.benchmark_scene()
rows = []
cap = []
orig = R._reconstruct_weighted
def rw(c, fp, fq, s, prev):
    if not cap:
        cap.append((fp, fq))
    return orig(c, fp, fq, s, prev)
R._reconstruct_weighted = rw
t0 = time.time()
for seed in seeds:
    for rid in rids:
        spec = robots[rid]
        poses = A.random_poses(np.random.default_rng([seed, rid]), 30)
        body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
        r = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + rid)
        tr = PostureTracker(cal, RecognitionSettings(dark_level=imaging.dark_level), body=spec)
        for k in range(30):
            pair = r.render(poses[k])
            tr._track = None
            cap.clear()
            post = tr.process(pair.images['p'], pair.images['q'], frame=0, t=0.0)
            if not cap:
                continue
            for name, f in zip('pq', cap[0]):
                e = f.eigenvalues[0] / max(f.eigenvalues[1], 1e-9)
                if e >= 1.3:
                    continue
                v = cal.views[name]
                hp, tp = v.project(np.array([pair.head_mm]))[0], v.project(np.array([pair.tail_mm]))[0]
                a = (hp - tp) / np.linalg.norm(hp - tp)
                err = math.degrees(math.acos(min(1.0, abs(float(a @ f.axis)))))
                rows.append(dict(seed=seed, robot=rid, pose=k, view=name, elong=e, sigma=math.degrees(f.axis_sigma_rad or 0),
                                 err2d=err, len_px=float(np.linalg.norm(hp - tp))))
    json.dump(rows, open(path, 'w'))
print('frames done in', time.time() - t0, file=sys.stderr)
json.dump(rows, open(path, 'w'))
