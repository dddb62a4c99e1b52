"""Rigid alignment of a template surface to a new head: a similarity fit by trimmed ICP.

``similarity_icp`` moves template points (e.g. the ICT face) onto a target mesh by
alternating closest points on the target surface with Umeyama's least-squares similarity,
keeping only the ``trim`` fraction of pairs with the smallest distances at each iteration
(trimmed ICP, Chetverikov et al. 2002), so the parts of the target the template does not
cover (scalp, neck, shoulders) do not pull it. ``fit_landmarks`` uses it to place a
template's landmarks on a new head with no hand-picked vertices: the landmarks of the
aligned template, each snapped to the nearest target vertex.

The start is the identity rotation (both heads are assumed y up, facing +z, in the same
units) with the frontmost points (largest z: the nose tip) put together; ``fit_landmarks``
reports the fit's trimmed RMS distance and refuses a fit that does not converge onto the
surface (a head facing elsewhere, e.g. stored z up) or whose scale says other units.
"""

import dataclasses

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Float64, Int
from scipy.spatial import KDTree

from ._checks import check_mesh
from ._remesh import SurfaceMap, closest_surface_points
from ._transfer import similarity_transform


@dataclasses.dataclass(frozen=True)
class SimilarityFit:
    """target ~ scale * rotation @ source + translation.

    Attributes:
        scale, rotation (3, 3), translation (3,): the similarity.
        rms: root mean square distance of the kept (trimmed) pairs after the last iteration,
            in the target's units.
        iterations: iterations run.
    """

    scale: float
    rotation: Float[np.ndarray, "3 3"]
    translation: Float[np.ndarray, " 3"]
    rms: float
    iterations: int

    def apply(self, points: Float[ArrayLike, "*N 3"]) -> Float64[np.ndarray, "*N 3"]:
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation


