"""The true scene of the simulated biplane X-ray system: view geometry, the robot's solid, phantoms.

This is the device-side truth that the loopback frame grabber renders from; the appliance never sees
it and only knows what it calibrated. Everything here is in millimetres, in the world frame whose
origin is the isocentre and whose ``z`` axis points up (the C-arm's vertical rotation axis).

The solids are convex pieces (cylinder, cone, sphere, mitred tube segment) described by a few
scalars, so the chord a ray cuts through each is found in closed form for millions of rays at once:
every ray ``X(s) = S + s*D`` leaves one source ``S`` with a unit direction ``D``; a convex piece is
the intersection of a quadric ``{a s^2 + b s + c <= 0}`` with half-spaces, so its chord is the
length of an interval intersection. Only two dot products per ray are needed (``D.u`` and
``D.o_perp``), which is what makes per-frame rendering cheap.

Not modelled: scatter, beam hardening (attenuation coefficients are effective values), focal-spot
size (use the detector blur), and objects behind the source.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# A conical head may take at most this share of the body's length, so a stubby robot with a blunt
# angle (robot 4 of the seed paper: 3 mm long, 1.5 mm wide, 30 degrees) keeps a cylinder; the cone
# then gets wider than the nominal angle. ``appliance.robots`` uses the same rule.
MAX_CONE_FRACTION = 0.8


# ----------------------------------------------------------------------------------------- views
@dataclass(frozen=True)
class TrueView:
    """One X-ray source/detector pair, OpenCV pinhole convention: ``x_cam = R X + t``, ``px = K x``.

    ``dist`` is OpenCV's (k1, k2, p1, p2, k3). Pixel centres sit at integer coordinates.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple[int, int]  # (w, h)

    def __post_init__(self) -> None:
        for key, shape in (("K", (3, 3)), ("dist", (5,)), ("R", (3, 3)), ("t", (3,))):
            value = np.asarray(getattr(self, key), dtype=float)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"view {self.name}: {key} must be a finite array of shape {shape}")
            value.setflags(write=False)
            object.__setattr__(self, key, value)
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-9) or np.linalg.det(self.R) < 0:
            raise ValueError(f"view {self.name}: R is not a rotation")
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    @property
    def source_mm(self) -> np.ndarray:
        """The X-ray source (camera centre) in world coordinates."""
        return -self.R.T @ self.t

    def to_camera(self, points_mm: np.ndarray) -> np.ndarray:
        return np.asarray(points_mm, dtype=float).reshape(-1, 3) @ self.R.T + self.t

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply OpenCV's radial-tangential model to normalized coordinates (N,2)."""
        if not self.has_distortion:
            return xy
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, points_mm: np.ndarray) -> np.ndarray:
        """World points (N,3) to pixels (N,2), with distortion. Points behind the source give NaN."""
        cam = self.to_camera(points_mm)
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = cam[:, :2] / cam[:, 2:3]
        xy[cam[:, 2] <= 0] = np.nan
        xy = self.distort_normalized(xy)
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def undistort_normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels (N,2) to ideal normalized coordinates (N,2): the inverse of K and distortion.

        Distortion is inverted by the fixed-point iteration OpenCV uses, run to convergence
        (mild distortion converges in a handful of steps)."""
        pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        k_inv = np.linalg.inv(self.K)
        xd = pts @ k_inv[:2, :2].T + k_inv[:2, 2]
        if not self.has_distortion:
            return xd
        k1, k2, p1, p2, k3 = self.dist
        x, y = xd[:, 0].copy(), xd[:, 1].copy()
        for _ in range(100):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x_new = (xd[:, 0] - 2.0 * p1 * x * y - p2 * (r2 + 2.0 * x * x)) / radial
            y_new = (xd[:, 1] - p1 * (r2 + 2.0 * y * y) - 2.0 * p2 * x * y) / radial
            step = max(float(np.max(np.abs(x_new - x), initial=0.0)),
                       float(np.max(np.abs(y_new - y), initial=0.0)))
            x, y = x_new, y_new
            if step < 1e-13:
                break
        return np.stack([x, y], axis=1)

    def pixel_rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit world directions (N,3) of the rays from the source through pixels (N,2)."""
        xy = self.undistort_normalized(pixels)
        cam = np.hstack([xy, np.ones((len(xy), 1))])
        cam /= np.linalg.norm(cam, axis=1, keepdims=True)
        return cam @ self.R


