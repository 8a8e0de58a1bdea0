"""Where robot 4's axis error comes from (round 11, issue 2; a diagnostic, asserts nothing).

Usage: ``python benchmarks/robot4_axis_study.py OUT.json SEED [SEED ...]`` (cold path, frames as
``benchmarks/accuracy.py --robots 4`` renders them). Per frame: each view's 2D axis error against the projected
true axis (deg, signed), its axis sigma, the blob's elongation; the 3D axis from the two measured axis planes, from
the true 2D axes through the measured centroids, and from one view measured / the other true; the posture's final
axis error and its flags.
"""
import json
import math
import sys

import numpy as np

sys.path.insert(0, '.')
import benchmarks.accuracy as acc  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.robots import load_robots  # noqa: E402
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody  # noqa: E402


def line_angle(a, b):
    c = abs(float(np.dot(a, b)) / np.linalg.norm(a) / np.linalg.norm(b))
    return math.degrees(math.acos(min(c, 1.0)))


def signed_2d(axis, true_axis):
    if np.dot(axis, true_axis) < 0:
        axis = -axis
    return math.degrees(math.atan2(true_axis[0] * axis[1] - true_axis[1] * axis[0], float(np.dot(axis, true_axis))))


def plane(view, c, a):
    return np.asarray(view.backproject_plane(c - 5.0 * a, c + 5.0 * a))[:3]


def main():
    out_path, seeds = sys.argv[1], [int(s) for s in sys.argv[2:]]
    robots, views, cal, phantom, imaging = acc.benchmark_scene()
    spec = robots[4]
    rows = []
    for seed in seeds:
        poses = acc.random_poses(np.random.default_rng([seed, 4]), 30)
        body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
        renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + 4)
        tr = PostureTracker(cal, RecognitionSettings(dark_level=imaging.dark_level), body=spec)
        found = {}
        orig = tr._search_full

        def sf(images, timings, orig=orig, found=found):
            r = orig(images, timings)
            found['r'] = r
            return r
        tr._search_full = sf
        for i, pose in enumerate(poses):
            pair = renderer.render(pose)
            tr.reset()
            found.clear()
            post = tr.process(pair.images['p'], pair.images['q'], frame=i, t=0.0)
            rec = acc.score(post.to_record(), pose, pair.head_mm, pair.tail_mm)
            row = {'seed': seed, 'pose': i, 'ok': rec['ok'], 'ambiguous': rec['ambiguous'], 'axis_deg': rec['axis_deg'],
                   'reason': rec['reason']}
            try:
                (blobs, feats), _ = found['r']
            except (KeyError, TypeError, ValueError):
                rows.append(row)
                continue
            normals_m, normals_t = {}, {}
            for name in 'pq':
                f, t, b = feats[name], pair.truth[name], blobs[name]
                ta = np.asarray(t.head_px - t.tail_px, float)
                row[f'len_{name}'] = float(np.linalg.norm(ta))
                ta /= np.linalg.norm(ta)
                row[f'err2d_{name}'] = signed_2d(np.asarray(f.axis), ta)
                row[f'sig2d_{name}'] = None if f.axis_sigma_rad is None else math.degrees(f.axis_sigma_rad)
                row[f'elong_{name}'] = math.sqrt(f.eigenvalues[0] / max(f.eigenvalues[1], 1e-9))
                row[f'clutter_{name}'] = float(b.clutter)
                row[f'width_{name}'] = float(b.width_px)
                view = cal.views[name]
                normals_m[name] = plane(view, np.asarray(f.centroid), np.asarray(f.axis))
                normals_t[name] = plane(view, np.asarray(f.centroid), ta)
            for label, (np_, nq) in {'mm': (normals_m['p'], normals_m['q']), 'tt': (normals_t['p'], normals_t['q']),
                                     'mt': (normals_m['p'], normals_t['q']), 'tm': (normals_t['p'], normals_m['q'])}.items():
                row[f'axis3d_{label}'] = line_angle(np.cross(np_, nq), pose.direction)
            row['planes_deg'] = line_angle(normals_t['p'], normals_t['q'])
            rows.append(row)
        print(seed, file=sys.stderr)
    json.dump(rows, open(out_path, 'w'), indent=0)


if __name__ == '__main__':
    main()
