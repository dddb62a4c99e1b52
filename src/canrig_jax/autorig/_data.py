"""Rigged training heads for RigAnyFace, from the real ICT assets.

* **Poses** (``PoseSet``): the 53 ICT expressions (one-hot pose vectors) plus combination
  poses (several ones) taken from the ict-quartic rig — the combinations whose corrective
  terms move the face most, by order (the paper used 48 FACS + 48 corrective poses). The
  ground-truth displacement of a pose is the quartic rig evaluated with weight 1 on its
  expressions (deltas plus every corrective whose expressions are all active).
* **Heads** (``RiggedHead``): an ICT identity (neutral + sum c_i mode_i, c ~ N(0, 1), the kit's
  ``randomize_identity``), whole head with all 17 parts, remeshed (``canrig_jax.mesh``)
  and its ground-truth displacements carried to the new vertices by the surface map. In the
  ICT model expression offsets are shared by all identities, so the ground truth of an
  identity is the shared displacement field sampled on its own surface.

Units: ``RiggedHead`` stores centimetres; ``normalise`` gives the unit-sphere view the
network is trained on.
"""

import dataclasses
import os
import warnings
from typing import Any

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Float32, Float64, Int
from scipy.spatial import KDTree

from .._warnings import warn
from ..data import ICTFaceModel, ict_identity, load_ict
from ..mesh import (
    Remeshed,
    SimilarityFit,
    TriangleCorrespondence,
    closest_point_correspondence,
    connected_components,
    decimate,
    similarity_transform,
    subdivide,
)
from ..rig import BlendshapeRig, deformation_transfer, evaluate_batch