def _look_at_rotation(source: np.ndarray) -> np.ndarray:
    """Rotation whose optical axis points from ``source`` to the isocentre, image 'down' = world -z."""
    z_cam = -source / np.linalg.norm(source)
    down = np.array([0.0, 0.0, -1.0])
    y_cam = down - (down @ z_cam) * z_cam
    if np.linalg.norm(y_cam) < 1e-9:
        raise ValueError("a view looking straight down the vertical axis is not supported")
    y_cam /= np.linalg.norm(y_cam)
    x_cam = np.cross(y_cam, z_cam)
    return np.vstack([x_cam, y_cam, z_cam])


def biplane_views(*, sod_mm: float = 500.0, sdd_mm: float = 1000.0,
                  fov_mm: tuple[float, float] = (150.0, 130.0),
                  image_size: tuple[int, int] = (768, 672), separation_deg: float = 90.0,
                  elevation_deg: float = 0.0,
                  dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0),
                  ) -> dict[str, TrueView]:
    """The true geometry of a biplane system, views ``"p"`` and ``"q"``.

    Both sources sit ``sod_mm`` from the isocentre (world origin) and look at it. Plane p's source is
    on the world's -x axis; plane q's is rotated about the vertical (z) axis by ``separation_deg`` and
    raised by ``elevation_deg``. ``fov_mm`` is the field of view measured at the isocentre, which
    fixes the focal length in pixels (``f = w * sod / fov_w``); ``sdd_mm`` only sets the physical
    detector pixel pitch (``fov_w * sdd / sod / w``) and so does not change the images.
    """
    if sod_mm <= 0 or sdd_mm <= sod_mm:
        raise ValueError(f"need 0 < sod_mm < sdd_mm, got sod_mm={sod_mm}, sdd_mm={sdd_mm}")
    w, h = int(image_size[0]), int(image_size[1])
    if w < 8 or h < 8 or fov_mm[0] <= 0 or fov_mm[1] <= 0:
        raise ValueError(f"bad image_size {image_size} or fov_mm {fov_mm}")
    K = np.array([[w * sod_mm / fov_mm[0], 0.0, (w - 1) / 2.0],
                  [0.0, h * sod_mm / fov_mm[1], (h - 1) / 2.0],
                  [0.0, 0.0, 1.0]])
    views = {}
    for name, azimuth, elevation in (("p", 0.0, 0.0), ("q", separation_deg, elevation_deg)):
        az, el = math.radians(azimuth), math.radians(elevation)
        source = -sod_mm * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                     -math.sin(el)])
        R = _look_at_rotation(source)
        views[name] = TrueView(name=name, K=K.copy(), dist=np.array(dist, dtype=float), R=R,
                               t=-R @ source, image_size=(w, h))
    return views


