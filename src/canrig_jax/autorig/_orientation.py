"""Which way a head faces, from its shape alone (no template, no landmarks).

RigAnyFace was trained on ICT heads: +y up, +z forward (facing the viewer), +x the head's
left. ``head_orientation`` finds a head's axes among the 24 axis-aligned rotations from
three cues of a human head that do not depend on where it was cropped:

* **left-right**: the axis across which the head is mirror-symmetric (mean distance from
  each mirrored vertex to the nearest vertex, per axis; the smallest wins);
* **forward**: of the four signed directions across the other two axes, the one whose
  extreme is the sharpest point — the nose tip (the vertices within ``5 %`` of the size of
  the extreme spread the least around it; the crown, the back of the head and a neck or
  shoulder cut are broad); parts inside the skin (eyes, teeth), if any, must lie on that
  side of the centre;
* **up**: along the remaining axis, the side of the nose tip on which the paired parts off
  the mid-plane sit (eyeballs, lashes: above), and the side away from the skin's longest
  open boundary (a neck or shoulder cut: below); the cues that are clear must agree.

Each cue reports a margin; a head whose cues are weak (a sphere, a flat patch, a head
turned by other than a multiple of 90 degrees) is "undetermined", which the network
(``AbstractNetworkMethod.generate``) lets through: it refuses or fixes only what the cues
show clearly.
"""

import dataclasses
from importlib.resources import files
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int
from scipy.spatial import KDTree

from ..mesh import check_mesh, connected_components
from ._data import AutorigDataset

AXES = ("x", "y", "z")
CONVENTION = "+y up, +z forward (ICT)"
SYMMETRY_MARGIN = 1.5
"""The symmetry axis must be this many times more symmetric than the next one."""
SHARPNESS_MARGIN = 1.6
"""The nose tip must spread this many times less than the next sharpest extreme (ICT heads:
2.0-3.8; a random ICT identity whose lips stand out as far as its nose: 1.2-1.4, left
undetermined)."""
INNER_FORWARD = 0.05
"""Parts inside the skin (eyes, teeth), when there are any, must sit this far (fraction of
the head's radius) on the forward side of the skin's centre (ICT heads: ~0.3)."""
UP_MARGINS = {"side_parts": 0.03, "boundary": 0.3}
"""An up cue counts when the side parts sit this far (fraction of the head's radius) above
or below the nose tip (ICT heads: 0.07-0.09), or the longest boundary's centre this far
(fraction of the half height) below or above the centre (ICT heads with a neck or cut at
the chin: 0.78-0.96; a face-only mask: 0.06, undetermined)."""


def _signed(axis: int, sign: float) -> str:
    return f"{'+' if sign > 0 else '-'}{AXES[axis]}"


@dataclasses.dataclass(frozen=True)
class HeadOrientation:
    """A head's axes as found by ``head_orientation``.

    Attributes:
        rotation: (3, 3) proper rotation taking the head into the model's convention
            (``vertices @ rotation.T``: +y up, +z forward), or None when undetermined.
        up, forward: the head's up and forward directions as signed axis names ("+y",
            "-z", ...) or None where a cue was inconclusive; lateral: its left-right axis.
        margins: the cues' values (symmetry ratio, sharpness ratio, up votes).
    """

    rotation: Float[np.ndarray, "3 3"] | None
    up: str | None
    forward: str | None
    lateral: str | None
    margins: dict

    @property
    def determined(self) -> bool:
        return self.rotation is not None

    @property
    def conventional(self) -> bool:
        """True when the head already faces +z with +y up."""
        return self.rotation is not None and np.allclose(self.rotation, np.eye(3))

    @property
    def contradicts(self) -> bool:
        """True when a clear cue says the head is not in the convention (even if another
        cue is inconclusive)."""
        return (
            (self.lateral is not None and self.lateral != "x")
            or (self.forward is not None and self.forward != "+z")
            or (self.up is not None and self.up != "+y")
        )

    def describe(self) -> str:
        parts = [
            f"up {self.up or 'undetermined'}",
            f"facing {self.forward or 'undetermined'}",
            f"left-right axis {self.lateral or 'undetermined'}",
        ]
        return ", ".join(parts)


