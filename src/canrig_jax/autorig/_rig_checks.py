"""A rigger's functional checks of an ARKit face rig: does the blink close the eye, does the
jaw open the lips, do the eyes turn as balls, does the mesh stay whole under motion.

Each check is a named pass/fail with its number, independent of any artist's style. The
limits were set on the artists' own rigs (ICT, both Rocketbox heads, MakeHuman: every artist
rig passes every hard check) and on generated rigs a rigger rejects on sight (see the
checks page of the docs for the calibration). *Hard* checks are those a rig must pass to be
written without a warning; *soft* ones are reported (an artist's own rig can miss them: the
Rocketbox artists' ``mouthClose`` does not seal the lips).

Everything is measured on the rig's neutral and its own shapes, in millimetres where a value
has a unit; the parts (skin, eyeballs, lower teeth) are found from the mesh itself."""

import dataclasses
import os
import textwrap
from collections.abc import Callable, Sequence

import numpy as np
from jaxtyping import ArrayLike, Float, Int
from scipy.spatial import cKDTree

from ..data import arkit_name_of
from ..mesh import (
    connected_components,
    edge_stretch,
    flipped_triangles,
    mesh_edges,
    rigid_residual,
    self_intersections,
)
from ..rig import UNIT_IN_CM, BlendshapeRig, evaluate_batch, random_sparse_poses
from ._orientation import parse_axis

LIMITS: dict[str, tuple[float, str, bool]] = {
    "blink_closes": (0.25, "<=", True),
    "lids_clear_eyes": (0.50, "<=", False),
    "jaw_opens_lips": (2.0, ">=", True),
    "chin_moves_down": (2.0, ">=", True),
    "mouth_close_seals": (0.50, "<=", False),
    "eyes_turn": (0.5, ">=", False),
    "eyes_rigid": (0.15, "<=", True),
    "lower_teeth_rigid": (0.05, "<=", True),
    "symmetry": (0.50, "<=", False),
    "locality": (0.15, "<=", True),
    "flipped_triangles": (0.008, "<=", True),
    "self_intersections": (0.03, "<=", True),
    "edge_stretch": (40.0, "<=", False),
}
"""Each check's limit, its direction (the value must be ``<=`` or ``>=`` it) and whether it is
hard. Units are those of ``MEANING``."""

MEANING: dict[str, str] = {
    "blink_closes": "share of the eyeball's open front still seen at eyeBlink = 1 (worse eye)",
    "lids_clear_eyes": "share of the moving lid vertices that enter the eyeball at eyeBlink = 1",
    "jaw_opens_lips": "mm the lips open at jawOpen = 1 (0 when they do not open monotonically)",
    "chin_moves_down": "mm the chin moves down at jawOpen = 1",
    "mouth_close_seals": "share of jawOpen's lip gap left with mouthClose = 1 on top",
    "eyes_turn": "mm the least-moving eyeball moves under its eyeLook shapes (the most)",
    "eyes_rigid": "rigid-fit residual of an eyeball under eyeLook, over its motion (worst)",
    "lower_teeth_rigid": "rigid-fit residual of the lower teeth (the jaw's most rigid part) "
    "under jawOpen, over its motion",
    "symmetry": "median over Left/Right pairs of |mirrored Left - Right| / |Right|",
    "locality": "worst share of a shape's motion outside its region (brows below the mouth, "
    "mouth above the eyes)",
    "flipped_triangles": "skin triangles turned inside out per frame, as a share of the skin's",
    "self_intersections": "new crossings (edge through triangle) per frame, per skin triangle",
    "edge_stretch": "worst skin edge length over its neutral length, over all frames",
}
"""What each check's value measures."""

_UPPER = ("browDown", "browInnerUp", "browOuterUp", "eyeBlink", "eyeWide")
_LOWER = ("jaw", "mouth")


@dataclasses.dataclass(frozen=True)
class Check:
    """One check: ``value`` (None where the rig has no such part: it passes), its ``limit``,
    ``ok``, and whether it is ``hard``."""

    name: str
    value: float | None
    limit: float
    ok: bool
    hard: bool

    @property
    def meaning(self) -> str:
        return MEANING[self.name]