# ---------------------------------------------------------------------------------------- solids
@dataclass(frozen=True)
class RobotBody:
    """Cylinder with a conical head, axis along +z of the body frame, head (apex) at +z.

    The body frame's origin is the solid's volume centroid. ``tip_angle_deg`` is the full apex angle
    of the cone; its length is ``(D/2) / tan(angle/2)``, capped at ``MAX_CONE_FRACTION * L``.
    """

    length_mm: float
    diameter_mm: float
    tip_angle_deg: float
    attenuation_per_mm: float
    cone_length_mm: float = field(init=False)
    volume_mm3: float = field(init=False)
    centroid_from_tail_mm: float = field(init=False)

    def __post_init__(self) -> None:
        if not (self.length_mm > 0 and self.diameter_mm > 0 and self.attenuation_per_mm >= 0):
            raise ValueError(f"robot body needs positive sizes, got {self}")
        if not 0 < self.tip_angle_deg < 180:
            raise ValueError(f"tip_angle_deg must be in (0, 180), got {self.tip_angle_deg}")
        r = self.diameter_mm / 2.0
        h = min(r / math.tan(math.radians(self.tip_angle_deg) / 2.0), MAX_CONE_FRACTION * self.length_mm)
        cyl = self.length_mm - h
        v_cyl, v_cone = math.pi * r * r * cyl, math.pi * r * r * h / 3.0
        # A cone's centroid is a quarter of its height above its base.
        z_c = (v_cyl * cyl / 2.0 + v_cone * (cyl + h / 4.0)) / (v_cyl + v_cone)
        object.__setattr__(self, "cone_length_mm", h)
        object.__setattr__(self, "volume_mm3", v_cyl + v_cone)
        object.__setattr__(self, "centroid_from_tail_mm", z_c)

    @classmethod
    def from_spec(cls, spec: object) -> "RobotBody":
        """From anything with ``length_mm``, ``diameter_mm``, ``tip_angle_deg`` and
        ``attenuation_per_mm`` (such as a catalogue entry of ``config/robots.yaml``)."""
        return cls(**{name: float(getattr(spec, name)) for name in
                      ("length_mm", "diameter_mm", "tip_angle_deg", "attenuation_per_mm")})

    @property
    def radius_mm(self) -> float:
        return self.diameter_mm / 2.0

    @property
    def head_offset_mm(self) -> float:
        """Apex position along the axis, from the centroid (positive)."""
        return self.length_mm - self.centroid_from_tail_mm

    @property
    def tail_offset_mm(self) -> float:
        """Tail-face centre along the axis, from the centroid (negative)."""
        return -self.centroid_from_tail_mm

    @property
    def head_body_mm(self) -> np.ndarray:
        """The apex in the body frame (origin at the centroid, axis +z)."""
        return np.array([0.0, 0.0, self.head_offset_mm])

    @property
    def tail_body_mm(self) -> np.ndarray:
        """The tail face's centre in the body frame."""
        return np.array([0.0, 0.0, self.tail_offset_mm])


@dataclass(frozen=True)
class RobotPose:
    """Where the robot is: its volume centroid in world mm and its unit axis, tail -> head."""

    centroid_mm: np.ndarray
    direction: np.ndarray

    def __post_init__(self) -> None:
        c = np.asarray(self.centroid_mm, dtype=float).reshape(3)
        d = np.asarray(self.direction, dtype=float).reshape(3)
        n = float(np.linalg.norm(d))
        if not (np.all(np.isfinite(c)) and np.isfinite(n) and n > 1e-9):
            raise ValueError(f"robot pose needs a finite centroid and a non-zero direction, got {c}, {d}")
        c.setflags(write=False)
        d = d / n
        d.setflags(write=False)
        object.__setattr__(self, "centroid_mm", c)
        object.__setattr__(self, "direction", d)

    def head_mm(self, body: RobotBody) -> np.ndarray:
        return self.centroid_mm + body.head_offset_mm * self.direction

    def tail_mm(self, body: RobotBody) -> np.ndarray:
        return self.centroid_mm + body.tail_offset_mm * self.direction