def head_orientation(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], *, max_points: int = 4000
) -> HeadOrientation:
    """The up, forward and left-right axes of a head (see the module docstring).

    Args:
        vertices: (V, 3) head in any units; faces: (F, 3) triangles.
        max_points: the symmetry cue uses a regular subsample of at most this many vertices.

    Returns a ``HeadOrientation`` (axis-aligned only: a head turned by another angle comes
    back undetermined or with its nearest axis-aligned orientation).
    """
    vertices, faces = check_mesh(vertices, faces)
    v = np.asarray(vertices, np.float64)
    # the largest component carries the cues (the skin; eyes and teeth are inside it)
    labels = connected_components(faces, v.shape[0])
    main = labels == np.bincount(labels).argmax()
    skin = v[main]
    centre = 0.5 * (skin.min(0) + skin.max(0))
    p = skin - centre
    radius = float(np.linalg.norm(p, axis=1).max())
    margins: dict = {}
    if not radius > 0 or skin.shape[0] < 8:
        return HeadOrientation(None, None, None, None, margins)
    p = p / radius

    # -- left-right: mirror symmetry ---------------------------------------------------
    asymmetry = _mirror_asymmetry(p, max_points)
    order = np.argsort(asymmetry)
    lateral_axis = int(order[0])
    ratio = asymmetry[order[1]] / max(asymmetry[order[0]], 1e-12)
    margins["symmetry"] = float(ratio)
    margins["asymmetry"] = dict(zip(AXES, asymmetry, strict=True))
    if ratio < SYMMETRY_MARGIN:
        return HeadOrientation(None, None, None, None, margins)
    lateral = AXES[lateral_axis]

    # -- forward: the sharpest extreme (the nose tip) -------------------------------------
    others = [a for a in range(3) if a != lateral_axis]
    spreads = _extreme_spreads(p, others)
    ranked = sorted(spreads, key=lambda axis: spreads[axis])
    sharpness = spreads[ranked[1]] / max(spreads[ranked[0]], 1e-12)
    margins["sharpness"] = float(sharpness)
    margins["spreads"] = {_signed(a, s): value for (a, s), value in spreads.items()}
    if sharpness < SHARPNESS_MARGIN:
        return HeadOrientation(None, None, None, lateral, margins)
    forward_axis, forward_sign = ranked[0]
    inner = (v[~main] - centre) / radius
    if inner.shape[0]:  # eyes and teeth sit behind the face, in front of the centre
        ahead = float(forward_sign * inner[:, forward_axis].mean())
        margins["inner_forward"] = ahead
        if ahead < INNER_FORWARD:
            return HeadOrientation(None, None, None, lateral, margins)
    forward = _signed(forward_axis, forward_sign)

    # -- up: the eyes above the nose, the neck cut below -------------------------------
    up_axis = next(a for a in others if a != forward_axis)
    nose = p[np.argmax(forward_sign * p[:, forward_axis])]
    votes = _side_parts_vote(p, inner, labels[~main], lateral_axis, up_axis, nose)
    votes.update(_neck_cut_vote(p, faces, main, up_axis))
    margins["up_votes"] = votes
    signs = {np.sign(value) for name, value in votes.items() if abs(value) >= UP_MARGINS[name]}
    offset = float(next(iter(signs))) if len(signs) == 1 else 0.0
    margins["up_sign"] = offset
    if offset == 0.0:
        return HeadOrientation(None, None, forward, lateral, margins)
    up_sign = 1.0 if offset > 0 else -1.0
    up = _signed(up_axis, up_sign)
    rotation = _axis_rotation(up_axis, up_sign, forward_axis, forward_sign)
    return HeadOrientation(rotation, up, forward, lateral, margins)