@dataclasses.dataclass(frozen=True)
class PoseSet:
    """Poses of an auto-rig: each a set of basis expressions at weight 1.

    Attributes:
        basis_names: the A basis expressions (ICT: 53 ARKit names); pose vectors have length A.
        combinations: P tuples of basis indices; the first A are the single expressions
            (0,), (1,), ... in order, the rest combination poses of 2 to 4 expressions.
    """

    basis_names: tuple[str, ...]
    combinations: tuple[tuple[int, ...], ...]

    def __post_init__(self):
        a = len(self.basis_names)
        if tuple(self.combinations[:a]) != tuple((i,) for i in range(a)):
            raise ValueError("combinations: the first A poses must be the single expressions")
        for combo in self.combinations:
            if len(set(combo)) != len(combo) or not all(0 <= i < a for i in combo):
                raise ValueError(f"combinations: {combo} is not a set of basis indices < {a}")

    @property
    def n_basis(self) -> int:
        return len(self.basis_names)

    @property
    def n_poses(self) -> int:
        return len(self.combinations)

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple("+".join(self.basis_names[i] for i in c) for c in self.combinations)

    def vectors(self) -> Float32[np.ndarray, "P A"]:
        """(P, A) float32 pose vectors A_i (ones on the pose's expressions)."""
        out = np.zeros((self.n_poses, self.n_basis), np.float32)
        for p, combo in enumerate(self.combinations):
            out[p, list(combo)] = 1.0
        return out

    def to_dict(self) -> dict:
        return {
            "basis_names": list(self.basis_names),
            "combinations": [list(c) for c in self.combinations],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "PoseSet":
        return cls(tuple(d["basis_names"]), tuple(tuple(c) for c in d["combinations"]))


def quartic_pose_set(rig: BlendshapeRig, per_order: dict[int, int] | None = None) -> PoseSet:
    """The rig's single expressions plus its largest correctives as combination poses.

    Args:
        rig: a rig with correctives (the ict-quartic rig).
        per_order: how many combinations of each order to take, by decreasing corrective
            magnitude (sum of vertex offset norms); default {2: 25, 3: 12, 4: 6}, i.e. 53 + 43
            = 96 poses, the paper's count.
    """
    per_order = {2: 25, 3: 12, 4: 6} if per_order is None else per_order
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    for order, count in per_order.items():
        if not isinstance(count, int | np.integer) or count < 0 or order < 2:
            raise ValueError(
                f"per_order: expected counts >= 0 for orders >= 2, got {order}: {count!r}"
            )
    combos = [(i,) for i in range(rig.n_blendshapes)]
    for order, count in sorted(per_order.items()):
        table = rig.corrective(order)
        available = 0 if table is None else int(table.indices.shape[0])
        if count > available:
            raise ValueError(
                f"per_order: asked for {count} order-{order} combinations, the rig has {available}"
            )
        if count == 0 or table is None:
            continue
        size = np.linalg.norm(np.asarray(table.deltas), axis=-1).sum(axis=1)
        best = np.argsort(-size, kind="stable")[:count]
        combos += [tuple(int(i) for i in np.asarray(table.indices)[j]) for j in best]
    return PoseSet(tuple(rig.names), tuple(combos))


def pose_displacements(rig: BlendshapeRig, poses: PoseSet) -> Float32[np.ndarray, "P V 3"]:
    """(P, V, 3) float32 ground truth: the rig at weight 1 on each pose's expressions."""
    if not isinstance(rig, BlendshapeRig) or not isinstance(poses, PoseSet):
        raise TypeError(
            f"rig, poses: expected a BlendshapeRig and a PoseSet, got {type(rig).__name__}, "
            f"{type(poses).__name__}"
        )
    if tuple(rig.names) != poses.basis_names:
        raise ValueError("rig: its blendshape names differ from the pose set's basis names")
    neutral = np.asarray(rig.neutral)
    posed = evaluate_batch(rig, poses.vectors())
    return np.asarray(posed) - neutral[None]


def head_rig(face_rig: BlendshapeRig, head: ICTFaceModel) -> BlendshapeRig:
    """The whole-head rig: ICT's head deltas plus the face rig's correctives (the face part
    is the head's first vertices, so corrective vertex indices carry over unchanged)."""
    if tuple(face_rig.names) != tuple(head.names):
        raise ValueError("face_rig: its blendshape names differ from the head's")
    n_face = face_rig.n_vertices
    if not np.array_equal(head.vertex_ids[:n_face], np.arange(n_face)) or not np.allclose(
        np.asarray(face_rig.neutral), head.neutral[:n_face], atol=1e-5
    ):
        raise ValueError("face_rig: its vertices are not the first vertices of the head")
    return BlendshapeRig(head.neutral, head.deltas, face_rig.correctives, head.names, head.faces)


def vertex_parts(head: ICTFaceModel) -> Int[np.ndarray, " V"]:
    """(V,) index into ``head.part_names`` of every vertex."""
    part = np.empty(head.n_vertices, np.int32)
    for i, (lo, hi) in enumerate(head.part_vertex_range):
        part[lo:hi] = i
    return part


@dataclasses.dataclass(frozen=True)
class RiggedHead:
    """One training or test head with its ground-truth rig (centimetres).

    Attributes:
        name: e.g. "id07/decimate_1300".
        vertices: (V, 3) neutral; faces: (F, 3).
        displacements: (P, V, 3) ground-truth offsets for each pose of the pose set.
        landmarks: (68,) vertex nearest each ICT Multi-PIE landmark.
        parts: (V,) ICT part index of each vertex (of the source vertex it lies on).
        identity: (n,) identity coefficients; topology: remeshing label.
    """

    name: str
    vertices: Float[np.ndarray, "V 3"]
    faces: Int[np.ndarray, "F 3"]
    displacements: Float[np.ndarray, "P V 3"]
    landmarks: Int[np.ndarray, " L"]
    parts: Int[np.ndarray, " V"]
    identity: Float[np.ndarray, " n"]
    topology: str

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])


TOPOLOGIES = ("decimate_<n>", "subdivide_<n>")


