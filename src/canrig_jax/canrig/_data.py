"""Training and test data for CANRig from a blendshape rig with correctives.

Shapes are the rig evaluated at poses (the ict-quartic rig: its correctives give the model
real nonlinear correlations to learn): the first half of the Live Link capture and random
sparse poses for training; the second half of the capture and a disjoint set of random poses
for testing. Each training shape also has a *nearby* pose (the previous capture frame, or the
random pose's active weights jittered), the paper's "previous frame" base shape.

A training example (``sample_examples``) draws a target shape, a base shape (another random
pose, a nearby pose or the neutral), 20-200 random handles from a pool of vertices whose
geodesic distances are precomputed, one radius and falloff, and a random subset of vertices
on which the loss is evaluated (each vertex's output depends only on its own query and the
handles, so the loss over a subset is an unbiased estimate of the loss over all vertices).
"""

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float32, Int

from ..mesh import edge_graph, farthest_point_vertices, weighted_geodesic_distance
from ..rig import BlendshapeRig, evaluate_batch, random_sparse_poses

RADII_CM = {"small": 1.0, "medium": 2.0, "large": 4.0}
"""Named radii of the evaluation (geodesic cm on the ICT face, about 18 cm wide): the one
home of these numbers; experiments, benchmarks and ``ExampleOptions.eval_radii_cm`` read them."""

EVAL_FALLOFF_PER_CM = 3.0
"""Falloff of the evaluation's masks (per cm)."""


def nearby_poses(
    poses: Float[ArrayLike, "N K"],
    rng: np.random.Generator,
    *,
    sequence: bool,
    jitter: float = 0.1,
) -> Float32[np.ndarray, "N K"]:
    """A pose near each pose: the previous frame of a sequence (the next one for frame 0),
    or the active weights jittered by N(0, jitter) and clipped to [0, 1]."""
    poses = np.asarray(poses, np.float32)
    if sequence:
        if len(poses) < 2:
            raise ValueError("poses: a sequence needs at least 2 frames")
        return np.concatenate([poses[1:2], poses[:-1]])
    noise = rng.normal(0.0, jitter, poses.shape).astype(np.float32)
    return np.clip(poses + noise * (poses > 0), 0.0, 1.0)


def evaluate_poses(
    rig: BlendshapeRig, poses: Float[ArrayLike, "N K"], chunk: int = 64
) -> Float32[np.ndarray, "N V 3"]:
    """(N, V, 3) float32 NumPy meshes of ``poses`` (N, K): ``rig.evaluate_batch`` in chunks."""
    return np.asarray(evaluate_batch(rig, poses, chunk=chunk), np.float32)


class TrainingSet(eqx.Module):
    """Device arrays a jitted training step gathers from (``build_training_set`` lists the
    fields)."""

    neutral: Float[Array, "V 3"]
    shapes: Float[Array, "N V 3"]
    nearby: Float[Array, "N V 3"]
    pool: Int[Array, " P"]
    pool_distance: Float[Array, "V P"]
    handle_sets: Int[Array, "S n"] | None = None
    n_capture: int = eqx.field(static=True, default=0)


