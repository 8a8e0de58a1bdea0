"""One frame of the accuracy benchmark studied stage by stage against the truth (a diagnostic; asserts nothing).

Usage: ``python benchmarks/frame_study.py SEED ROBOT POSE [VESSEL_MU]`` (cold path, as ``benchmarks/accuracy.py``
renders it). ``VESSEL_MU`` 0 renders the same frame, same noise, without the vessel's contrast: where the
error goes away, the vessel made it. Prints each view's image centroid and ends against their projections,
the centroid error along and across the image axis, each correction's reconstruction, and the two blobs'
integrated attenuation times the pixel area at the object (mm^2; the body's expected value is its
attenuation per mm times its volume).
"""
import sys, math
import numpy as np
sys.path.insert(0, '.')
import benchmarks.accuracy as acc
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.robots import load_robots
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, VesselPhantom, biplane_views
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline

seed, robot_id, idx = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
vessel_mu = float(sys.argv[4]) if len(sys.argv) > 4 else acc.VESSEL_ATTENUATION_PER_MM
robots = load_robots(); spec = robots[robot_id]
views = biplane_views(); cal = acc.true_calibration(views)
phantom = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), acc.VESSEL_RADIUS_MM, vessel_mu)
imaging = ImagingSettings()
poses = acc.random_poses(np.random.default_rng([seed, robot_id]), 30)
body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + robot_id)
for i in range(idx):
    renderer.render(poses[i])
pose = poses[idx]
pair = renderer.render(pose)
tr = PostureTracker(cal, RecognitionSettings(dark_level=imaging.dark_level), body=spec)

# instrument the stages
stages = {}
def wrap(name):
    f = getattr(tr, name)
    def g(rec, *a, **k):
        out = f(rec, *a, **k)
        stages[name] = out
        return out
    setattr(tr, name, g)
for n in ("_head_by_clean_view", "_head_in_doubt", "_head_by_body", "_mirror_by_body", "_axis_by_length"):
    wrap(n)
orig_search = tr._search_full
found = {}
def sf(images, timings):
    r = orig_search(images, timings); found['r'] = r; return r
tr._search_full = sf
post = tr.process(pair.images['p'], pair.images['q'], frame=0, t=0.0)
truth_c = pose.centroid_mm
print('truth centroid', truth_c, 'dir', pose.direction, 'head', pair.head_mm, 'tail', pair.tail_mm)
print('posture ok', post.ok, 'amb', post.ambiguous, 'centroid', post.centroid_mm, 'err', None if post.centroid_mm is None else np.linalg.norm(post.centroid_mm-truth_c))
print('reason', post.reason)
(blobs, feats), _ = found['r']
for name in 'pq':
    b, f, t = blobs[name], feats[name], pair.truth[name]
    print(f'view {name}: blob centroid {np.round(b.centroid_px,3)} feat centroid {np.round(f.centroid,3)} true {np.round(t.centroid_px,3)} '
          f'diff {np.round(np.asarray(f.centroid)-t.centroid_px,3)}; tips {np.round(f.tips,2).tolist()} true head {np.round(t.head_px,2)} tail {np.round(t.tail_px,2)}')
    print(f'   clutter {b.clutter:.3f} width {b.width_px:.2f} strength {b.strength:.1f} peak {b.peak:.3f} baseline {b.baseline:.3f} px {b.pixel_count} head_index {f.head_index} window {b.window}')
    # along/across decomposition of the centroid error
    ax = np.asarray(f.axis); d = np.asarray(f.centroid) - t.centroid_px
    print(f'   centroid err along axis {d@ax:.3f} px, across {d@np.array([-ax[1],ax[0]]):.3f} px; true image length {np.linalg.norm(t.head_px-t.tail_px):.1f}')
for k, r in stages.items():
    print(k, 'centroid', None if r.centroid is None else np.round(r.centroid,3), 'err', None if r.centroid is None else round(float(np.linalg.norm(r.centroid-truth_c)),3),
          'dir', None if r.direction is None else np.round(r.direction,4), 'head', r.head_identified, 'amb', r.ambiguous,
          'plane', r.plane_angle_deg, 'axsig', None if r.axis_sigma_rad is None else math.degrees(r.axis_sigma_rad), 'len', r.length_mm)
# triangulate the true image centroids, and the measured ones
from appliance.geometry import triangulate
X = triangulate(cal.p, cal.q, np.asarray(feats['p'].centroid), np.asarray(feats['q'].centroid), optimal=False)[0]
Xt = triangulate(cal.p, cal.q, pair.truth['p'].centroid_px, pair.truth['q'].centroid_px, optimal=False)[0]
print('triangulated measured image centroids', X, 'err', np.linalg.norm(X-truth_c), ' vec', X-truth_c)
print('triangulated true image centroids err', np.linalg.norm(Xt-truth_c))
print('err vector along true axis', (X-truth_c)@pose.direction)

w, s = tr._size_mismatch(blobs)
print('size mismatch |log width ratio|', round(w,4), '|log mass ratio|', round(s,4))
for name in 'pq':
    scale = float(np.linalg.norm(X - cal.views[name].source_mm)) / float(cal.views[name].K[0, 0])
    print(name, 'mass mm^2', blobs[name].strength * scale**2)