@dataclass(frozen=True)
class VesselPhantom:
    """A contrast-filled tube of constant radius along a 3D polyline centreline (N,3), in mm.

    Consecutive segments meet at mitre planes (the bisector of the two tangents), so the tube is an
    exact union without overlaps as long as each bend's radius of curvature exceeds the tube radius.
    """

    centreline_mm: np.ndarray
    radius_mm: float
    attenuation_per_mm: float

    def __post_init__(self) -> None:
        pts = np.asarray(self.centreline_mm, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.all(np.isfinite(pts)):
            raise ValueError("vessel centreline must be a finite (N>=2, 3) array")
        keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]
        pts = pts[keep]
        if len(pts) < 2 or self.radius_mm <= 0 or self.attenuation_per_mm < 0:
            raise ValueError("vessel needs two distinct points, radius_mm > 0, attenuation_per_mm >= 0")
        pts.setflags(write=False)
        object.__setattr__(self, "centreline_mm", pts)

    def distance_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Distance of points (N,3) from the centreline (N,); inside the lumen where <= radius."""
        p = np.asarray(points_mm, dtype=float).reshape(-1, 1, 3)
        a, b = self.centreline_mm[:-1], self.centreline_mm[1:]
        ab = b - a
        t = np.clip(np.einsum("nsk,sk->ns", p - a, ab) / np.einsum("sk,sk->s", ab, ab), 0.0, 1.0)
        closest = a + t[..., None] * ab
        return np.linalg.norm(p - closest, axis=-1).min(axis=1)

    def segments(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Per segment: start, end, and the outward normals of its start and end mitre planes."""
        pts = self.centreline_mm
        tang = np.diff(pts, axis=0)
        tang /= np.linalg.norm(tang, axis=1, keepdims=True)
        joints = [tang[0]] + [_unit(tang[i - 1] + tang[i]) for i in range(1, len(tang))] + [tang[-1]]
        return [(pts[i], pts[i + 1], joints[i], joints[i + 1]) for i in range(len(tang))]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n < 1e-9:
        raise ValueError("vessel centreline folds back on itself")
    return v / n


