"""An independent reference for the rasterisers' hard limit: NumPy ray casting."""

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Float64, Int

from ._camera import Camera


def ray_cast(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], camera: Camera
) -> tuple[Bool[np.ndarray, "H W"], Float64[np.ndarray, "H W"]]:
    """Moeller-Trumbore ray-triangle intersection (NumPy, float64) of one ray through every
    pixel centre of ``camera`` (from the eye, or parallel for an orthographic camera).

    Returns (hit (H, W) bool, depth (H, W): distance of the first hit along the viewing axis,
    in the units of ``vertices``, NaN where no triangle is hit). Slow (a loop over chunks
    of 256 rays against every triangle); meant for checks, not for rendering."""
    h, w = camera.image_size
    rotation = np.asarray(camera.rotation, np.float64)
    position = np.asarray(camera.position, np.float64)
    focal = float(camera.focal)
    cu, cv = np.asarray(camera.principal, np.float64)
    rows, cols = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    x, y = (cols - cu) / focal, -(rows - cv) / focal
    if camera.projection == "perspective":
        local_dir = np.stack([x, y, -np.ones_like(x)], -1).reshape(-1, 3)
        local_origin = np.zeros_like(local_dir)
    else:
        local_dir = np.tile([0.0, 0.0, -1.0], (h * w, 1))
        local_origin = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3)
    directions = local_dir @ rotation
    origins = local_origin @ rotation + position
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    depth = np.full(h * w, np.inf)
    for start in range(0, h * w, 256):
        d = directions[start : start + 256, None]  # (R, 1, 3)
        o = origins[start : start + 256, None]
        p = np.cross(d, e2)
        det = np.sum(e1 * p, -1)
        ok = np.abs(det) > 1e-12
        inv = 1.0 / np.where(ok, det, 1.0)
        s = o - a
        u = np.sum(s * p, -1) * inv
        q = np.cross(s, e1)
        v = np.sum(d * q, -1) * inv
        t = np.sum(e2 * q, -1) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        point = o + t[..., None] * d
        along = (point - position) @ -rotation[2]
        depth[start : start + 256] = np.where(hit, along, np.inf).min(axis=1)
    hit = np.isfinite(depth)
    depth[~hit] = np.nan
    return hit.reshape(h, w), depth.reshape(h, w)