def remesh_head(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], topology: str
) -> tuple[Remeshed, Remeshed | None]:
    """``decimate_<n>``: quadric decimation to ~n vertices; ``subdivide_<n>``: decimation to
    ~n vertices then one midpoint subdivision (~4n vertices, a regular 1-to-4 pattern).

    Returns (decimated, subdivided or None)."""
    kind, _, count = topology.partition("_")
    if kind not in ("decimate", "subdivide") or not count.isdigit():
        raise ValueError(f"topology: expected one of {TOPOLOGIES}, got {topology!r}")
    coarse = decimate(vertices, faces, int(count))
    if kind == "decimate":
        return coarse, None
    return coarse, subdivide(coarse.vertices, coarse.faces)


def make_head(
    head: ICTFaceModel,
    displacements: Float[ArrayLike, "P Vh 3"],
    coefficients: Float[ArrayLike, " n"],
    topology: str,
    *,
    name: str,
    data_dir: str | os.PathLike | None = None,
) -> RiggedHead:
    """An ICT identity remeshed to ``topology`` with the head's pose displacements carried.

    Args:
        head: the whole ICT head (``load_ict(parts=None)``).
        displacements: (P, V_head, 3) pose displacements on the head (``pose_displacements``).
        coefficients: (n,) identity coefficients.
        topology: see ``remesh_head``.
    """
    neutral = ict_identity(coefficients, data_dir, model=head)
    coarse, fine = remesh_head(neutral, head.faces, topology)
    carried = coarse.map.carry(np.asarray(displacements, np.float64))
    source_parts = vertex_parts(head)
    corner = np.argmax(coarse.map.barycentric, axis=1)
    parts = source_parts[head.faces[coarse.map.triangle, corner]]
    vertices, faces = coarse.vertices, coarse.faces
    if fine is not None:
        carried = fine.map.carry(carried)
        corner = np.argmax(fine.map.barycentric, axis=1)
        parts = parts[coarse.faces[fine.map.triangle, corner]]
        vertices, faces = fine.vertices, fine.faces
    landmarks = KDTree(vertices).query(neutral[head.landmarks])[1]
    return RiggedHead(
        name=name,
        vertices=np.asarray(vertices, np.float32),
        faces=np.asarray(faces, np.int32),
        displacements=np.asarray(carried, np.float32),
        landmarks=np.asarray(landmarks, np.int32),
        parts=np.asarray(parts, np.int32),
        identity=np.asarray(coefficients, np.float32),
        topology=topology,
    )


@dataclasses.dataclass(frozen=True)
class AutorigDataset:
    """Training and held-out heads of one pose set.

    Attributes:
        poses: the ``PoseSet``; head: the whole ICT head (generic identity, original mesh);
        head_displacements: (P, 26719, 3) ground truth on the original head;
        train: heads of the training identities in ``train_topologies``;
        test: {"same_topology": ..., "unseen_topology": ...} heads of held-out identities.
    """

    poses: PoseSet
    head: ICTFaceModel
    head_displacements: Float[np.ndarray, "P V 3"]
    train: list[RiggedHead]
    test: dict[str, list[RiggedHead]]