def _mirror_asymmetry(p: np.ndarray, max_points: int) -> list[float]:
    """Per axis, the mean distance from each mirrored point of a regular subsample of ``p``
    (at most ``max_points``) to the nearest point of the subsample (unit-sphere units)."""
    sample = p[:: max(1, int(np.ceil(p.shape[0] / max_points)))]
    tree = KDTree(sample)
    asymmetry = []
    for a in range(3):
        mirrored = sample.copy()
        # mirror about the plane through the mean along a (bounding-box centres are pulled
        # by one-sided features such as the nose on the forward axis; the mean is not)
        mirrored[:, a] = 2 * sample[:, a].mean() - mirrored[:, a]
        asymmetry.append(float(tree.query(mirrored)[0].mean()))
    return asymmetry


def _extreme_spreads(p: np.ndarray, axes: list[int]) -> dict:
    """{(axis, sign): RMS distance to the extreme point of the points within 0.05 of it}
    for both signs of each of ``axes``: small at a sharp extreme (the nose tip)."""
    spreads = {}
    for a in axes:
        for sign in (1.0, -1.0):
            height = sign * p[:, a]
            near = height >= height.max() - 0.05
            tip = p[np.argmax(height)]
            spreads[(a, sign)] = float(np.sqrt(np.mean(np.sum((p[near] - tip) ** 2, axis=1))))
    return spreads


def _side_parts_vote(p, inner, inner_labels, lateral_axis: int, up_axis: int, nose) -> dict:
    """{"side_parts": weighted mean height above the nose tip of the inner parts off the
    mid-plane}, or {} when there are none."""
    votes = {}
    # paired side parts (eyeballs, lashes, lacrimal fluid: off the mid-plane) sit above the
    # nose tip; parts on the mid-plane (teeth, tongue) are left out
    if inner.shape[0]:
        counts = np.bincount(inner_labels)
        ids = np.flatnonzero(counts)
        centroids = np.stack([inner[inner_labels == i].mean(0) for i in ids])
        side = np.abs(centroids[:, lateral_axis] - p[:, lateral_axis].mean()) > 0.1
        if side.any():
            weights = counts[ids][side]
            rise = np.average(centroids[side, up_axis] - nose[up_axis], weights=weights)
            votes["side_parts"] = float(rise)
    return votes


def _neck_cut_vote(p, faces, main, up_axis: int) -> dict:
    """{"boundary": how far below the middle (in half-heights) the skin's longest open
    boundary lies along ``up_axis``}, or {} when the skin is closed."""
    votes = {}
    # the longest open boundary of the skin (a neck or shoulder cut) lies at the bottom
    cut = _longest_boundary(p, faces[main[faces].all(axis=1)], np.cumsum(main) - 1)
    if cut is not None:
        half = 0.5 * (p[:, up_axis].max() - p[:, up_axis].min())
        votes["boundary"] = float(
            -(cut[up_axis] - 0.5 * (p[:, up_axis].max() + p[:, up_axis].min())) / half
        )
    return votes


def _axis_rotation(up_axis: int, up_sign: float, forward_axis: int, forward_sign: float):
    """(3, 3) right-handed rotation taking the signed up axis to +y and forward to +z."""
    rotation = np.zeros((3, 3))
    rotation[1, up_axis] = up_sign
    rotation[2, forward_axis] = forward_sign
    rotation[0] = np.cross(rotation[1], rotation[2])  # right-handed: x = y cross z
    return rotation