def similarity_icp(
    source_points: Float[ArrayLike, "N 3"],
    target_vertices: Float[ArrayLike, "V 3"],
    target_faces: Int[ArrayLike, "F 3"],
    *,
    trim: float = 0.9,
    iterations: int = 100,
    tolerance: float = 1e-6,
    with_scale: bool = True,
) -> SimilarityFit:
    """Trimmed ICP of ``source_points`` (N, 3) onto the target surface.

    The alternations (closest points, then the best similarity to them) are Anderson-
    accelerated (``_icp``); more than ``2 * ICP_COARSE_POINTS`` points first converge on a
    regular subsample, then refine on all of them.

    Args:
        trim: fraction of closest-point pairs kept at each iteration (0 < trim <= 1).
        iterations: at most this many alternations.
        tolerance: stop when the kept RMS changes by less than this fraction.
        with_scale: fit a similarity (True) or a rigid motion (scale 1).
    """
    points = np.asarray(source_points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 3:
        raise ValueError(f"source_points: expected shape (N >= 3, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("source_points: contains non-finite values")
    if not 0 < trim <= 1:
        raise ValueError(f"trim: expected a fraction in (0, 1], got {trim}")
    tv, tf = check_mesh(target_vertices, target_faces)
    translation = tv[np.argmax(tv[:, 2])] - points[np.argmax(points[:, 2])]
    start = (1.0, np.eye(3), translation)
    done = 0
    if points.shape[0] >= 2 * ICP_COARSE_POINTS:  # converge on a subsample, then refine
        coarse = points[:: points.shape[0] // ICP_COARSE_POINTS]
        *start, _, done = _icp(coarse, tv, tf, start, trim, iterations, tolerance, with_scale)
    scale, rotation, translation, rms, more = _icp(
        points, tv, tf, start, trim, max(iterations - done, 1), tolerance, with_scale
    )
    return SimilarityFit(float(scale), rotation, np.asarray(translation), rms, done + more)


ICP_COARSE_POINTS = 400
"""``similarity_icp`` of more than twice this many points first converges on a regular
subsample of about this many, then refines on all of them (most alternations are then cheap)."""


ICP_MEMORY = 5
"""Alternations ``similarity_icp`` extrapolates from (Anderson acceleration)."""


def _icp(points, tv, tf, start, trim, iterations, tolerance, with_scale):
    """Trimmed ICP alternations from ``start`` (scale, rotation, translation), Anderson-
    accelerated on the transform's parameters (Pavlov et al. 2018, AA-ICP): the next
    transform extrapolates the last ``ICP_MEMORY`` alternations; one that raises the kept RMS
    is replaced by the plain alternation. Returns (scale, rotation, translation, kept RMS,
    alternations run)."""
    keep = max(3, int(round(trim * points.shape[0])))
    radius = float(np.linalg.norm(points - points.mean(0), axis=1).max())
    x = _transform_params(*start, radius)
    xs, gs = [], []  # accepted parameters and their plain alternations
    best_rms, best, done = np.inf, None, 0
    for done in range(1, iterations + 1):  # noqa: B007 (reported after the loop)
        scale, rotation, translation = _params_transform(x, radius)
        found = closest_surface_points(scale * points @ rotation.T + translation, tv, tf)
        closest = np.einsum("nk,nkd->nd", found.barycentric, tv[tf[found.triangle]])
        kept = np.argsort(found.distance)[:keep]
        rms = float(np.sqrt(np.mean(found.distance[kept] ** 2)))
        if rms > best_rms and xs:  # the extrapolation went uphill: the plain step instead
            xs, gs = [], []
            x = best[1]
            continue
        s, rotation, translation = similarity_transform(points[kept], closest[kept])
        if not with_scale:
            s = 1.0
            translation = closest[kept].mean(0) - rotation @ points[kept].mean(0)
        g = _transform_params(s, rotation, translation, radius)
        converged = abs(best_rms - rms) <= tolerance * max(rms, 1e-30)
        best_rms, best = rms, (x, g)
        if converged:
            break
        xs, gs = (xs + [x])[-ICP_MEMORY - 1 :], (gs + [g])[-ICP_MEMORY - 1 :]
        x = _anderson(np.array(xs), np.array(gs))
    scale, rotation, translation = _params_transform(best[1], radius)
    return scale, rotation, translation, best_rms, done


def _anderson(xs, gs):
    """The Anderson (type II) extrapolation of fixed-point iterates ``xs`` (m, 7) with their
    images ``gs`` (m, 7): the plain image when there is one iterate."""
    if len(xs) < 2:
        return gs[-1]
    f = gs - xs
    df, dg = np.diff(f, axis=0).T, np.diff(gs, axis=0).T
    gamma = np.linalg.lstsq(df, f[-1], rcond=None)[0]
    return gs[-1] - dg @ gamma


def _transform_params(scale, rotation, translation, radius):
    """(7,) a similarity as (log scale, rotation vector) times ``radius`` and translation:
    every entry a distance, so the extrapolation weighs them alike."""
    from scipy.spatial.transform import Rotation

    rotvec = Rotation.from_matrix(rotation).as_rotvec()
    return np.concatenate([[np.log(scale) * radius], rotvec * radius, translation])


def _params_transform(x, radius):
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_rotvec(x[1:4] / radius).as_matrix()
    return float(np.exp(x[0] / radius)), rotation, x[4:]


def fit_landmarks(
    source_vertices: Float[ArrayLike, "Vs 3"],
    source_landmarks: Int[ArrayLike, " L"],
    source_region: Bool[ArrayLike, " Vs"],
    target_vertices: Float[ArrayLike, "V 3"],
    target_faces: Int[ArrayLike, "F 3"],
    *,
    target_region: Bool[ArrayLike, " V"] | None = None,
    trim: float = 0.9,
    max_rms: float | None = None,
    max_scale_ratio: float = 2.0,
) -> tuple[Int[np.ndarray, " L"], SimilarityFit]:
    """A template's landmarks placed on a new head: trimmed-ICP similarity of the template's
    ``source_region`` vertices onto the target, then each transformed landmark snapped to the
    nearest target vertex (of ``target_region`` when given).

    Args:
        source_vertices: (Vs, 3) template vertices; source_landmarks: (L,) vertex indices.
        source_region: (Vs,) bool, the template vertices fitted (e.g. the ICT face part).
        target_vertices, target_faces: the new head (same units and orientation).
        target_region: (V,) bool, the target vertices landmarks may land on (e.g. its skin).
        max_rms: refuse (ValueError naming ``target_vertices``) a fit whose trimmed RMS
            distance exceeds this (target units); default 1.2 % of the template region's
            size (the ICT face fits MakeHuman at 0.5 %, and the same ICT head stored z up
            converges to a wrong fit at 1.8 %: refused).
        max_scale_ratio: refuse a fit whose scale is outside [1 / ratio, ratio]: the head is
            then in other units than the template (e.g. metres or decimetres for cm).

    Returns:
        ((L,) target vertex indices, the ``SimilarityFit``).
    """
    sv = np.asarray(source_vertices, np.float64)
    landmarks = np.asarray(source_landmarks, np.int64)
    region = np.asarray(source_region, bool)
    if region.shape != (sv.shape[0],) or region.sum() < 3:
        raise ValueError(
            f"source_region: expected a (Vs,) mask of >= 3 vertices, got shape {region.shape}"
        )
    if landmarks.ndim != 1 or landmarks.min() < 0 or landmarks.max() >= sv.shape[0]:
        raise ValueError(f"source_landmarks: expected vertex indices in [0, {sv.shape[0]})")
    tv, tf = check_mesh(target_vertices, target_faces)
    points = sv[region]
    if points.shape[0] > 4000:  # a regular subsample keeps the fit fast
        points = points[:: int(np.ceil(points.shape[0] / 4000))]
    fit = similarity_icp(points, tv, tf, trim=trim)
    size = float(np.linalg.norm(points.max(0) - points.min(0)))
    limit = 0.012 * size if max_rms is None else float(max_rms)
    if not np.isfinite(fit.rms) or fit.rms > limit:
        raise ValueError(
            f"target_vertices: the template did not fit the head (trimmed RMS {fit.rms:.3g} > "
            f"{limit:.3g}); check its units (same as the template) and orientation (y up, "
            "facing +z)"
        )
    if not 1.0 / max_scale_ratio <= fit.scale <= max_scale_ratio:
        raise ValueError(
            f"target_vertices: the head is {fit.scale:.3g} times the template's size; it is "
            "probably in other units (the template's, e.g. centimetres, expected)"
        )
    candidates = np.arange(tv.shape[0])
    if target_region is not None:
        mask = np.asarray(target_region, bool)
        if mask.shape != (tv.shape[0],) or not mask.any():
            raise ValueError(f"target_region: expected a non-empty (V,) mask, got {mask.shape}")
        candidates = np.flatnonzero(mask)
    nearest = KDTree(tv[candidates]).query(fit.apply(sv[landmarks]))[1]
    return candidates[nearest].astype(np.int64), fit


def bind_points(
    points: Float[ArrayLike, "N 3"],
    target_vertices: Float[ArrayLike, "V 3"],
    target_faces: Int[ArrayLike, "F 3"],
    *,
    target_triangles: Bool[ArrayLike, " F"] | None = None,
    trim: float = 0.9,
    max_rms: float | None = None,
) -> tuple[SurfaceMap, SimilarityFit]:
    """Points of another surface (a landmark layout such as MediaPipe's canonical face) bound
    to a head: the trimmed-ICP similarity of ``points`` onto the head's surface
    (``similarity_icp``), then each moved point's closest point on the head, as a triangle and
    barycentric coordinates (a ``SurfaceMap`` on ``target_faces``). No correspondence is given
    or hand-picked: the binding is this registration's.

    Args:
        points: (N, 3) in the head's units and orientation (y up, facing +z).
        target_vertices, target_faces: the head.
        target_triangles: (F,) bool, the triangles points may bind to (e.g. the skin: not the
            eyeballs or teeth); default all.
        max_rms: refuse (ValueError naming ``points``) a fit whose trimmed RMS distance
            exceeds this (head units); default 2 % of the points' bounding-box diagonal.

    Returns:
        (the binding, the similarity): the binding a ``SurfaceMap`` whose ``distance`` is each
        moved point's distance to the surface; the similarity a ``SimilarityFit``, target ~
        ``scale * rotation @ source + translation`` (``rotation`` (3, 3), ``translation``
        (3,)), with ``rms``, the root mean square distance of the kept (trimmed) pairs after
        the last iteration (the target's units), ``iterations`` run, and ``apply(points)``.
    """
    tv, tf = check_mesh(target_vertices, target_faces)
    keep = np.ones(tf.shape[0], bool) if target_triangles is None else np.asarray(target_triangles)
    if keep.shape != (tf.shape[0],) or keep.dtype != bool or not keep.any():
        raise ValueError(
            f"target_triangles: expected a non-empty ({tf.shape[0]},) bool mask of triangles"
        )
    chosen = np.flatnonzero(keep)
    fit = similarity_icp(points, tv, tf[chosen], trim=trim)
    source = np.asarray(points, np.float64)
    size = float(np.linalg.norm(source.max(0) - source.min(0)))
    limit = 0.02 * size if max_rms is None else float(max_rms)
    if not np.isfinite(fit.rms) or fit.rms > limit:
        raise ValueError(
            f"points: they did not fit the head (trimmed RMS {fit.rms:.3g} > {limit:.3g}); "
            "check their units (the head's) and orientation (y up, facing +z)"
        )
    found = closest_surface_points(fit.apply(source), tv, tf[chosen])
    binding = SurfaceMap(
        triangle=chosen[found.triangle].astype(np.int64),
        barycentric=found.barycentric,
        source_faces=tf,
        n_source=int(tv.shape[0]),
        distance=found.distance,
    )
    return binding, fit