def ict_autorig_dataset(
    data_dir: str | os.PathLike | None = None,
    *,
    n_train: int = 24,
    n_test: int = 8,
    train_topologies: tuple[str, ...] = ("decimate_1000", "decimate_1600"),
    unseen_topology: str = "decimate_1300",
    per_order: dict[int, int] | None = None,
    seed: int = 0,
    progress: bool = True,
) -> AutorigDataset:
    """ICT identities remeshed into training and held-out heads with ground-truth rigs.

    Training identities (``n_train``) appear in every ``train_topologies``; held-out
    identities (``n_test``, drawn from another random stream) appear in the first training
    topology ("same_topology": same remeshing recipe, new identity) and in
    ``unseen_topology`` (a resolution never seen in training).
    """
    if unseen_topology in train_topologies:
        raise ValueError(f"unseen_topology: {unseen_topology!r} is also a training topology")
    if n_train < 1 or n_test < 1:
        raise ValueError(f"n_train, n_test: expected >= 1, got {n_train}, {n_test}")
    source = ict_pose_source(data_dir, per_order=per_order, progress=progress)
    head, poses, displacements = source.head, source.poses, source.head_displacements
    jobs = []
    train_rng = np.random.default_rng([seed, 0])
    for i in range(n_train):
        coefficients = train_rng.standard_normal(100)
        jobs += [("train", f"train{i:02d}/{t}", coefficients, t) for t in train_topologies]
    test_rng = np.random.default_rng([seed, 1])
    for i in range(n_test):
        coefficients = test_rng.standard_normal(100)
        jobs.append(
            (
                "same_topology",
                f"test{i:02d}/{train_topologies[0]}",
                coefficients,
                train_topologies[0],
            )
        )
        jobs.append(
            ("unseen_topology", f"test{i:02d}/{unseen_topology}", coefficients, unseen_topology)
        )
    if progress:
        from tqdm.auto import tqdm

        jobs = tqdm(jobs, desc="heads", dynamic_ncols=True)
    split: dict[str, list[RiggedHead]] = {"train": [], "same_topology": [], "unseen_topology": []}
    for group, name, coefficients, topology in jobs:
        split[group].append(
            make_head(head, displacements, coefficients, topology, name=name, data_dir=data_dir)
        )
    return AutorigDataset(
        poses=poses,
        head=head,
        head_displacements=displacements,
        train=split["train"],
        test={k: split[k] for k in ("same_topology", "unseen_topology")},
    )


def ict_pose_source(
    data_dir: str | os.PathLike | None = None,
    *,
    per_order: dict[int, int] | None = None,
    progress: bool = True,
) -> AutorigDataset:
    """What deformation transfer and copying carry onto a new head, without any training
    or held-out identity: the generic ICT head, the pose set (``quartic_pose_set``) and every
    pose's ground truth on the head. An ``AutorigDataset`` with no heads (``train`` empty,
    ``test`` empty), accepted wherever the baselines take a dataset (``transfer_poses``,
    ``copy_poses``, ``fit_head_landmarks``, ``head_correspondence``, ``face_placement``).
    Seconds with the quartic rig cached (``ict_quartic_rig``), minutes the first time."""
    from ..rig import ict_quartic_rig

    head = load_ict(data_dir, parts=None)
    face_rig, _ = ict_quartic_rig(data_dir, progress=progress)
    poses = quartic_pose_set(face_rig, per_order)
    displacements = pose_displacements(head_rig(face_rig, head), poses)
    return AutorigDataset(
        poses=poses, head=head, head_displacements=displacements, train=[], test={}
    )


def fit_head_landmarks(
    dataset: AutorigDataset,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    region: Bool[ArrayLike, " V"] | None = None,
) -> tuple[Int[np.ndarray, " L"], SimilarityFit]:
    """The ICT Multi-PIE landmarks placed on a new head with no hand-picked vertices: the
    ICT face part fitted to the head by a trimmed-ICP similarity
    (``canrig_jax.mesh.fit_landmarks``; the head in centimetres, y up, facing +z), each
    landmark snapped to the nearest head vertex (of ``region``, e.g. the skin, when given).

    Returns ((68,) vertex indices, the ``SimilarityFit``)."""
    from ..mesh import check_mesh, fit_landmarks

    head = dataset.head
    vertices, faces = check_mesh(vertices, faces)
    size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    reference = float(np.linalg.norm(np.ptp(head.neutral, axis=0)))
    if not 0.25 <= size / reference <= 4.0:
        warn(
            f"vertices: the head's bounding box is {size:.3g} across, the ICT head's "
            f"{reference:.3g} cm (a human head with neck: ~35-70 cm); is it in centimetres? "
            "(metres or decimetres given as centimetres look like this)",
        )
    face = vertex_parts(head) == list(head.part_names).index("Face")
    try:
        return fit_landmarks(
            head.neutral, head.landmarks, face, vertices, faces, target_region=region
        )
    except ValueError as error:  # name this function's argument, not fit_landmarks'
        message = (
            str(error).replace("target_vertices", "vertices").replace("target_region", "region")
        )
        raise ValueError(message + " (the ICT face part is fitted to it)") from error