@dataclasses.dataclass(frozen=True)
class RigCheck:
    """The checks of one rig (``check_rig``).

    Attributes:
        checks: every ``Check``, in ``LIMITS`` order.
        poses: (T, K) the weights the geometry checks drove the rig with (rig order).
        source: ``"take"`` or ``"random sparse poses"``.
        flips: (T,) flipped skin triangles in each frame; intersections: (T,) new crossings.
    """

    checks: tuple[Check, ...]
    poses: Float[np.ndarray, "T K"]
    source: str
    flips: Int[np.ndarray, " T"]
    intersections: Int[np.ndarray, " T"]

    @property
    def ok(self) -> bool:
        """Every hard check passes."""
        return all(c.ok for c in self.checks if c.hard)

    @property
    def failed(self) -> tuple[str, ...]:
        """Names of the failed hard checks."""
        return tuple(c.name for c in self.checks if c.hard and not c.ok)

    def __getitem__(self, name: str) -> Check:
        return next(c for c in self.checks if c.name == name)

    def worst_frames(self, n: int = 6, apart: int = 10) -> Int[np.ndarray, " n"]:
        """Indices of up to ``n`` frames with the most flips and crossings, worst first, each
        at least ``apart`` frames from those before it (one per bad moment of a take)."""
        picked: list[int] = []
        for t in np.argsort(-(self.flips + self.intersections), kind="stable"):
            if all(abs(int(t) - p) >= apart for p in picked):
                picked.append(int(t))
            if len(picked) == n:
                break
        return np.asarray(picked, np.int64)

    def as_dict(self) -> dict[str, dict]:
        """{name: {"ok", "value"}} (JSON-ready)."""
        return {c.name: {"ok": c.ok, "value": c.value} for c in self.checks}

    def table(self) -> str:
        """A Markdown table: check, hard/soft, value, limit, pass."""
        rows = ["| check | kind | value | limit | pass | measures |", "|---|---|---|---|---|---|"]
        for c in self.checks:
            value = "n/a" if c.value is None else f"{c.value:.4g}"
            sign = LIMITS[c.name][1]
            rows.append(
                f"| {c.name} | {'hard' if c.hard else 'soft'} | {value} | {sign} {c.limit:g} "
                f"| {'yes' if c.ok else 'NO'} | {c.meaning} |"
            )
        return "\n".join(rows)

    def summary(self) -> str:
        """One line: how many checks pass, and the failed ones by name."""
        failed_soft = [c.name for c in self.checks if not c.hard and not c.ok]
        text = f"{sum(c.ok for c in self.checks)}/{len(self.checks)} rig checks pass"
        if self.failed:
            text += f"; FAILED (hard): {', '.join(self.failed)}"
        if failed_soft:
            text += f"; soft: {', '.join(failed_soft)}"
        return text


@dataclasses.dataclass(frozen=True)
class _Head:
    """The rig's neutral in cm, its parts and axes."""

    neutral: np.ndarray
    faces: np.ndarray
    skin: np.ndarray  # (V,) bool
    skin_faces: np.ndarray  # (F,) bool
    eyes: tuple[np.ndarray, ...]  # vertex indices of each eyeball
    spheres: tuple[tuple[np.ndarray, float], ...]  # (centre, radius) of each eyeball, cm
    others: tuple[np.ndarray, ...]  # vertex indices of the other parts (teeth, tongue, ...)
    up: np.ndarray
    forward: np.ndarray
    lateral: np.ndarray
    edge: float  # median skin edge length, cm


