"""Pinhole and orthographic cameras for the differentiable rasteriser.

Conventions: world units are the mesh's (ICT: cm). Camera frame: x right, y up, the camera
looks down -z (OpenGL); the depth of a point is its distance along the viewing axis.
Image: ``image_size = (height, width)`` pixels; pixel (row i, column j) has its centre at
screen coordinates (u, v) = (j + 0.5, i + 0.5), u to the right, v down.

* perspective: u = cu + focal * x / depth, v = cv - focal * y / depth (focal in pixels);
* orthographic: u = cu + focal * x, v = cv - focal * y (focal in pixels per world unit).

A ``Camera`` is a pytree of arrays (plus static image size and projection), so cameras of
the same kind stack (``stack_cameras``) and ``jax.vmap`` maps over views.
"""

import math
from collections.abc import Iterable, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_finite, is_concrete

PROJECTIONS = ("perspective", "orthographic")


class Camera(eqx.Module):
    """A camera: world-to-camera rotation, centre, focal length and principal point.

    Attributes:
        rotation: (3, 3) rows are the camera's right, up and backward axes in world
            coordinates (world -> camera: ``rotation @ (p - position)``).
        position: (3,) camera centre (perspective) or a point on the viewing axis
            (orthographic), world units.
        focal: () pixels (perspective) or pixels per world unit (orthographic).
        principal: (2,) screen coordinates (u, v) of the viewing axis.
        image_size: (height, width) pixels, static.
        projection: ``"perspective"`` or ``"orthographic"``, static.
    """

    rotation: Float[Array, "*views 3 3"]
    position: Float[Array, "*views 3"]
    focal: Float[Array, "*views"]
    principal: Float[Array, "*views 2"]
    image_size: tuple[int, int] = eqx.field(static=True)
    projection: str = eqx.field(static=True, default="perspective")

    @property
    def height(self) -> int:
        return self.image_size[0]

    @property
    def width(self) -> int:
        return self.image_size[1]

    @property
    def perspective(self) -> bool:
        return self.projection == "perspective"


def _check_image_size(image_size) -> tuple[int, int]:
    if isinstance(image_size, int | np.integer):
        image_size = (int(image_size), int(image_size))
    try:
        height, width = (int(s) for s in image_size)
        exact = all(int(s) == s for s in image_size)
    except (TypeError, ValueError):
        raise ValueError(
            f"image_size: expected an int or (height, width), got {image_size!r}"
        ) from None
    if not exact or height < 1 or width < 1:
        raise ValueError(f"image_size: expected integers >= 1, got {tuple(image_size)}")
    return height, width


def check_camera(camera: Any) -> None:
    """ValueError naming ``camera`` when it is not a usable ``Camera`` (concrete fields only:
    traced fields, inside ``jax.vmap``/``jit``, are left to the caller)."""
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    if camera.projection not in PROJECTIONS:
        raise ValueError(
            f"camera: projection must be one of {PROJECTIONS}, got {camera.projection}"
        )
    _check_image_size(camera.image_size)
    for name in ("rotation", "position", "focal", "principal"):
        check_finite(f"camera: {name}", getattr(camera, name))
    if is_concrete(camera.focal) and not bool(np.all(np.asarray(camera.focal) > 0)):
        raise ValueError(f"camera: focal length must be > 0, got {np.asarray(camera.focal)}")
    if is_concrete(camera.rotation):
        r = np.asarray(camera.rotation, np.float64).reshape(-1, 3, 3)
        eye = np.einsum("nij,nkj->nik", r, r)
        if not np.allclose(eye, np.eye(3), atol=1e-4):
            raise ValueError("camera: rotation is not orthonormal")