def face_placement(
    dataset: AutorigDataset,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    fit: SimilarityFit | None = None,
) -> tuple[Float64[np.ndarray, " 3"], float]:
    """Centre and scale that place a head in the unit sphere as the model's training heads
    were placed, derived from the face instead of the head's bounding box (which moves with
    where the head was cropped: a neck, shoulders or none): the ICT face part is fitted to
    the head by a trimmed-ICP similarity (``fit_head_landmarks``) and the generic ICT head's
    bounding-box centre and radius (``normalise``, the training placement) are carried
    through that similarity.

    Args:
        vertices, faces: the head (centimetres, y up, facing +z, as ``fit_head_landmarks``).
        fit: a ``SimilarityFit`` already computed for this head (skips the fit).

    Returns ``(centre (3,), scale)`` for ``AbstractNetworkMethod.generate(..., placement=...)``.
    """
    from ._model import normalise

    if fit is None:
        _, fit = fit_head_landmarks(dataset, vertices, faces)
    _, centre, radius = normalise(dataset.head.neutral)
    return fit.apply(centre[None])[0], float(fit.scale * radius)


def head_correspondence(
    dataset: AutorigDataset,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    landmarks: Int[ArrayLike, " L"],
) -> TriangleCorrespondence:
    """The correspondence of the generic ICT head (``dataset.head``) with a new head
    (``closest_point_correspondence``: landmark similarity, thin-plate warp, component
    matching, closest points). ``landmarks``: (68,) vertices of the ICT Multi-PIE landmarks
    on the new head (``canrig_jax.mesh.fit_landmarks`` finds them). Closest points never
    cross the mouth or a lid slit (``slit_sides`` of each head, from its landmarks)."""
    from ._slits import slit_sides

    source = dataset.head
    return closest_point_correspondence(
        source.neutral, source.faces, vertices, faces, source.landmarks, landmarks,
        source_sides=slit_sides(source.neutral, source.faces, source.landmarks),
        target_sides=slit_sides(vertices, faces, landmarks),
    )  # fmt: skip


def _correspondence_of(dataset: AutorigDataset, head):
    """``head_correspondence`` of any head: its ``landmarks`` when it has them, else ICT's
    landmarks fitted to it (``fit_head_landmarks``, on its ``skin`` when it names one)."""
    for name in ("vertices", "faces"):
        if not hasattr(head, name):
            raise ValueError(f"head: expected an object with vertices and faces, no {name!r}")
    landmarks = getattr(head, "landmarks", None)
    if landmarks is None:
        landmarks, _ = fit_head_landmarks(
            dataset, head.vertices, head.faces, region=getattr(head, "skin", None)
        )
    return head_correspondence(dataset, head.vertices, head.faces, landmarks)


ANCHOR_MODES = ("vertex", "part", "skin_vertex")
"""How ``transfer_poses`` anchors (``anchor=``): per vertex; per part (the generic head's
connected components, each held as a whole or not at all); or per vertex on the skin (the
head's largest component: face, head and neck, mouth and eye sockets) and per part
elsewhere."""


def anchor_parts(head: ICTFaceModel, anchor: str) -> Int[np.ndarray, " V"] | None:
    """The ``static_parts`` labels of ``transfer_deltas`` for an ``ANCHOR_MODES`` entry on
    the generic ICT head: None for "vertex"; its connected components for "part"; the same
    with the largest component (the skin) -1 (per vertex) for "skin_vertex"."""
    if anchor not in ANCHOR_MODES:
        raise ValueError(f"anchor: expected one of {ANCHOR_MODES}, got {anchor!r}")
    if anchor == "vertex":
        return None
    labels = connected_components(np.asarray(head.faces), head.n_vertices).astype(np.int64)
    if anchor == "skin_vertex":
        labels[labels == np.bincount(labels).argmax()] = -1
    return labels


