"""Offline: the body placed by the two views' tails triangulated, vs the posture's: tailtri.py SEED ROBOT POSE ..."""
import sys, math
sys.path.insert(0, '.')
import numpy as np
from benchmarks import accuracy as A
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.geometry import triangulate
from appliance.recognition.body_prior import BodyModel
robots, views, cal, phantom, imaging = A.benchmark_scene()
args = list(map(int, sys.argv[1:]))
for j in range(0, len(args), 3):
    seed, rid, k = args[j:j + 3]
    spec = robots[rid]; bm = BodyModel.of(spec)
    poses = A.random_poses(np.random.default_rng([seed, rid]), 30)
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    r = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + rid)
    for i in range(k + 1):
        pair = r.render(poses[i])
    tr = PostureTracker(cal, RecognitionSettings(dark_level=imaging.dark_level), body=spec)
    post = tr.process(pair.images['p'], pair.images['q'], frame=0, t=0.0)
    tc = poses[k].centroid_mm
    d = post.direction
    tails = np.array([post.views['p'].tips_px[1]]), np.array([post.views['q'].tips_px[1]])
    heads = np.array([post.views['p'].tips_px[0]]), np.array([post.views['q'].tips_px[0]])
    T = triangulate(cal.p, cal.q, tails[0], tails[1], optimal=True)[0]
    H = triangulate(cal.p, cal.q, heads[0], heads[1], optimal=True)[0]
    c0 = post.centroid_mm
    # place along the posture's axis by the triangulated tail
    b = float((T - c0) @ d) + bm.centroid_from_tail_mm
    c_tail = c0 + b * d
    print(f'{seed} r{rid} p{k}: head_id {post.head_identified} posture c err {np.linalg.norm(c0 - tc):.3f} along {(c0-tc)@poses[k].direction:+.3f}; '
          f'tri tail err {np.linalg.norm(T - pair.tail_mm):.3f} (along {(T-pair.tail_mm)@poses[k].direction:+.3f}); tri head err {np.linalg.norm(H-pair.head_mm):.3f}; '
          f'placed by tri tail: c err {np.linalg.norm(c_tail - tc):.3f}; tri tail off axis {np.linalg.norm((T-c0) - ((T-c0)@d)*d):.3f} mm')