def build_training_set(
    rig: BlendshapeRig,
    capture_train: Float[np.ndarray, "F K"],
    *,
    n_random: int = 800,
    n_pool: int = 2048,
    distance_limit_cm: float = 10.0,
    edge_factor: Float[ArrayLike, " E"] | None = None,
    seed: int = 0,
    n_active: tuple[int, int] = (4, 10),
    farthest_sets: int = 0,
    farthest_size: int = 200,
    farthest_geodesic: bool = False,
    capture_mixes: int = 0,
) -> TrainingSet:
    """Evaluate the rig at the capture's training frames and ``n_random`` random sparse poses
    (seed ``seed``, ``n_active`` active weights each), their nearby poses, and the distances
    from ``n_pool`` handle candidates (edge lengths times ``edge_factor`` if given, e.g.
    ``correlation_edge_factor``). With ``farthest_sets`` > 0, that many farthest-point
    orders of ``farthest_size`` vertices (from random start vertices other than 0, the start
    of the evaluation's handles; geodesic distances with ``farthest_geodesic``) are added to
    the pool and kept as ``handle_sets``. With ``capture_mixes`` > 0, that many more poses are
    appended, each a convex combination of two random training capture frames
    (``capture_mixes_of``; drawn after everything else, so the other shapes are unchanged).

    Returns:
        The device arrays ``train`` gathers from (a ``TrainingSet``): ``neutral`` (V, 3), the
        canonical shape S_0; ``shapes`` (N, V, 3), the training targets, the first
        ``n_capture`` of them capture frames, the rest random poses; ``nearby`` (N, V, 3), a
        nearby pose of each; ``pool`` (P,), the handle candidates, and ``pool_distance``
        (V, P), the weighted geodesic distance of each vertex to each (inf beyond the limit);
        ``handle_sets`` (S, n), the farthest-point handle sets as indices into ``pool`` (each
        a farthest-point order, so any prefix is itself a farthest-point set), or None.
    """
    if capture_mixes < 0:
        raise ValueError(f"capture_mixes: expected >= 0, got {capture_mixes}")
    rng = np.random.default_rng(seed)
    random_poses = random_sparse_poses(
        rng, n_random, rig.names, n_active=(int(n_active[0]), int(n_active[1]))
    )
    poses = np.concatenate([capture_train, random_poses]).astype(np.float32)
    near = np.concatenate(
        [
            nearby_poses(capture_train, rng, sequence=True),
            nearby_poses(random_poses, rng, sequence=False),
        ]
    )
    neutral = np.asarray(rig.neutral, np.float32)
    graph = edge_graph(neutral, np.asarray(rig.faces), edge_factor)
    pool = np.sort(rng.choice(rig.n_vertices, size=min(n_pool, rig.n_vertices), replace=False))
    handle_sets = None
    if farthest_sets > 0:
        starts = rng.choice(np.arange(1, rig.n_vertices), size=farthest_sets, replace=False)
        fps_graph = graph if farthest_geodesic else None
        orders = np.stack(
            [farthest_point_vertices(neutral, farthest_size, s, graph=fps_graph) for s in starts]
        )
        pool = np.union1d(pool, orders.ravel())
        handle_sets = jnp.asarray(np.searchsorted(pool, orders).astype(np.int32))
    if capture_mixes > 0:
        mixes = capture_mixes_of(capture_train, capture_mixes, rng)
        poses = np.concatenate([poses, mixes])
        near = np.concatenate([near, nearby_poses(mixes, rng, sequence=False)])
    distance = weighted_geodesic_distance(graph, pool, limit=distance_limit_cm)
    return TrainingSet(
        neutral=jnp.asarray(neutral),
        shapes=jnp.asarray(evaluate_poses(rig, poses)),
        nearby=jnp.asarray(evaluate_poses(rig, near)),
        pool=jnp.asarray(pool.astype(np.int32)),
        pool_distance=jnp.asarray(np.ascontiguousarray(distance.T)),
        handle_sets=handle_sets,
        n_capture=len(capture_train),
    )


FARTHEST_METRICS = ("euclidean", "geodesic")