def transfer_poses(
    dataset: AutorigDataset,
    head: Any,
    correspondence: TriangleCorrespondence | None = None,
    *,
    static_below: float | None = None,
    anchor: str = "vertex",
) -> Float[np.ndarray, "P V 3"]:
    """The deformation-transfer baseline: every ground-truth pose of the generic ICT head
    carried onto ``head`` (Sumner & Popović; landmark + closest-point correspondence).

    Args:
        dataset: the source: ``ict_pose_source()`` (or an ``ict_autorig_dataset``).
        head: any head with ``vertices`` (centimetres, y up, facing +z) and ``faces`` — a
            ``RiggedHead``, a loaded mesh; its ``landmarks`` (68 ICT Multi-PIE vertices) are
            used when it has them, else fitted (``fit_head_landmarks``, no hand-picked
            vertices; on its ``skin`` when it has one).
        correspondence: a precomputed ``head_correspondence`` (else computed here).
        static_below: anchored transfer (``deformation_transfer(static_below=)``): per pose,
            the vertices whose carried ICT displacement is shorter than this (cm; e.g.
            0.001, the evaluation's static threshold of 0.01 mm) stay exactly still. None:
            plain DT.
        anchor: with ``static_below``, what is held (``ANCHOR_MODES``): "vertex" (default)
            each vertex by its own carried displacement; "part" a vertex only when the whole
            ICT connected component it is matched to is still in that pose (a part is held as
            a whole or not at all); "skin_vertex" per vertex on the skin, per part elsewhere.

    Returns (P, V, 3) displacements on ``head`` (centimetres)."""
    source = dataset.head
    static_parts = anchor_parts(source, anchor)
    if static_parts is not None and static_below is None:
        raise ValueError(f"anchor: {anchor!r} anchoring needs static_below (a threshold)")
    source_rig = BlendshapeRig(
        source.neutral, dataset.head_displacements, (), dataset.poses.labels, source.faces
    )
    if correspondence is None:
        correspondence = _correspondence_of(dataset, head)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "correctives are not transferred": there are none
        transferred = deformation_transfer(
            source_rig,
            head.vertices,
            correspondence,
            static_below=static_below,
            static_parts=static_parts,
        )
    return np.asarray(transferred.deltas)


def copy_poses(
    dataset: AutorigDataset, head: Any, correspondence: TriangleCorrespondence | None = None
) -> Float[np.ndarray, "P V 3"]:
    """The copy baseline: every ground-truth pose of the generic ICT head sampled at the
    corresponding surface point of each ``head`` vertex (no deformation-gradient solve),
    rotated into the head's orientation (the similarity of the carried ICT neutral onto the
    head; no scaling). (P, V, 3) displacements, centimetres."""
    if correspondence is None:
        correspondence = _correspondence_of(dataset, head)
    carried = correspondence.vertex_map.carry(dataset.head_displacements.astype(np.float64))
    _, rotation, _ = similarity_transform(
        correspondence.vertex_map.carry(dataset.head.neutral.astype(np.float64)),
        np.asarray(head.vertices, np.float64),
    )
    return (carried @ rotation.T).astype(np.float32)


MULTIPIE_REGIONS = {
    "eyes": tuple(range(36, 48)),
    "nose": tuple(range(27, 36)),
    "mouth": tuple(range(48, 68)),
}
"""Multi-PIE landmark indices (of ``RiggedHead.landmarks``) of the regions that
``SmoothWarp`` rescales: both eyes (one scaling, so the warp keeps the eyes alike), the nose,
the mouth."""