def _sphere_fit(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere through ``points``: centre, radius, RMS radial residual."""
    a = np.c_[2 * points, np.ones(len(points))]
    solution, *_ = np.linalg.lstsq(a, (points**2).sum(1), rcond=None)
    centre = solution[:3]
    radius = float(np.sqrt(max(solution[3] + centre @ centre, 1e-12)))
    residual = float(np.sqrt(np.mean((np.linalg.norm(points - centre, axis=1) - radius) ** 2)))
    return centre, radius, residual


def _head(rig: BlendshapeRig, up: str, forward: str) -> _Head:
    neutral = np.asarray(rig.neutral, np.float64) * UNIT_IN_CM[rig.units]
    faces = np.asarray(rig.faces, np.int64)
    labels = connected_components(faces, len(neutral))
    skin_label = np.bincount(labels[faces[:, 0]]).argmax()
    skin = labels == skin_label
    eyes, spheres, others = [], [], []
    for label in np.unique(labels[faces[:, 0]]):
        if label == skin_label:
            continue
        index = np.flatnonzero(labels == label)
        if len(index) >= 20:
            centre, radius, residual = _sphere_fit(neutral[index])
            if 0.6 <= radius <= 2.0 and residual <= 0.06 * radius:
                eyes.append(index)
                spheres.append((centre, radius))
                continue
        others.append(index)
    up_axis, forward_axis = parse_axis(up, "up"), parse_axis(forward, "forward")
    if abs(up_axis @ forward_axis) > 0.5:
        raise ValueError(f"up, forward: {up} and {forward} are not two different axes")
    skin_faces = skin[faces].all(axis=1)
    edges = mesh_edges(faces[skin_faces])
    edge = float(np.median(np.linalg.norm(neutral[edges[:, 0]] - neutral[edges[:, 1]], axis=1)))
    return _Head(
        neutral, faces, skin, skin_faces, tuple(eyes), tuple(spheres), tuple(others),
        up_axis, forward_axis, np.cross(up_axis, forward_axis), edge,
    )  # fmt: skip


class _Probe:
    """The rig evaluated (cm) at single shapes and a few combinations, by ARKit name."""

    def __init__(self, rig: BlendshapeRig, index: dict[str, int]):
        self.rig, self.index, self._cache = rig, index, {}
        self.scale = UNIT_IN_CM[rig.units]

    def has(self, *names: str) -> bool:
        return all(n in self.index for n in names)

    def poses(self, combos: Sequence[dict[str, float]]) -> np.ndarray:
        """(N, V, 3) float64 meshes (cm) at the weight dicts ``combos``."""
        missing = [c for c in combos if tuple(sorted(c.items())) not in self._cache]
        if missing:
            w = np.zeros((len(missing), self.rig.n_blendshapes), np.float32)
            for row, combo in enumerate(missing):
                for name, value in combo.items():
                    w[row, self.index[name]] = value
            meshes = np.asarray(evaluate_batch(self.rig, w), np.float64) * self.scale
            for combo, mesh in zip(missing, meshes, strict=True):
                self._cache[tuple(sorted(combo.items()))] = mesh
        return np.stack([self._cache[tuple(sorted(c.items()))] for c in combos])

    def delta(self, name: str, weight: float = 1.0) -> np.ndarray:
        """(V, 3) cm: the mesh at ``name`` = ``weight`` minus the neutral."""
        return self.poses([{name: weight}])[0] - self.poses([{}])[0]


def _check(name: str, value: float | None) -> Check:
    limit, sign, hard = LIMITS[name]
    ok = value is None or (value <= limit if sign == "<=" else value >= limit)
    return Check(name, None if value is None else float(value), limit, bool(ok), hard)


def _movers(delta: np.ndarray, where: np.ndarray, share: float) -> np.ndarray:
    """Vertices of ``where`` moving by more than ``share`` of the most any of them moves."""
    size = np.linalg.norm(delta, axis=1) * where
    return np.flatnonzero(size > share * max(float(size.max()), 1e-12))


def _ray_hits(origins, directions, triangles):
    """Ray n (origin, unit direction) against triangle n (3, 3): True where it hits."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = b - a, c - a
    h = np.cross(directions, e2)
    det = (e1 * h).sum(-1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origins - a
    u = inv * (s * h).sum(-1)
    q = np.cross(s, e1)
    v = inv * (directions * q).sum(-1)
    t = inv * (e2 * q).sum(-1)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)


def _visible(head: _Head, mesh: np.ndarray, eye: int) -> float:
    """Share of eyeball ``eye``'s front cap (its vertices within 60 degrees of the forward
    axis, seen from the sphere's centre) that a ray cast forward reaches without meeting
    the skin of ``mesh`` (the lids)."""
    centre, radius = head.spheres[eye]
    index = head.eyes[eye]
    cap = index[(head.neutral[index] - centre) @ head.forward > 0.5 * radius]
    tri = mesh[head.faces[head.skin_faces]]
    near = np.linalg.norm(tri.mean(axis=1) - centre, axis=1) < 2.0 * radius
    tri = tri[near]
    if len(cap) == 0 or len(tri) == 0:
        return 1.0
    origins = np.repeat(mesh[cap], len(tri), axis=0)
    hit = _ray_hits(
        origins, np.broadcast_to(head.forward, origins.shape), np.tile(tri, (len(cap), 1, 1))
    )
    return float((~hit.reshape(len(cap), len(tri)).any(axis=1)).mean())


def _entered(head: _Head, rest: np.ndarray, moved: np.ndarray, eye: int) -> np.ndarray:
    """(N,) which of the points entered eyeball ``eye`` by more than 0.5 mm (from outside
    at rest): behind the nearest eyeball vertex along its outward direction."""
    centre, _ = head.spheres[eye]
    ball = head.neutral[head.eyes[eye]]
    tree = cKDTree(ball)

    def depth(x):
        _, nearest = tree.query(x)
        outward = ball[nearest] - centre
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        return ((ball[nearest] - x) * outward).sum(1)

    return (depth(moved) > 0.05) & (depth(rest) <= 0.05)


def _blink_checks(head: _Head, probe: _Probe) -> list[Check]:
    """Each eyeBlink at 1 against the eyeball it covers the most: the share of its open
    front cap still visible, and the share of the lid's moving vertices inside it."""
    blinks = [n for n in ("eyeBlinkLeft", "eyeBlinkRight") if probe.has(n)]
    if not blinks:
        raise ValueError("rig: no eyeBlinkLeft/eyeBlinkRight shape (ARKit names) to check")
    if not head.eyes:
        return [_check("blink_closes", None), _check("lids_clear_eyes", None)]
    rest = probe.poses([{}])[0]
    open_ = [_visible(head, rest, e) for e in range(len(head.eyes))]
    left, entered = [], []
    for name in blinks:
        mesh = probe.poses([{name: 1.0}])[0]
        share = [_visible(head, mesh, e) / max(open_[e], 1e-9) for e in range(len(head.eyes))]
        eye = int(np.argmin(share))
        left.append(share[eye])
        lid = _movers(mesh - rest, head.skin, 0.25)
        entered.append(float(_entered(head, rest[lid], mesh[lid], eye).mean()) if len(lid) else 0.0)
    return [_check("blink_closes", max(left)), _check("lids_clear_eyes", max(entered))]


def _lip_pairs(head: _Head, jaw: np.ndarray) -> np.ndarray:
    """(P, 2) skin vertex pairs near each other at rest, sharing no edge, that ``jaw`` (the
    jawOpen delta) tears apart the most: the lips."""
    skin = np.flatnonzero(head.skin)
    pairs = cKDTree(head.neutral[skin]).query_pairs(3.0 * head.edge, output_type="ndarray")
    pairs = skin[pairs]
    edges = mesh_edges(head.faces)
    key = lambda e: e[:, 0].astype(np.int64) * len(head.neutral) + e[:, 1]  # noqa: E731
    pairs = pairs[~np.isin(key(np.sort(pairs, axis=1)), key(edges))]
    if len(pairs) == 0:
        return pairs
    gain = np.linalg.norm(
        head.neutral[pairs[:, 0]] + jaw[pairs[:, 0]] - head.neutral[pairs[:, 1]] - jaw[pairs[:, 1]],
        axis=1,
    ) - np.linalg.norm(head.neutral[pairs[:, 0]] - head.neutral[pairs[:, 1]], axis=1)
    best = np.argsort(-gain)[:60]
    return pairs[best[gain[best] >= 0.5 * gain[best[0]]]]


def _gaps(meshes: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    return np.linalg.norm(meshes[:, pairs[:, 0]] - meshes[:, pairs[:, 1]], axis=-1).mean(-1)


def _mouth_checks(head: _Head, probe: _Probe) -> list[Check]:
    if not probe.has("jawOpen"):
        raise ValueError("rig: no jawOpen shape (ARKit names) to check")
    jaw = probe.delta("jawOpen")
    pairs = _lip_pairs(head, jaw)
    steps = [{"jawOpen": w} for w in (0.0, 0.25, 0.5, 0.75, 1.0)]
    gaps = _gaps(probe.poses(steps), pairs) if len(pairs) else np.zeros(5)
    opening = 10.0 * (gaps[-1] - gaps[0]) if np.all(np.diff(gaps) > 0) else 0.0
    chin = _movers(jaw, head.skin, 0.9)
    down = -10.0 * float((jaw[chin] @ head.up).mean())
    sealed = None
    if probe.has("mouthClose") and len(pairs) and gaps[-1] > gaps[0]:
        both = _gaps(probe.poses([{"jawOpen": 1.0, "mouthClose": 1.0}]), pairs)[0]
        sealed = max(0.0, (both - gaps[0]) / (gaps[-1] - gaps[0]))
    return [
        _check("jaw_opens_lips", opening),
        _check("chin_moves_down", down),
        _check("mouth_close_seals", sealed),
    ]


def _part_motion(rest: np.ndarray, moved: np.ndarray) -> tuple[float, float]:
    """RMS motion (cm) of a part and its rigid-fit residual over that motion."""
    motion = float(np.sqrt(((moved - rest) ** 2).sum(1).mean()))
    return motion, float(rigid_residual(rest, moved)) / max(motion, 1e-9)


def _rigid_checks(head: _Head, probe: _Probe) -> list[Check]:
    looks = [n for n in probe.index if n.startswith("eyeLook")]
    turn, eye_residual = [], []
    for eye in head.eyes:
        moves = [_part_motion(head.neutral[eye], head.neutral[eye] + probe.delta(n)[eye])
                 for n in looks]  # fmt: skip
        turn.append(10.0 * max((m for m, _ in moves), default=0.0))
        eye_residual += [r for m, r in moves if m > 0.005]
    teeth = None
    if probe.has("jawOpen") and head.others:
        jaw = probe.delta("jawOpen")
        chin = float(np.linalg.norm(jaw[_movers(jaw, head.skin, 0.9)], axis=1).mean())
        residuals = []
        for part in head.others:
            motion, residual = _part_motion(head.neutral[part], head.neutral[part] + jaw[part])
            if len(part) >= 10 and motion >= 0.3 * chin:
                residuals.append(residual)
        teeth = min(residuals, default=None)  # the lower teeth: the jaw's most rigid part
    return [
        _check("eyes_turn", min(turn) if turn and looks else None),
        _check("eyes_rigid", max(eye_residual, default=None)),
        _check("lower_teeth_rigid", teeth),
    ]


def _symmetry(head: _Head, probe: _Probe) -> float | None:
    """Median over Left/Right pairs of |mirror(Left) - Right| / |Right| on the skin; None on a
    head that is not itself symmetric (its mirror more than two edges from itself)."""
    skin = np.flatnonzero(head.skin)
    x = head.neutral[skin]
    lateral = head.lateral / np.linalg.norm(head.lateral)
    plane = float(np.median(x @ lateral))
    mirror = lambda v: v - 2 * np.outer(v @ lateral - plane, lateral)  # noqa: E731
    distance, partner = cKDTree(x).query(mirror(x))
    if np.median(distance) > 2.0 * head.edge:
        return None
    errors = []
    for name in probe.index:
        twin = name[: -len("Left")] + "Right"
        if name.endswith("Left") and twin in probe.index:
            left, right = probe.delta(name)[skin], probe.delta(twin)[skin]
            mirrored = left[partner] - 2 * np.outer(left[partner] @ lateral, lateral)
            errors.append(np.linalg.norm(mirrored - right) / max(np.linalg.norm(right), 1e-9))
    return float(np.median(errors)) if errors else None


def _locality(head: _Head, probe: _Probe) -> float | None:
    """Worst share of a shape's skin motion outside its region: the upper face's shapes
    (brows, blinks, wide eyes) below the mouth, the jaw's and mouth's above the eyes (the
    mouth line: where jawOpen tears the lips; the eye line: the lids' blink motion)."""
    if not probe.has("jawOpen", "eyeBlinkLeft"):
        return None
    height = head.neutral @ head.up
    pairs = _lip_pairs(head, probe.delta("jawOpen"))
    lid = _movers(probe.delta("eyeBlinkLeft"), head.skin, 0.5)
    if len(pairs) == 0 or len(lid) == 0:
        return None
    mouth, eyes = float(height[pairs].mean()), float(height[lid].mean())
    worst = 0.0
    for name in probe.index:
        outside = None
        if name.startswith(_UPPER):
            outside = height < mouth
        elif name.startswith(_LOWER):
            outside = height > eyes
        if outside is not None:
            size = np.linalg.norm(probe.delta(name), axis=1) * head.skin
            worst = max(worst, float(size[outside].sum() / max(size.sum(), 1e-12)))
    return worst


def _motion_checks(head: _Head, rig: BlendshapeRig, poses: np.ndarray, progress) -> tuple:
    """Flipped triangles, new self-intersections of the skin and the worst edge stretch
    over the frames of ``poses``."""
    progress(f"evaluating the rig at {len(poses)} frames")
    frames = np.asarray(evaluate_batch(rig, poses, chunk=64), np.float64) * UNIT_IN_CM[rig.units]
    n_skin = max(int(head.skin_faces.sum()), 1)
    flips = flipped_triangles(frames, head.neutral, head.faces, mask=head.skin_faces).sum(1)
    progress("testing self-intersections")
    crossings = self_intersections(frames, head.neutral, head.faces, mask=head.skin_faces)
    stretch = edge_stretch(frames, head.neutral, head.faces[head.skin_faces])
    checks = [
        _check("flipped_triangles", flips.mean() / n_skin),
        _check("self_intersections", crossings.mean() / n_skin),
        _check("edge_stretch", float(stretch.max()) if stretch.size else None),
    ]
    return checks, flips, crossings


def _check_inputs(rig, poses) -> tuple[dict[str, int], np.ndarray | None]:
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if rig.faces is None:
        raise ValueError("rig: the checks need the rig's triangles (faces), this rig has none")
    index = {}
    for i, name in enumerate(rig.names):
        arkit = arkit_name_of(str(name))
        if arkit is not None:
            index.setdefault(arkit, i)
    if not {"eyeBlinkLeft", "jawOpen"} <= set(index):
        raise ValueError(
            "rig: the checks read ARKit shapes (eyeBlinkLeft, jawOpen, ...) and this rig has "
            f"none of those names (it has {list(rig.names)[:5]}...)"
        )
    if poses is not None:
        poses = np.asarray(poses, np.float32)
        if poses.ndim != 2 or poses.shape[1] != rig.n_blendshapes:
            raise ValueError(
                f"poses: expected (T, {rig.n_blendshapes}) weights in the rig's order, got "
                f"{poses.shape} (a take of another rig?)"
            )
        if not np.all(np.isfinite(poses)):
            raise ValueError("poses: contains NaN or infinite weights")
        if len(poses) == 0:
            raise ValueError("poses: no frames")
    return index, poses


def check_rig(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "T K"] | None = None,
    *,
    n_random: int = 120,
    seed: int = 0,
    up: str = "+y",
    forward: str = "+z",
    progress: Callable[[str], None] | None = None,
) -> RigCheck:
    """Run every rigger's check (``LIMITS``, ``MEANING``) on an ARKit face rig.

    Args:
        rig: a ``BlendshapeRig`` with faces and ARKit shape names (any spelling that
            ``data.arkit_name_of`` reads); any unit (values are reported in mm).
        poses: (T, K) weights in the rig's order to drive the geometry checks with (a take:
            ``LiveLinkCapture.weights_for(rig.names)``); None: ``n_random`` random sparse
            combinations of the rig's own shapes (``rig.random_sparse_poses``, ``seed``).
        up, forward: the head's up axis and the one its face looks along, in the rig's
            frame (a rig from ``auto_rig`` is +y up, facing +z).
        progress: called with a message before each long step.

    Returns:
        A ``RigCheck``: ``ok`` when every hard check passes, ``table()``, ``summary()``.

    Raises ValueError/TypeError naming ``rig`` or ``poses`` before any compiled work (no
    faces, no ARKit names, NaN, weights of another rig)."""
    index, poses = _check_inputs(rig, poses)
    head = _head(rig, up, forward)
    progress = progress or (lambda message: None)
    source = "take"
    if poses is None:
        source = "random sparse poses"
        poses = random_sparse_poses(np.random.default_rng(seed), n_random, list(rig.names))
    probe = _Probe(rig, index)
    checks = _blink_checks(head, probe) + _mouth_checks(head, probe) + _rigid_checks(head, probe)
    checks += [
        _check("symmetry", _symmetry(head, probe)),
        _check("locality", _locality(head, probe)),
    ]
    motion, flips, crossings = _motion_checks(head, rig, poses, progress)
    order = list(LIMITS)
    checks = sorted(checks + motion, key=lambda c: order.index(c.name))
    return RigCheck(tuple(checks), poses, source, flips, crossings)


def plot_check_frames(
    rig: BlendshapeRig,
    result: RigCheck,
    path: str | os.PathLike,
    *,
    n: int = 6,
    title: str | None = None,
) -> None:
    """A contact sheet (PNG at ``path``) of the ``n`` frames of ``result`` with the most
    flipped triangles and crossings, front view, each vertex coloured by how many flipped
    skin triangles touch it (0: grey). The rig must face +z with +y up."""
    import matplotlib.pyplot as plt

    from ..render import plot_vertex_scalar, save_figure

    frames = result.worst_frames(n)
    meshes = np.asarray(evaluate_batch(rig, result.poses[frames]), np.float64)
    neutral = np.asarray(rig.neutral, np.float64)
    faces = np.asarray(rig.faces)
    flipped = flipped_triangles(meshes, neutral, faces)
    moving = np.linalg.norm(meshes - neutral, axis=-1) > 0.02 * np.ptp(neutral, axis=0).max()
    face = neutral[moving.any(axis=0)] if moving.any() else neutral
    pad = 0.15 * np.ptp(face, axis=0)
    box = np.stack([face.min(axis=0) - pad, face.max(axis=0) + pad])  # the moving face, framed
    fig, axes = plt.subplots(1, len(frames), figsize=(2.4 * len(frames), 3.0), squeeze=False)
    for ax, t, mesh, bad in zip(axes[0], frames, meshes, flipped, strict=True):
        count = np.zeros(len(neutral))
        np.add.at(count, faces[bad].ravel(), 1.0)
        plot_vertex_scalar(
            ax, mesh, faces, count, vmin=0.0, vmax=3.0, cmap="Reds",
            title=f"frame {t}\n{result.flips[t]} flips, {result.intersections[t]} crossings",
        )  # fmt: skip
        ax.set_xlim(*box[:, 0])
        ax.set_ylim(*box[:, 1])
    fig.suptitle(textwrap.fill(title or result.summary(), 150), fontsize=8)
    save_figure(fig, path)


def failed_hard_checks(report: RigCheck) -> str:
    """The failed hard checks of ``report`` as one line: "name (value, limit L), ..."."""
    return ", ".join(
        f"{c.name} ({c.value:.3g}, limit {c.limit:g})" for c in report.checks if c.hard and not c.ok
    )