@dataclasses.dataclass(frozen=True)
class DataOptions:
    """How the training set is built (``build_training_set``'s options, one record): stored in
    a training checkpoint so that a resume notices when they changed.

    ``farthest_metric`` is the distance of the farthest-point handle sets ("euclidean" or
    "geodesic", the metric of the masks). ``quick()`` gives the tiny set of ``--quick`` runs.
    """

    n_random: int = 800
    n_pool: int = 2048
    distance_limit_cm: float = 10.0
    n_active: tuple[int, int] = (4, 10)
    farthest_sets: int = 0
    farthest_size: int = 200
    farthest_metric: str = "euclidean"
    capture_mixes: int = 0

    def __post_init__(self):
        if self.farthest_metric not in FARTHEST_METRICS:
            raise ValueError(
                f"farthest_metric: expected one of {FARTHEST_METRICS}, got {self.farthest_metric!r}"
            )
        for name in ("n_random", "farthest_sets", "capture_mixes"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if self.n_pool < 1 or self.farthest_size < 1:
            raise ValueError(
                f"n_pool, farthest_size: expected >= 1, got {self.n_pool}, {self.farthest_size}"
            )
        if not self.distance_limit_cm > 0:
            raise ValueError(f"distance_limit_cm: expected > 0, got {self.distance_limit_cm}")
        if len(self.n_active) != 2 or not 1 <= self.n_active[0] <= self.n_active[1]:
            raise ValueError(
                f"n_active: expected (low, high) with 1 <= low <= high, got {self.n_active}"
            )

    def quick(self) -> "DataOptions":
        """The same options with the tiny sizes of a ``--quick`` run."""
        return dataclasses.replace(self, n_random=50, n_pool=256)

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "n_active": list(self.n_active)}

    def build(
        self,
        rig: BlendshapeRig,
        capture_train: Float[np.ndarray, "F K"],
        *,
        seed: int = 0,
        edge_factor: Float[ArrayLike, " E"] | None = None,
    ) -> TrainingSet:
        """``build_training_set`` with these options."""
        return build_training_set(
            rig,
            capture_train,
            n_random=self.n_random,
            n_pool=self.n_pool,
            distance_limit_cm=self.distance_limit_cm,
            edge_factor=edge_factor,
            seed=seed,
            n_active=self.n_active,
            farthest_sets=self.farthest_sets,
            farthest_size=self.farthest_size,
            farthest_geodesic=self.farthest_metric == "geodesic",
            capture_mixes=self.capture_mixes,
        )


def capture_mixes_of(
    capture: Float[ArrayLike, "F K"], n: int, rng: np.random.Generator
) -> Float32[np.ndarray, "n K"]:
    """``n`` poses (1 - t) w_a + t w_b from random pairs a != b of capture frames, t ~ U(0, 1):
    new dense, capture-like expressions (mixup of the training frames; no test frame used)."""
    capture = np.asarray(capture, np.float32)
    if capture.ndim != 2 or len(capture) < 2:
        raise ValueError(f"capture: expected (F, K) with F >= 2 frames, got {capture.shape}")
    a = rng.integers(0, len(capture), n)
    b = (a + rng.integers(1, len(capture), n)) % len(capture)
    t = rng.uniform(size=(n, 1)).astype(np.float32)
    return (1.0 - t) * capture[a] + t * capture[b]


@dataclasses.dataclass(frozen=True)
class ExampleOptions:
    """How training examples are drawn (section 5 of the paper)."""

    batch: int = 8
    n_vertices: int = 384
    n_handles: tuple[int, int] = (20, 200)
    handle_bucket: int = 50  # pad handle arrays to a multiple of this (few compiled shapes)
    radius_cm: tuple[float, float] = (0.7, 6.0)  # log-uniform
    falloff_per_cm: tuple[float, float] = (1.5, 6.0)  # uniform
    p_nearby: float = 0.1
    p_neutral: float = 0.1
    # matching the evaluation (all 0 / None: the draws above only)
    p_farthest: float = 0.0  # handles: a prefix of a farthest-point set (``handle_sets``)
    p_eval_radius: float = 0.0  # radius one of ``eval_radii_cm``, falloff ``eval_falloff``
    eval_radii_cm: tuple[float, ...] = tuple(RADII_CM.values())
    eval_falloff_per_cm: float = EVAL_FALLOFF_PER_CM
    p_capture: float | None = None  # target a capture frame with this probability


class Examples(eqx.Module):
    """Index arrays of one batch (numpy, drawn on the host; the step gathers on device)."""

    target: Int[np.ndarray | Array, " B"]
    base: Int[np.ndarray | Array, " B"]  # index into shapes, or -1 for the neutral
    base_nearby: Int[np.ndarray | Array, " B"]  # 1: the target's nearby pose
    handles: Int[np.ndarray | Array, "B H"]  # indices into the pool
    handle_valid: Float[np.ndarray | Array, "B H"]  # 1 for real handles, 0 for padding
    vertices: Int[np.ndarray | Array, "B Nv"]
    radius: Float[np.ndarray | Array, " B"]
    falloff: Float[np.ndarray | Array, " B"]