@dataclasses.dataclass(frozen=True)
class SmoothWarp:
    """A smooth deformation of space (centimetres): stylised proportions plus a low-frequency
    displacement field,

        w(x) = c + S (x - c) + sum_k a_k g_k(x) + sum_r (D_r - I)(x - m_r) h_r(x),

    with ``g_k(x) = exp(-|x - b_k|^2 / (2 radius^2))`` (Gaussian RBFs) and ``h_r`` the same
    around a region centre ``m_r`` with the region's own radius. The identity when every
    scale is 1 and every weight 0 (``SmoothWarp.identity``).

    Attributes:
        centre: (3,) c, the head's centre; scale: (3,) the diagonal of S (whole-head
            proportions).
        rbf_centres: (K, 3) b_k; rbf_weights: (K, 3) a_k (cm); radius: the RBFs' radius (cm).
        region_centres: (R, 3) m_r; region_scales: (R, 3) diagonals of D_r;
        region_radii: (R,) cm.
    """

    centre: Float64[np.ndarray, " 3"]
    scale: Float64[np.ndarray, " 3"]
    rbf_centres: Float64[np.ndarray, "K 3"]
    rbf_weights: Float64[np.ndarray, "K 3"]
    radius: float
    region_centres: Float64[np.ndarray, "R 3"]
    region_scales: Float64[np.ndarray, "R 3"]
    region_radii: Float64[np.ndarray, " R"]

    @classmethod
    def identity(cls, centre: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0)) -> "SmoothWarp":
        empty = np.zeros((0, 3))
        return cls(np.asarray(centre, np.float64), np.ones(3), empty, empty, 1.0, empty,
                   empty, np.zeros(0))  # fmt: skip

    def __call__(self, points: Float[ArrayLike, "... 3"]) -> Float64[np.ndarray, "... 3"]:
        """The warped points, same shape (float64)."""
        x = np.asarray(points, np.float64)
        out = self.centre + (x - self.centre) * self.scale
        if len(self.rbf_centres):
            d2 = np.sum((x[..., None, :] - self.rbf_centres) ** 2, axis=-1)  # (..., K)
            out = out + np.exp(-d2 / (2 * self.radius**2)) @ self.rbf_weights
        for m, s, r in zip(self.region_centres, self.region_scales, self.region_radii,
                           strict=True):  # fmt: skip
            h = np.exp(-np.sum((x - m) ** 2, axis=-1) / (2 * r**2))[..., None]
            out = out + (x - m) * (s - 1.0) * h
        return out


WARP_REGION_LOG_LIMIT = 0.4
"""``random_warp`` clips each region's log scale to +-this: with the Gaussian falloff the
warp's Jacobian stays positive definite (its worst eigenvalue is 1 - 1.74 (1 - e^-0.4) > 0.4)."""