def _longest_boundary(points: np.ndarray, faces: np.ndarray, index: np.ndarray):
    """Centre (3,) of the longest boundary loop (by length) of ``faces`` (original vertex
    numbers, mapped by ``index`` into ``points``), or None for a closed surface."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as components

    if faces.shape[0] == 0:
        return None
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    border = index[unique[counts == 1]]
    if border.shape[0] < 3:
        return None
    n = points.shape[0]
    graph = coo_matrix((np.ones(border.shape[0]), (border[:, 0], border[:, 1])), shape=(n, n))
    _, loop = components(graph, directed=False)
    length = np.linalg.norm(points[border[:, 0]] - points[border[:, 1]], axis=1)
    loop_of_edge = loop[border[:, 0]]
    total = np.bincount(loop_of_edge, weights=length)
    best = np.argmax(total)
    chosen = border[loop_of_edge == best]
    midpoints = 0.5 * (points[chosen[:, 0]] + points[chosen[:, 1]])
    weights = length[loop_of_edge == best]
    return np.average(midpoints, axis=0, weights=weights)


# ------------------------------------------------------------- deciding from the fitted face
SEARCH_POINTS = 240
"""Template points of the inner face fitted from each of the 24 starts (a regular subsample)."""
INNER_FACE_CM = 2.0
"""The inner face: the ICT face-part vertices within this distance (cm) of an ICT landmark
(brows, eyes, nose, mouth, jaw line); a face-only mask keeps it, a neck or a crown adds
nothing to it."""
FIT_TRIM = 0.7
"""Fraction of closest-point pairs the trimmed ICP keeps (a crop may miss part of the inner
face; the wrong starts still leave 30 % of it far away)."""
FIT_LIMIT = 0.012
"""The best start's trimmed RMS over the fitted inner face's size must be below this (the
two Rocketbox heads and their face crops, the validation set: 0.005-0.008; a wrong start
0.015-0.03)."""
AGREE_RATIO = 1.5
"""Every start that fits within this factor of the best must have converged to the same
rotation (within ``AGREE_DEGREES``) — else two orientations explain the head and it is
refused."""
AGREE_DEGREES = 15.0
SNAP_DEGREES = 20.0
"""The found rotation must lie this close to one of the 24 axis-aligned orientations (the
head turned by a multiple of 90 degrees, as files store them); a head turned by another
angle is refused, naming the angle."""


REFINED = 3
"""The search's best distinct rotations refined onto the surface and compared."""
SCALE_RANGE = (0.75, 1.33)
"""The search's scale of the head's face to ICT's (a head in centimetres)."""


class OrientationError(ValueError):
    """The head's orientation could not be decided: the message says why and asks the caller
    to state it (``up=``/``forward=``; ``canrig autorig --up/--forward``)."""