def look_at(
    eye: Float[ArrayLike, " 3"] | Sequence[float],
    target: Float[ArrayLike, " 3"] | Sequence[float],
    up: Float[ArrayLike, " 3"] | Sequence[float] = (0.0, 1.0, 0.0),
    *,
    image_size: int | tuple[int, int],
    fov_degrees: float | None = 30.0,
    ortho_width: float | None = None,
    projection: str = "perspective",
) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` roughly up in the image.

    Args:
        image_size: int or (height, width), pixels >= 1.
        fov_degrees: horizontal field of view (perspective), in (0, 180).
        ortho_width: width of the visible region in world units (orthographic), > 0.
        projection: ``"perspective"`` or ``"orthographic"``.
    """
    if projection not in PROJECTIONS:
        raise ValueError(f"projection: expected one of {PROJECTIONS}, got {projection!r}")
    height, width = _check_image_size(image_size)
    eye = np.asarray(eye, np.float64)
    target = np.asarray(target, np.float64)
    up = np.asarray(up, np.float64)
    for name, value in (("eye", eye), ("target", target), ("up", up)):
        if value.shape != (3,):
            raise ValueError(f"{name}: expected shape (3,), got {value.shape}")
        check_finite(name, value)
    backward = eye - target
    if np.linalg.norm(backward) < 1e-12:
        raise ValueError("eye, target: the camera must not sit on its target")
    backward /= np.linalg.norm(backward)
    right = np.cross(up, backward)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("up: must not be parallel to the viewing direction")
    right /= np.linalg.norm(right)
    true_up = np.cross(backward, right)
    if projection == "perspective":
        if fov_degrees is None or not 0.0 < fov_degrees < 180.0:
            raise ValueError(f"fov_degrees: expected a value in (0, 180), got {fov_degrees}")
        focal = 0.5 * width / math.tan(math.radians(fov_degrees) / 2.0)
    else:
        if ortho_width is None or not ortho_width > 0 or not math.isfinite(ortho_width):
            raise ValueError(f"ortho_width: expected a finite value > 0, got {ortho_width}")
        focal = width / ortho_width
    return Camera(
        rotation=jnp.asarray(np.stack([right, true_up, backward]), jnp.float32),
        position=jnp.asarray(eye, jnp.float32),
        focal=jnp.asarray(focal, jnp.float32),
        principal=jnp.asarray([width / 2.0, height / 2.0], jnp.float32),
        image_size=(height, width),
        projection=projection,
    )


def orbit_cameras(
    target: Float[ArrayLike, " 3"] | Sequence[float],
    distance: float,
    yaw_degrees: float | Float[ArrayLike, " N"] | Sequence[float],
    *,
    pitch_degrees: float = 0.0,
    image_size: int | tuple[int, int],
    fov_degrees: float = 30.0,
    projection: str = "perspective",
    ortho_width: float | None = None,
) -> Camera:
    """Stacked cameras around ``target`` (y up), at ``distance`` along +z turned by each yaw
    (degrees, about +y; 0 = in front, facing -z) and ``pitch_degrees`` (up is positive)."""
    target = np.asarray(target, np.float64)
    if not distance > 0:
        raise ValueError(f"distance: expected > 0, got {distance}")
    cameras = []
    pitch = math.radians(pitch_degrees)
    for yaw in np.atleast_1d(np.asarray(yaw_degrees, np.float64)):
        y = math.radians(float(yaw))
        direction = np.array(
            [math.sin(y) * math.cos(pitch), math.sin(pitch), math.cos(y) * math.cos(pitch)]
        )
        cameras.append(
            look_at(
                target + distance * direction,
                target,
                image_size=image_size,
                fov_degrees=fov_degrees,
                projection=projection,
                ortho_width=ortho_width,
            )
        )
    return stack_cameras(cameras)


def stack_cameras(cameras: Iterable[Camera]) -> Camera:
    """One ``Camera`` whose array fields have a leading view axis (for ``jax.vmap``)."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("cameras: expected at least one camera")
    for c in cameras:
        check_camera(c)
    kinds = {(c.image_size, c.projection) for c in cameras}
    if len(kinds) != 1:
        raise ValueError(f"cameras: expected one image size and projection, got {sorted(kinds)}")
    return Camera(
        rotation=jnp.stack([c.rotation for c in cameras]),
        position=jnp.stack([c.position for c in cameras]),
        focal=jnp.stack([c.focal for c in cameras]),
        principal=jnp.stack([c.principal for c in cameras]),
        image_size=cameras[0].image_size,
        projection=cameras[0].projection,
    )


def camera_depth(camera: Camera, points: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Depth of ``points`` along the viewing axis (positive in front of the camera)."""
    return -jnp.einsum("j,...j->...", camera.rotation[2], points - camera.position)


def project_points(
    camera: Camera, points: Float[Array, "... 3"]
) -> tuple[Float[Array, "... 2"], Float[Array, "..."]]:
    """Screen coordinates (u, v) in pixels and depth of world ``points``. Perspective
    division uses the depth as is: keep points in front of the camera (``rasterise``
    checks concrete inputs)."""
    local = jnp.einsum("ij,...j->...i", camera.rotation, points - camera.position)
    depth = -local[..., 2]
    if camera.perspective:
        scale = camera.focal / depth
    else:
        scale = jnp.broadcast_to(camera.focal, depth.shape)
    u = camera.principal[0] + scale * local[..., 0]
    v = camera.principal[1] - scale * local[..., 1]
    return jnp.stack([u, v], axis=-1), depth


def screen_displacement(
    camera: Camera, neutral: Float[Array, "V 3"], posed: Float[Array, "... V 3"]
) -> Float[Array, "... V 2"]:
    """2D screen displacement (pixels) of each vertex from ``neutral`` to ``posed``: the
    per-vertex optical flow of the pose seen by ``camera`` (the "2D displacement"
    supervision of RigAnyFace, section 3.3)."""
    start, _ = project_points(camera, neutral)
    end, _ = project_points(camera, posed)
    return end - start