def random_warp(
    rng: np.random.Generator,
    vertices: Float[ArrayLike, "V 3"],
    landmarks: Int[ArrayLike, " L"],
    *,
    amplitude: float = 1.0,
    proportions: float = 0.1,
    radius: float = 8.0,
    n_rbf: int = 8,
) -> SmoothWarp:
    """A random ``SmoothWarp`` of a head (centimetres; ``landmarks`` its 68 Multi-PIE
    vertices, for the regions of ``MULTIPIE_REGIONS``).

    Args:
        amplitude: standard deviation (cm) of each RBF weight component; 0 for none.
        proportions: standard deviation of the log scale of each axis of the whole head, and
            twice that of each region's (clipped to ``WARP_REGION_LOG_LIMIT``); 0 for none.
        radius: the RBFs' radius (cm; the default 8 cm is low frequency on a ~25 cm head).
        n_rbf: RBF centres, drawn among the head's vertices.

    The RBF part's Jacobian is at most about 0.61 sqrt(n_rbf) amplitude / radius in norm
    (0.22 at the defaults), so the warp does not fold a head at these values; ``warp_head``
    refuses one that turns any triangle over."""
    for name, value in (("amplitude", amplitude), ("proportions", proportions)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name}: expected a finite value >= 0, got {value}")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius: expected > 0 (cm), got {radius}")
    if n_rbf < 0:
        raise ValueError(f"n_rbf: expected >= 0, got {n_rbf}")
    x = np.asarray(vertices, np.float64)
    landmarks = np.asarray(landmarks)
    centre = 0.5 * (x.min(axis=0) + x.max(axis=0))
    scale = np.exp(rng.normal(0.0, proportions, 3)) if proportions else np.ones(3)
    picks = rng.choice(len(x), n_rbf, replace=len(x) < n_rbf) if n_rbf else []
    rbf_centres = x[picks].reshape(-1, 3)
    rbf_weights = rng.normal(0.0, 1.0, (n_rbf, 3)) * amplitude
    centres, scales, radii = [], [], []
    if proportions:
        for ids in MULTIPIE_REGIONS.values():
            points = x[landmarks[list(ids)]]
            m = points.mean(axis=0)
            centres.append(m)
            radii.append(max(float(np.linalg.norm(points - m, axis=1).max()), 1e-3))
            log_scale = np.clip(rng.normal(0.0, 2 * proportions, 3), -WARP_REGION_LOG_LIMIT,
                                WARP_REGION_LOG_LIMIT)  # fmt: skip
            scales.append(np.exp(log_scale))
    return SmoothWarp(
        centre, scale, rbf_centres, rbf_weights, float(radius),
        np.asarray(centres, np.float64).reshape(-1, 3), np.asarray(scales).reshape(-1, 3),
        np.asarray(radii, np.float64),
    )  # fmt: skip


def warp_head(head: RiggedHead, warp: SmoothWarp, *, name: str | None = None) -> RiggedHead:
    """``head`` deformed by ``warp``: the neutral warped and every pose's displacement carried
    as ``warp(neutral + d) - warp(neutral)`` (the posed shape warped by the same map), the
    topology, landmarks and parts kept. Refuses (``ValueError``) a warp that turns any of the
    head's non-degenerate triangles against its normal."""
    from ..mesh import flipped_triangles

    neutral = np.asarray(head.vertices, np.float64)
    warped = warp(neutral)
    if flipped_triangles(warped[None], neutral, head.faces).any():
        raise ValueError(f"warp: it folds {head.name} (a triangle turns over); use a smaller "
                         "amplitude or proportions")  # fmt: skip
    posed = warp(neutral[None] + np.asarray(head.displacements, np.float64))
    return dataclasses.replace(
        head,
        name=name or f"{head.name}/warp",
        vertices=warped.astype(np.float32),
        displacements=(posed - warped[None]).astype(np.float32),
    )


def warped_heads(
    heads: list[RiggedHead],
    copies: int,
    *,
    amplitude: float = 1.0,
    proportions: float = 0.1,
    radius: float = 8.0,
    seed: int = 0,
    attempts: int = 10,
) -> list[RiggedHead]:
    """``copies`` warped versions of each head (``random_warp`` then ``warp_head``), named
    ``<name>/warp<j>``. The warp of copy j of head i is drawn from
    ``numpy.random.default_rng([seed, i, j, attempt])``, attempt 0 first; a draw that would
    turn a triangle over (a strongly anisotropic region scaling can turn a sliver) is
    redrawn with the next attempt, up to ``attempts`` (then ``ValueError``). A head's warps
    do not depend on the others'; heads of one identity in several remeshings (the training
    set's) get different warps."""
    if copies < 0:
        raise ValueError(f"copies: expected >= 0, got {copies}")
    out = []
    for i, head in enumerate(heads):
        for j in range(copies):
            for attempt in range(attempts):
                rng = np.random.default_rng([seed, i, j, attempt])
                warp = random_warp(rng, head.vertices, head.landmarks, amplitude=amplitude,
                                   proportions=proportions, radius=radius)  # fmt: skip
                try:
                    out.append(warp_head(head, warp, name=f"{head.name}/warp{j}"))
                    break
                except ValueError:
                    if attempt == attempts - 1:
                        raise
    return out