# --------------------------------------------------------------------------- closed-form chords
# Intervals of the ray parameter s are (lo, hi) arrays; empty ones have lo >= hi. Infinite bounds
# and IEEE arithmetic stand in for special cases (a ray parallel to a slab gets +-inf from 1/0), and
# fmin/fmax ignore the NaN of a measure-zero 0*inf, so the hot path has almost no branches.
def _roots(a: np.ndarray, half_b: np.ndarray, c: np.ndarray | float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted roots of ``a s^2 + 2 half_b s + c`` in the cancellation-free form, and where real."""
    disc = half_b * half_b - a * c
    real = disc >= 0.0
    k = -(half_b + np.copysign(np.sqrt(np.maximum(disc, 0.0)), half_b))
    r1 = k / a
    r2 = c / k
    return np.fmin(r1, r2), np.fmax(r1, r2), real


def _length(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Length of the part of [lo, hi] in front of the source (s >= 0); 0 if empty."""
    return np.fmax(hi - np.fmax(lo, 0.0), 0.0)


def _halfspace(dn: np.ndarray, on: float) -> tuple[np.ndarray, np.ndarray]:
    """Interval of s with ``on + s*dn >= 0``."""
    s0 = -on / dn
    lo = np.where(dn > 0.0, s0, -np.inf)
    hi = np.where(dn < 0.0, s0, np.inf)
    if on < 0.0:                       # source outside: a ray parallel to the plane never enters
        lo = np.where(dn == 0.0, np.inf, lo)
    return lo, hi


def _infinite_cylinder(dpar: np.ndarray, q: np.ndarray, operp2: float, r: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Interval inside an infinite cylinder of radius r about the axis (rays of unit direction)."""
    a = 1.0 - dpar * dpar
    lo, hi, real = _roots(a, q, operp2 - r * r)
    lo = np.where(real, lo, np.inf)
    parallel = a < 1e-14               # a ray along the axis is all in or all out
    if np.any(parallel):
        lo = np.where(parallel, -np.inf if operp2 <= r * r else np.inf, lo)
        hi = np.where(parallel, np.inf, hi)
    return lo, hi


def _axial_terms(source: np.ndarray, base: np.ndarray, axis: np.ndarray
                 ) -> tuple[float, np.ndarray, float]:
    """The source relative to an axis through ``base``: axial coordinate, perpendicular offset and
    its squared length."""
    o = source - base
    opar = float(o @ axis)
    operp = o - opar * axis
    return opar, operp, float(operp @ operp)


def robot_chords(body: RobotBody, pose: RobotPose, source: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Path length (mm) through the robot of rays from ``source`` along unit ``dirs`` (..., 3)."""
    u = pose.direction
    opar, operp, operp2 = _axial_terms(source, pose.tail_mm(body), u)
    return robot_chords_from_dots(body, opar, operp2, dirs @ u, dirs @ operp)


def robot_chords_from_dots(body: RobotBody, opar: float, operp2: float, dpar: np.ndarray,
                           q: np.ndarray) -> np.ndarray:
    """Chords from the two per-ray dot products (see module doc). ``opar``, ``operp2``: the source's
    axial coordinate relative to the tail face and squared distance from the axis; ``dpar = D.u``,
    ``q = D.o_perp``. Any array shapes that broadcast."""
    r = body.radius_mm
    h = body.cone_length_mm
    cyl_len = body.length_mm - h
    dpar, q = np.broadcast_arrays(dpar, q)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = 1.0 / dpar
        # Where the ray crosses the tail face, the cone's base plane and the apex plane.
        t0, t1, t2 = -opar * inv, (cyl_len - opar) * inv, (body.length_mm - opar) * inv
        lo, hi = _infinite_cylinder(dpar, q, operp2, r)
        total = _length(np.fmax(lo, np.fmin(t0, t1)), np.fmin(hi, np.fmax(t0, t1)))
        # Cone: rho^2 <= k^2 (L - z)^2, a double cone; the slab cyl_len <= z <= L keeps one nappe.
        k2 = (r / h) ** 2
        w = body.length_mm - opar
        big_a = (1.0 - dpar * dpar) - k2 * dpar * dpar
        s1, s2, real = _roots(big_a, q + k2 * w * dpar, operp2 - k2 * w * w)
        slab_lo, slab_hi = np.fmin(t1, t2), np.fmax(t1, t2)
        # big_a > 0: inside between the roots. big_a < 0: the ray is steeper than the cone's
        # flank and is inside outside the roots (one piece per nappe; the slab keeps one).
        inner = np.where(real, _length(np.fmax(slab_lo, s1), np.fmin(slab_hi, s2)), 0.0)
        outer = np.where(real, _length(slab_lo, np.fmin(slab_hi, s1))
                         + _length(np.fmax(slab_lo, s2), slab_hi), _length(slab_lo, slab_hi))
        total += np.where(big_a > 0.0, inner, outer)
    return total


def sphere_chords(centre: np.ndarray, radius: float, source: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Path length through a sphere of rays from ``source`` along unit ``dirs`` (..., 3)."""
    o = source - np.asarray(centre, dtype=float)
    b = dirs @ o
    disc = b * b - (o @ o - radius * radius)
    # b < 0: the sphere lies in front of the source.
    return np.where((disc > 0) & (b < 0), 2.0 * np.sqrt(np.maximum(disc, 0.0)), 0.0)


def tube_segment_chords(start: np.ndarray, end: np.ndarray, n_start: np.ndarray, n_end: np.ndarray,
                        radius: float, source: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Path length through one mitred tube segment (see :class:`VesselPhantom`): an infinite
    cylinder about the segment, cut by the start plane (normal ``n_start``, kept ahead of it) and
    the end plane (normal ``n_end``, kept behind it)."""
    axis = _unit(end - start)
    opar, operp, operp2 = _axial_terms(source, start, axis)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lo, hi = _infinite_cylinder(dirs @ axis, dirs @ operp, operp2, radius)
        s_lo, s_hi = _halfspace(dirs @ n_start, float((source - start) @ n_start))
        e_lo, e_hi = _halfspace(-(dirs @ n_end), float(-((source - end) @ n_end)))
        return _length(np.fmax(lo, np.fmax(s_lo, e_lo)), np.fmin(hi, np.fmin(s_hi, e_hi)))


def vessel_chords(vessel: VesselPhantom, source: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Path length through the whole vessel phantom (sum over its non-overlapping segments)."""
    total = np.zeros(dirs.shape[:-1])
    for start, end, n_start, n_end in vessel.segments():
        total += tube_segment_chords(start, end, n_start, n_end, vessel.radius_mm, source, dirs)
    return total