def axis_rotations() -> Float[np.ndarray, "24 3 3"]:
    """(24, 3, 3) the proper rotations that permute and flip the axes."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            rotation = np.zeros((3, 3))
            rotation[np.arange(3), perm] = signs
            if np.linalg.det(rotation) > 0:
                out.append(rotation)
    return np.stack(out)


def parse_axis(text: str, argument: str) -> Float[np.ndarray, " 3"]:
    """A signed axis ("+y", "-z", "x") as a unit vector; ValueError naming ``argument``."""
    spelled = str(text).strip().lower()
    sign = -1.0 if spelled.startswith("-") else 1.0
    letter = spelled.lstrip("+-")
    if letter not in AXES or len(spelled) - len(letter) > 1:
        raise ValueError(f"{argument}: expected a signed axis such as +y, -z or x, got {text!r}")
    vector = np.zeros(3)
    vector[AXES.index(letter)] = sign
    return vector


def _axis_name(vector: np.ndarray) -> str:
    a = int(np.argmax(np.abs(vector)))
    return _signed(a, float(np.sign(vector[a])))


def _angle_degrees(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@dataclasses.dataclass(frozen=True)
class OrientationDecision:
    """How a head is turned into the convention (+y up, +z forward), as decided by
    ``decide_orientation``.

    Attributes:
        rotation: (3, 3) proper axis-aligned rotation: ``vertices @ rotation.T`` is the head
            in the convention.
        up, forward: the head's own up and forward axes ("+z", "-y", ...).
        source: "stated" (``up=``/``forward=`` given) or "fitted" (found from the face).
        fit: {"rms_ratio": the best start's trimmed RMS over the inner face's size,
            "runner_up_ratio": the best start of another orientation, "off_axis_degrees":
            the found rotation's angle from ``rotation``} (empty when stated).
    """

    rotation: Float[np.ndarray, "3 3"]
    up: str
    forward: str
    source: str
    fit: dict

    @property
    def conventional(self) -> bool:
        return bool(np.allclose(self.rotation, np.eye(3)))

    def describe(self) -> str:
        return f"up {self.up}, facing {self.forward} ({self.source})"


def stated_orientation(up: str, forward: str) -> OrientationDecision:
    """The decision a caller states: ``up`` and ``forward`` as signed axes of the head."""
    u, f = parse_axis(up, "up"), parse_axis(forward, "forward")
    if abs(float(u @ f)) > 0:
        raise ValueError(f"up, forward: expected two different axes, got {up!r} and {forward!r}")
    rotation = np.stack([np.cross(u, f), u, f])
    return OrientationDecision(rotation, _axis_name(u), _axis_name(f), "stated", {})


def inner_face(dataset: AutorigDataset) -> Bool[np.ndarray, " Vs"]:
    """(Vs,) bool: the generic ICT head's inner face (see ``INNER_FACE_CM``)."""
    from ._data import vertex_parts

    head = dataset.head
    neutral = np.asarray(head.neutral, np.float64)
    near = KDTree(neutral[np.asarray(head.landmarks)]).query(neutral)[0] < INNER_FACE_CM
    return near & (vertex_parts(head) == list(head.part_names).index("Face"))


def _coarse_icp(points, tree, start, iterations: int = 25):
    """Trimmed point-to-vertex ICP of the template ``points`` onto the head's vertices
    (``tree``) from an axis-aligned start (``start``: head -> convention), the template's
    nose tip on the head's extreme along the start's forward axis, scale 1 (centimetres):
    (rotation template -> head, scale, trimmed RMS). Fast (a KD-tree query per iteration)
    and biased by the vertex spacing alike for every start, which is all the search needs."""
    from ..mesh import similarity_transform

    target = tree.data
    rotation, scale = start.T, 1.0
    tip = target[np.argmax(target @ start[2])]
    translation = tip - points[np.argmax(points[:, 2])] @ rotation.T
    keep = max(3, int(round(FIT_TRIM * points.shape[0])))
    rms = np.inf
    for _ in range(iterations):
        moved = scale * points @ rotation.T + translation
        distance, nearest = tree.query(moved)
        kept = np.argsort(distance)[:keep]
        rms = float(np.sqrt(np.mean(distance[kept] ** 2)))
        found, rotation, _ = similarity_transform(points[kept], target[nearest[kept]])
        # a trimmed fit may shrink onto a few vertices: faces differ from ICT's by less
        scale = float(np.clip(found, *SCALE_RANGE))
        source, goal = points[kept], target[nearest[kept]]
        translation = goal.mean(0) - scale * source.mean(0) @ rotation.T
    return rotation, scale, rms


ORIENTATION_TEMPLATE = Path(str(files("canrig_jax.autorig") / "models" / "ict_inner_face.npy"))
"""The points ``decide_orientation`` fits, packaged so that it (and ``auto_rig``'s network
method) runs without the data folder: ``orientation_points`` of the generic ICT head, float32
centimetres, derived from the ICT Face Model like the packaged network weights."""


def orientation_points(dataset: AutorigDataset | None = None) -> Float[np.ndarray, "N 3"]:
    """(N, 3) cm: the regular subsample of the ICT inner face that ``decide_orientation``
    fits (``SEARCH_POINTS`` at most), from ``dataset`` (``ict_pose_source()``) or, when None,
    the packaged copy (``ORIENTATION_TEMPLATE``)."""
    if dataset is None:
        points = np.load(ORIENTATION_TEMPLATE, allow_pickle=False)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise ValueError(f"{ORIENTATION_TEMPLATE}: damaged orientation template")
        return points
    template = np.asarray(dataset.head.neutral)[inner_face(dataset)]
    return template[:: max(1, int(np.ceil(template.shape[0] / SEARCH_POINTS)))]


NOSE_BAND_CM = (1.0, 2.5)
"""``face_cues``: the bands above and below the nose tip (cm along the up axis) whose most
forward points the nose tip is compared with."""


CUE_MARGIN_CM = 0.2
"""Both face cues must exceed this (cm) to settle a tie: a face turned on its side shows a
nose forward but an up cue of about 0 (its bands cross the cheeks); upright ICT and Rocketbox
faces (validation) show 0.5-1.0 cm up and 2.3-4.5 cm forward."""


def face_cues(
    vertices: Float[ArrayLike, "V 3"], to_convention: Float[ArrayLike, "3 3"]
) -> tuple[float, float]:
    """A face's own cues of which way it is turned, for a head in centimetres turned into the
    convention by ``vertices @ to_convention.T`` (+y up, +z forward).

    Returns (forward, up), both > ``CUE_MARGIN_CM`` for a face the right way: ``forward``,
    how far (cm) the nose tip (the most forward point of the middle fifth, across) stands
    ahead of the outer cheeks' most forward point (|x| beyond 0.3 of the width); ``up``, how
    much further (cm) the face falls back below the nose tip (the upper lip) than above it
    (the bridge), in ``NOSE_BAND_CM`` along the middle. A face upside down or seen from
    behind gives a negative cue."""
    h = np.asarray(vertices, np.float64) @ np.asarray(to_convention, np.float64).T
    h = h - np.median(h, axis=0)
    width = float(np.ptp(h[:, 0]))
    middle = np.abs(h[:, 0]) < 0.1 * width
    outer = np.abs(h[:, 0]) > 0.3 * width
    if not middle.any() or not outer.any():
        return -1.0, -1.0
    tip = h[middle][np.argmax(h[middle, 2])]
    forward = float(tip[2] - h[outer, 2].max())
    strip = np.abs(h[:, 0] - tip[0]) < 0.05 * width
    low, high = NOSE_BAND_CM

    def recession(sign: float) -> float:
        band = strip & (sign * (h[:, 1] - tip[1]) > low) & (sign * (h[:, 1] - tip[1]) < high)
        return float(tip[2] - h[band, 2].max()) if band.any() else 0.0

    return forward, recession(-1.0) - recession(1.0)


def _settled_by_cues(v, candidates, starts, best_ratio: float, state: str):
    """The one candidate (ratio, rotation) among those that fit almost equally whose
    axis-aligned orientation (as files store heads) shows both face cues; rotations that snap
    to the same orientation are one. Else an ``OrientationError``."""
    tied: dict[tuple, tuple[float, np.ndarray]] = {}
    for ratio, rotation in candidates:
        if ratio <= AGREE_RATIO * best_ratio:
            axes = min(starts, key=lambda r, t=rotation.T: _angle_degrees(r, t))
            tied.setdefault(tuple(np.rint(axes).astype(int).ravel()), (ratio, rotation))
    settled = [
        c
        for k, c in tied.items()
        if min(face_cues(v, np.reshape(k, (3, 3)).astype(np.float64))) > CUE_MARGIN_CM
    ]
    if len(settled) != 1:
        ratios = sorted(c[0] for c in candidates)[:2]
        raise OrientationError(
            f"vertices: cannot tell which way the head faces: two orientations fit the face "
            f"almost equally (RMS ratios {ratios[0]:.4f} and {ratios[1]:.4f}) and the face's "
            f"own cues (nose forward, nose's underside below) do not settle it; {state}"
        )
    return settled[0]


def decide_orientation(
    dataset: AutorigDataset | None,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    up: str | None = None,
    forward: str | None = None,
) -> OrientationDecision:
    """Which way a head (centimetres) faces, decided from a fit of the ICT inner face, or
    refused — never guessed.

    The ICT inner face (``inner_face``) is fitted to the head by trimmed ICP from each of the
    24 axis-aligned starts. The head's orientation is the best fit's when (1) it fits
    (``FIT_LIMIT``), (2) every start that fits nearly as well (``AGREE_RATIO``) found the same
    rotation — or, where two fit almost equally (a face-only mask), exactly one of them shows
    the face's own cues (``face_cues``: the nose forward, the nose's underside below) — and
    (3) that rotation is a multiple of 90 degrees about the axes (``SNAP_DEGREES``). A
    mirrored head is a head: it is turned, not refused.

    Args:
        dataset: the ICT source (``ict_pose_source()``), or None for the packaged template
            (the same points, ``orientation_points``).
        vertices: (V, 3) head in centimetres (any orientation); faces: (F, 3) triangles.
        up, forward: the caller's statement ("+z", "-y", ...): skips the search (both or
            neither).

    Returns an ``OrientationDecision``. Raises ``OrientationError`` (a ValueError) naming
    ``up``/``forward`` when the head cannot be decided.
    """
    from ..mesh import similarity_icp

    if (up is None) != (forward is None):
        raise ValueError("up, forward: state both of the head's axes or neither")
    if up is not None and forward is not None:
        return stated_orientation(up, forward)
    vertices, faces = check_mesh(vertices, faces)
    v = np.asarray(vertices, np.float64)
    points = np.asarray(orientation_points(dataset), np.float64)
    size = float(np.linalg.norm(np.ptp(points, axis=0)))
    starts = axis_rotations()
    tree = KDTree(v)
    found, ratios = [], []
    for start in starts:
        rotation, scale, rms = _coarse_icp(points, tree, start)
        found.append(rotation)  # template -> head
        ratios.append(rms / max(scale * size, 1e-12))
    # the leading distinct rotations of the search, refined onto the surface (trimmed ICP
    # from each one's nearest axis-aligned start): the decision is made on these
    candidates: list[tuple[float, np.ndarray]] = []
    for i in np.argsort(ratios):
        if len(candidates) == REFINED:
            break
        if any(_angle_degrees(found[i], r) <= AGREE_DEGREES for _, r in candidates):
            continue
        start = min(starts, key=lambda r, i=i: _angle_degrees(r, found[i].T))
        refined = similarity_icp(points, v @ start.T, faces, trim=FIT_TRIM, iterations=30)
        ratio = refined.rms / max(refined.scale * size, 1e-12)
        candidates.append((float(ratio), start.T @ refined.rotation))
    candidates.sort(key=lambda c: c[0])
    best_ratio, best_rotation = candidates[0]
    to_convention = best_rotation.T  # head -> template frame
    snapped = min(starts, key=lambda r: _angle_degrees(r, to_convention))
    off = _angle_degrees(snapped, to_convention)
    runner_up = candidates[1][0] if len(candidates) > 1 else float("inf")
    fit = {"rms_ratio": best_ratio, "runner_up_ratio": runner_up, "off_axis_degrees": off}
    state = "state it: up= and forward= (canrig autorig --up=+z --forward=-y, for example)"
    if not best_ratio <= FIT_LIMIT:
        raise OrientationError(
            f"vertices: cannot tell which way the head faces: the ICT face fits it nowhere "
            f"(best trimmed RMS {best_ratio:.3f} of the face's size > {FIT_LIMIT}); is it a "
            f"human(-like) face in centimetres? {state}"
        )
    if runner_up <= AGREE_RATIO * best_ratio:
        best_ratio, best_rotation = _settled_by_cues(v, candidates, starts, best_ratio, state)
        fit["settled_by"] = "face cues"
        to_convention = best_rotation.T
        snapped = min(starts, key=lambda r: _angle_degrees(r, to_convention))
        off = _angle_degrees(snapped, to_convention)
        fit["off_axis_degrees"] = off
    if off > SNAP_DEGREES:
        raise OrientationError(
            f"vertices: the head is turned {off:.0f} degrees away from every axis-aligned "
            f"orientation; turn it upright (y up, facing +z) first, or {state}"
        )
    return OrientationDecision(
        snapped, _axis_name(snapped[1]), _axis_name(snapped[2]), "fitted", fit
    )
