"""Exact numpy ray-casting of textured planes, boxes and spheres (the renderer behind ``nvls synth``).

Rays are given in world coordinates; every primitive has a world-from-object rigid pose (rotation ``R``,
centre ``c``) so moving objects reuse the static intersection code. Textures are float32 RGB images in
[0, 1] sampled bilinearly with wrap-around at ``texels_per_unit`` texels per world unit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Rays closer than this are ignored so a camera never "hits" a surface it sits on.
_EPS = 1e-6
# Fixed light for a mild Lambert shading: surfaces facing it are brighter, which helps SIFT and realism.
_LIGHT = np.array([0.3, -0.8, -0.5]) / np.linalg.norm([0.3, -0.8, -0.5])


@dataclass
class Primitive:
    """A textured shape in its own frame.

    Attributes:
        kind: ``"plane"`` (rectangle spanning local x in [0, size[0]], y in [0, size[1]], normal +z),
            ``"box"`` (half extents ``size``, centred) or ``"sphere"`` (radius ``size[0]``).
        size: ``[3]`` extents in world units (see ``kind``).
        texture: ``[Ht, Wt, 3]`` float32 colours in [0, 1].
        texels_per_unit: texture density on the surface.
        object_id: 0 for the static set, k >= 1 for the k-th moving object.
        R: ``[3, 3]`` world-from-object rotation (static pose; moving objects get theirs per call).
        c: ``[3]`` object origin in world coordinates.
    """

    kind: str
    size: np.ndarray
    texture: np.ndarray
    texels_per_unit: float
    object_id: int = 0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    c: np.ndarray = field(default_factory=lambda: np.zeros(3))


def sample_texture(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around. ``u, v``: ``[N]`` texel coordinates -> ``[N, 3]`` colours."""
    h, w = tex.shape[:2]
    x0 = np.floor(u)
    y0 = np.floor(v)
    fx = (u - x0)[:, None]
    fy = (v - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _safe(d: np.ndarray) -> np.ndarray:
    # Avoid division by zero for rays parallel to an axis: a tiny signed value gives +-inf-like distances.
    return np.where(np.abs(d) < 1e-12, np.where(d < 0, -1e-12, 1e-12), d)


def intersect(prim: Primitive, o: np.ndarray, d: np.ndarray, R=None, c=None):
    """Intersect rays with one primitive.

    Args:
        prim: the shape.
        o: ``[3]`` ray origin (world); d: ``[N, 3]`` unit ray directions (world).
        R, c: world-from-object pose overriding ``prim.R, prim.c`` (for moving objects).

    Returns:
        t ``[N]`` hit distance along ``d`` (inf where missed), uv ``[N, 2]`` surface coordinates in world
        units, n ``[N, 3]`` world-space unit normals.
    """
    R = prim.R if R is None else R
    c = prim.c if c is None else c
    dt = d.dtype  # float32 rays halve memory traffic; geometry stays exact to ~1e-7 relative
    ol = (R.T @ (o - c)).astype(dt)  # [3]
    dl = d @ R.astype(dt)  # [N, 3] = (R^T d)^T
    n_rays = d.shape[0]
    t = np.full(n_rays, np.inf, dtype=dt)
    uv = np.zeros((n_rays, 2), dtype=dt)
    n_world = np.zeros((n_rays, 3), dtype=dt)
    # Each shape works on the rays that can still hit and returns the ``hit`` rows only: most rays miss most
    # primitives, so this keeps the static set and small objects cheap.
    shapes = {"plane": _hit_plane, "box": _hit_box, "sphere": _hit_sphere}
    if prim.kind not in shapes:
        raise ValueError(f"unknown primitive kind {prim.kind!r}")
    hit, th, u, v, nl = shapes[prim.kind](prim, ol, dl, dt)
    t[hit] = th
    uv[hit, 0] = u
    uv[hit, 1] = v
    n_world[hit] = nl @ R.T.astype(dt)
    return t, uv, n_world


def _hit_plane(prim: Primitive, ol: np.ndarray, dl: np.ndarray, dt):
    """Rectangle ``[0, w] x [0, h]`` of the object's z = 0 plane, two-sided. Returns ``(hit rows, t, u, v,
    object-space normals)`` for the rays ``dl`` ``[N, 3]`` from ``ol`` (object space)."""
    dz = _safe(dl[:, 2])
    th = -ol[2] / dz
    cand = np.nonzero(th > _EPS)[0]
    px = ol[0] + th[cand] * dl[cand, 0]
    py = ol[1] + th[cand] * dl[cand, 1]
    ok = (px >= 0) & (px <= prim.size[0]) & (py >= 0) & (py <= prim.size[1])
    hit = cand[ok]
    nl = np.zeros((hit.size, 3), dtype=dt)
    nl[:, 2] = np.where(dz[hit] < 0, 1.0, -1.0)  # two-sided: normal faces the viewer
    return hit, th[hit], px[ok], py[ok], nl


def _hit_box(prim: Primitive, ol: np.ndarray, dl: np.ndarray, dt):
    """Axis-aligned box of half-sizes ``prim.size`` (as :func:`_hit_plane`)."""
    h = prim.size.astype(dt)
    # Cull with the bounding sphere first (a dot product per ray), then run the slab test on the rest.
    b = dl @ ol
    cand = np.nonzero(b * b - (ol @ ol - h @ h) >= 0)[0]
    dc = dl[cand]
    ds = _safe(dc)
    t1 = (-h[None, :] - ol[None, :]) / ds
    t2 = (h[None, :] - ol[None, :]) / ds
    tnear = np.minimum(t1, t2)
    tmin = tnear.max(axis=1)
    tmax = np.maximum(t1, t2).min(axis=1)
    ok = (tmax >= tmin) & (tmin > _EPS)
    hit = cand[ok]
    th = tmin[ok]
    axis = tnear[ok].argmax(axis=1)
    p = ol[None, :] + th[:, None] * dc[ok]
    # Face coordinates: the two other axes, offset per face so faces do not repeat the same patch.
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    rows = np.arange(hit.size)
    side = np.sign(p[rows, axis])
    u = p[rows, other[:, 0]] + h[other[:, 0]] + 2.3 * axis + 1.1 * (side > 0)
    v = p[rows, other[:, 1]] + h[other[:, 1]]
    nl = np.zeros((hit.size, 3), dtype=dt)
    nl[rows, axis] = side
    return hit, th, u, v, nl


def _hit_sphere(prim: Primitive, ol: np.ndarray, dl: np.ndarray, dt):
    """Sphere of radius ``prim.size[0]`` (as :func:`_hit_plane`; u, v: longitude and latitude in world units)."""
    r = prim.size[0]
    b = dl @ ol
    disc = b * b - (ol @ ol - r * r)
    th = -b - np.sqrt(np.maximum(disc, 0.0))
    hit = np.nonzero((disc >= 0) & (th > _EPS))[0]
    th = th[hit]
    p = ol[None, :] + th[:, None] * dl[hit]
    lon = np.arctan2(p[:, 0], p[:, 2])
    lat = np.arcsin(np.clip(p[:, 1] / r, -1.0, 1.0))
    return hit, th, (lon + np.pi) * r, (lat + np.pi / 2) * r, p / r


def shade(prim: Primitive, uv: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Texture colour times a mild Lambert factor. ``uv``: ``[N, 2]`` units, ``n``: ``[N, 3]`` -> ``[N, 3]``."""
    col = sample_texture(prim.texture, uv[:, 0] * prim.texels_per_unit, uv[:, 1] * prim.texels_per_unit)
    lam = 0.6 + 0.4 * np.clip(-(n @ _LIGHT.astype(n.dtype)), 0.0, 1.0)
    return col * lam[:, None]


def cast(prims, poses, o: np.ndarray, d: np.ndarray):
    """Nearest hit over several primitives.

    Args:
        prims: list of :class:`Primitive`.
        poses: list of ``(R, c)`` or None per primitive (None = the primitive's own pose).
        o: ``[3]`` origin; d: ``[N, 3]`` unit directions.

    Returns:
        t ``[N]`` (inf where nothing is hit), rgb ``[N, 3]`` float in [0, 1], object id ``[N]`` int
        (-1 where nothing is hit).
    """
    n_rays = d.shape[0]
    best = np.full(n_rays, np.inf, dtype=d.dtype)
    rgb = np.zeros((n_rays, 3), dtype=np.float32)
    oid = np.full(n_rays, -1, dtype=np.int16)
    for prim, pose in zip(prims, poses, strict=True):
        R, c = (None, None) if pose is None else pose
        t, uv, n = intersect(prim, o, d, R, c)
        win = t < best
        if not win.any():
            continue
        best[win] = t[win]
        rgb[win] = shade(prim, uv[win], n[win])
        oid[win] = prim.object_id
    return best, rgb, oid