def sample_examples(
    rng: np.random.Generator,
    n_shapes: int,
    n_pool: int,
    n_vertices: int,
    options: ExampleOptions,
    *,
    handle_sets: Int[np.ndarray | Array, "S n"] | None = None,
    n_capture: int = 0,
) -> Examples:
    """One batch of example indices; handle arrays are padded to the batch's largest handle
    count rounded up to ``handle_bucket`` (padding has ``handle_valid`` 0 and no influence).

    The options matching the evaluation (``p_farthest``, ``p_eval_radius``, ``p_capture``)
    draw after all the default draws, so with them off the batches are unchanged.
    ``handle_sets`` (S, n) are pool indices in farthest-point order; the first ``n_capture``
    shapes are capture frames."""
    b, (lo, hi) = options.batch, options.n_handles
    if not 1 <= lo <= hi <= n_pool:
        raise ValueError(
            f"n_handles: expected 1 <= low <= high <= {n_pool}, got {options.n_handles}"
        )
    target = rng.integers(0, n_shapes, b)
    shift = rng.integers(1, max(n_shapes, 2), b)
    base = (target + shift) % max(n_shapes, 1)
    kind = rng.uniform(size=b)
    nearby = kind < options.p_nearby
    neutral = (kind >= options.p_nearby) & (kind < options.p_nearby + options.p_neutral)
    base = np.where(neutral, -1, base)
    counts = rng.integers(lo, hi + 1, b)
    bucket = max(1, options.handle_bucket)
    width = min(hi, int(-(-counts.max() // bucket) * bucket))
    handles = np.zeros((b, width), np.int32)
    valid = np.zeros((b, width), np.float32)
    for row, count in enumerate(counts):
        handles[row, :count] = rng.choice(n_pool, size=count, replace=False)
        valid[row, :count] = 1.0
    vertices = np.stack(
        [rng.choice(n_vertices, size=options.n_vertices, replace=False) for _ in range(b)]
    )
    log_low, log_high = np.log(options.radius_cm)
    log_r = rng.uniform(log_low, log_high, b)
    radius = np.exp(log_r).astype(np.float32)
    falloff = rng.uniform(*options.falloff_per_cm, b).astype(np.float32)
    if options.p_farthest > 0:
        if handle_sets is None or len(handle_sets) == 0:
            raise ValueError("p_farthest: needs farthest-point handle_sets in the training set")
        handle_sets = np.asarray(handle_sets)
        use = rng.uniform(size=b) < options.p_farthest
        which = rng.integers(0, len(handle_sets), b)
        for row in np.flatnonzero(use):
            count = min(int(counts[row]), handle_sets.shape[1])
            handles[row] = 0
            handles[row, :count] = handle_sets[which[row], :count]
            valid[row] = 0.0
            valid[row, :count] = 1.0
    if options.p_eval_radius > 0:
        use = rng.uniform(size=b) < options.p_eval_radius
        chosen = rng.choice(np.asarray(options.eval_radii_cm, np.float32), b)
        radius = np.where(use, chosen, radius).astype(np.float32)
        falloff = np.where(use, options.eval_falloff_per_cm, falloff).astype(np.float32)
    if options.p_capture is not None and 0 < n_capture < n_shapes:
        from_capture = rng.uniform(size=b) < options.p_capture
        capture_target = rng.integers(0, n_capture, b)
        random_target = rng.integers(n_capture, n_shapes, b)
        target = np.where(from_capture, capture_target, random_target)
        base = np.where(base < 0, -1, (target + shift) % n_shapes)
    return Examples(
        target=target.astype(np.int32),
        base=base.astype(np.int32),
        base_nearby=nearby.astype(np.int32),
        handles=handles,
        handle_valid=valid,
        vertices=vertices.astype(np.int32),
        radius=radius,
        falloff=falloff,
    )
