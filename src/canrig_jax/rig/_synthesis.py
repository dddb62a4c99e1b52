"""Corrective synthesis: combination shapes sculpted from a nonlinear blend of the targets.

Production rigs obtain a corrective by sculpting the pose at a corner of the weight
hypercube (several weights at 1) and storing its difference from what the rig already gives
there. Here the "sculpt" is the deformation-gradient blend of the real targets
(``canrig_jax.mesh.DeformationGradientBlend``). Combinations are visited by increasing order
(pairs, then triplets, then quadruplets) and each corrective is

    c_S = N(1_S) - f(1_S),

the nonlinear blend at the corner minus the rig built so far evaluated there. When every
sub-combination of S carries a corrective this is exactly inclusion-exclusion over the
corner's sub-corners, c_S = sum_{T subset S} (-1)^{|S|-|T|} N(1_T); when some sub-corrective
was dropped for being small, its remainder is absorbed, so the finished rig equals the
nonlinear blend at every selected corner (up to the support tolerance).
"""

import dataclasses
import itertools
import time
from collections.abc import Sequence

import jax
import numpy as np
from jaxtyping import ArrayLike, Float
from tqdm.auto import tqdm

from ..data import to_arkit
from ..mesh import DeformationGradientBlend
from ._blendshape import UNIT_IN_CM, BlendshapeRig, Corrective, evaluate

MUTUALLY_EXCLUSIVE = (
    ("jawLeft", "jawRight"),
    ("mouthLeft", "mouthRight"),
    ("eyeLookUp_L", "eyeLookDown_L"),
    ("eyeLookUp_R", "eyeLookDown_R"),
    ("eyeLookIn_L", "eyeLookOut_L"),
    ("eyeLookIn_R", "eyeLookOut_R"),
)
"""ARKit blendshapes that are physically exclusive: the two directions of one motion of a
rigid part or of one single-axis displacement, which cannot happen at the same time. No
corrective is synthesised for them, random training poses never hold both, and
``inverse.Constrained`` keeps them from being both non-zero. Matched by canonical ARKit name
(``exclusive_pairs``), so they apply to a rig in any spelling (ICT ``eyeLookUp_L``, ARKit
``eyeLookUpLeft``, Unreal ``EyeLookUpLeft``).

- ``jawLeft`` / ``jawRight``: the mandible is one rigid bone; its lateral shift has one sign.
- ``mouthLeft`` / ``mouthRight``: the lateral shift of the closed lips as a whole, one
  direction at a time.
- ``eyeLookIn`` / ``eyeLookOut`` and ``eyeLookUp`` / ``eyeLookDown`` of each eye: the eyeball
  is rigid; its horizontal and vertical rotations each have one sign. (In and Out of the two
  eyes are *not* exclusive: looking sideways is one eye In and the other Out, converging is
  both In.)

Left out on purpose (they co-occur in real expressions, or are not one motion):
``mouthPucker`` / ``mouthFunnel`` (a rounded pout uses both); ``mouthSmile`` /
``mouthFrown`` (different muscles pull the corner up and down; grimaces and suppressed smiles
use both); ``eyeBlink`` / ``eyeWide`` (upper-lid height, but the shapes also move the brow and
the skin around the eye, and a squinting blink uses both); ``browDown`` / ``browInnerUp`` /
``browOuterUp`` (the worried brow combines them); ``cheekPuff`` / ``mouthPucker`` and
``jawOpen`` / ``mouthClose`` (``mouthClose`` is defined relative to an open jaw)."""


def _canonical(name: str) -> str:
    try:
        return to_arkit(name)
    except ValueError:  # not an ARKit channel (a viseme, a custom shape): its own name
        return name


def exclusive_pairs(
    names: Sequence[str], exclude: Sequence[tuple[str, str]] = MUTUALLY_EXCLUSIVE
) -> list[tuple[int, int]]:
    """Index pairs (i, j), i < j, of ``names`` that ``exclude`` forbids, matched by canonical
    ARKit name; a name split in halves (ICT's ``browInnerUp_L``/``_R``) matches each half.
    Pairs the rig lacks a member of are left out.

    Raises a ValueError naming ``names`` (not a sequence of names) or ``exclude`` (not pairs
    of two names; a name that is neither one of ``names`` nor an ARKit blendshape, e.g. a
    typo; a pair of one shape with itself)."""
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"names: expected a sequence of blendshape names, got {names!r}")
    by_name: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        by_name.setdefault(_canonical(name), []).append(i)
    pairs = set()
    for pair in exclude:
        if isinstance(pair, str) or len(pair) != 2 or not all(isinstance(n, str) for n in pair):
            raise ValueError(f"exclude: expected pairs of two names, got {pair!r}")
        for name in pair:
            if name not in names and _canonical(name) not in by_name and not _is_arkit(name):
                raise ValueError(
                    f"exclude: unknown blendshape name {name!r} (neither one of the rig's "
                    "names nor an ARKit blendshape)"
                )
        a, b = pair
        for i in by_name.get(_canonical(a), []):
            for j in by_name.get(_canonical(b), []):
                if i == j:
                    raise ValueError(f"exclude: {pair!r} pairs {names[i]!r} with itself")
                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def _is_arkit(name: str) -> bool:
    try:
        to_arkit(name)
    except ValueError:
        return False
    return True


@dataclasses.dataclass(frozen=True)
class SynthesisOptions:
    """Thresholds of ``synthesize_correctives``; lengths in centimetres, converted to the rig's
    unit (``BlendshapeRig.units``) by ``synthesize_correctives``, so a head in decimetres gets
    the same physical thresholds as ICT.

    Attributes:
        max_order: highest corrective order (2, 3 or 4).
        support_tol: a vertex is in a blendshape's support when it moves more than this.
        min_overlap: two blendshapes overlap when they share at least this many support vertices.
        min_magnitude: (pairs, triplets, quads) keep a corrective whose largest per-vertex
            offset exceeds this.
        combine_min_magnitude: triplets and quadruplets are built only from pairs whose
            corrective exceeds this (strong interactions), as production rigs add higher-order
            shapes only where pairs interact strongly.
        store_tol: offsets below this are not stored (the support-restricted layout).
        exclude: name pairs never combined (default: opposite directions of one control).
    """

    max_order: int = 4
    support_tol: float = 0.01
    min_overlap: int = 20
    min_magnitude: tuple[float, float, float] = (0.05, 0.05, 0.05)
    combine_min_magnitude: float = 0.2
    store_tol: float = 1e-5
    exclude: tuple[tuple[str, str], ...] = MUTUALLY_EXCLUSIVE

    def __post_init__(self):
        if self.max_order not in (1, 2, 3, 4):
            raise ValueError(f"max_order: expected 1, 2, 3 or 4, got {self.max_order}")
        if len(self.min_magnitude) != 3 or not all(
            np.isfinite(m) and m >= 0 for m in self.min_magnitude
        ):
            raise ValueError(
                f"min_magnitude: expected three finite non-negative thresholds (pairs, "
                f"triplets, quads), got {self.min_magnitude}"
            )
        checks = {
            "support_tol": self.support_tol > 0,
            "store_tol": self.store_tol >= 0,
            "combine_min_magnitude": self.combine_min_magnitude >= 0,
            "min_overlap": self.min_overlap >= 1,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not (ok and np.isfinite(value)):
                raise ValueError(f"{name}: invalid value {value} (finite, in range expected)")


def _in_rig_units(options: SynthesisOptions, units: str) -> SynthesisOptions:
    """``options`` with its centimetre lengths converted to ``units`` (unchanged for cm)."""
    if units == "cm":
        return options
    scale = 1.0 / UNIT_IN_CM[units]
    return dataclasses.replace(
        options,
        support_tol=options.support_tol * scale,
        min_magnitude=tuple(m * scale for m in options.min_magnitude),
        combine_min_magnitude=options.combine_min_magnitude * scale,
        store_tol=options.store_tol * scale,
    )


@dataclasses.dataclass(frozen=True)
class SynthesisReport:
    """What ``synthesize_correctives`` did.

    ``candidates[n]`` / ``kept[n]`` count combinations of order n examined / kept;
    ``corner_max_error`` is the largest per-vertex distance (rig units) between the finished
    rig and the nonlinear blend over all selected corners (singles included).
    """

    candidates: dict[int, int]
    kept: dict[int, int]
    max_magnitude: dict[int, float]
    corner_max_error: float
    fallback_triangles: int
    seconds: float


def overlapping_pairs(
    deltas: Float[ArrayLike, "K V 3"], names: Sequence[str], options: SynthesisOptions
) -> list[tuple[int, int]]:
    """Pairs of blendshapes whose supports share ``min_overlap`` vertices, minus exclusions."""
    deltas = np.asarray(deltas)
    support = (np.linalg.norm(deltas, axis=2) > options.support_tol).astype(np.int32)
    shared = support @ support.T
    excluded = {frozenset(pair) for pair in exclusive_pairs(names, options.exclude)}
    k = deltas.shape[0]
    return [
        (i, j)
        for i in range(k)
        for j in range(i + 1, k)
        if shared[i, j] >= options.min_overlap and frozenset((i, j)) not in excluded
    ]


def _cliques(pairs: Sequence[tuple[int, ...]], order: int) -> list[tuple[int, ...]]:
    """Sorted index tuples of size ``order`` all of whose pairs are in ``pairs``."""
    neighbours: dict[int, set[int]] = {}
    for i, j in pairs:
        neighbours.setdefault(i, set()).add(j)
        neighbours.setdefault(j, set()).add(i)
    found = set()
    for i, j in pairs:
        common = neighbours[i] & neighbours[j]
        for rest in itertools.combinations(sorted(common), order - 2):
            combo = tuple(sorted((i, j, *rest)))
            if all(b in neighbours[a] for a, b in itertools.combinations(combo, 2)):
                found.add(combo)
    return sorted(found)


def _corner_weights(combos: Sequence[tuple[int, ...]], k: int) -> np.ndarray:
    weights = np.zeros((len(combos), k), np.float32)
    for row, combo in enumerate(combos):
        weights[row, list(combo)] = 1.0
    return weights


def synthesize_correctives(
    rig: BlendshapeRig,
    options: SynthesisOptions | None = None,
    *,
    blend: DeformationGradientBlend | None = None,
    batch_size: int = 64,
    progress: bool = True,
) -> tuple[BlendshapeRig, SynthesisReport]:
    """Add corrective terms of order 2..``max_order`` to a linear rig from the nonlinear blend.

    Candidates: pairs whose supports overlap; triplets and quadruplets whose every pair has
    a corrective above ``combine_min_magnitude``. A corrective is kept when its largest
    per-vertex offset exceeds the order's ``min_magnitude``.

    Args:
        rig: rig with faces; its correctives, if any, are ignored.
        options: thresholds (``SynthesisOptions()`` by default).
        blend: a prebuilt blend of this rig's mesh (built here otherwise).

    Returns:
        The rig with correctives, and a ``SynthesisReport``.
    """
    options = options or SynthesisOptions()
    if rig.faces is None:
        raise ValueError("rig: corrective synthesis needs a rig with faces")
    options = _in_rig_units(options, rig.units)
    start = time.perf_counter()
    neutral = np.asarray(rig.neutral, np.float64)
    deltas = np.asarray(rig.deltas, np.float64)
    k = deltas.shape[0]
    if blend is None:
        blend = DeformationGradientBlend(neutral, deltas, np.asarray(rig.faces))
    current = rig.linear()
    evaluate_batch = jax.jit(jax.vmap(evaluate, (None, 0)))
    candidates, kept, largest = {}, {}, {}
    corner_error = float(
        np.linalg.norm(blend(np.eye(k)) - (neutral + deltas), axis=2).max(initial=0.0)
    )
    strong_pairs: list[tuple[int, ...]] = []
    for order in range(2, options.max_order + 1):
        combos = (
            overlapping_pairs(deltas, rig.names, options)
            if order == 2
            else _cliques(strong_pairs, order)
        )
        candidates[order] = len(combos)
        keep_indices, keep_deltas = [], []
        for s in tqdm(
            range(0, len(combos), batch_size),
            desc=f"order-{order} correctives",
            disable=not progress,
        ):
            chunk = combos[s : s + batch_size]
            corners = _corner_weights(chunk, k)
            target = blend(corners)
            corrective = target - np.asarray(evaluate_batch(current, corners), np.float64)
            magnitude = np.linalg.norm(corrective, axis=2).max(axis=1)
            for combo, offset, size in zip(chunk, corrective, magnitude, strict=True):
                if size > options.min_magnitude[order - 2]:
                    keep_indices.append(combo)
                    keep_deltas.append(offset.astype(np.float32))
        kept[order] = len(keep_indices)
        largest[order] = float(
            max((np.linalg.norm(d, axis=1).max() for d in keep_deltas), default=0.0)
        )
        if order == 2:
            strong_pairs = [
                combo
                for combo, offset in zip(keep_indices, keep_deltas, strict=True)
                if np.linalg.norm(offset, axis=1).max() > options.combine_min_magnitude
            ]
        if keep_indices:
            table = Corrective.from_dense(
                np.array(keep_indices), np.stack(keep_deltas), support_tol=options.store_tol
            )
            current = BlendshapeRig(
                current.neutral,
                current.deltas,
                (*current.correctives, table),
                rig.names,
                rig.faces,
                rig.units,
            )
            corners = _corner_weights(keep_indices, k)
            for s in range(0, len(corners), batch_size):
                error = blend(corners[s : s + batch_size]) - np.asarray(
                    evaluate_batch(current, corners[s : s + batch_size]), np.float64
                )
                corner_error = max(corner_error, float(np.linalg.norm(error, axis=2).max()))
    report = SynthesisReport(
        candidates=candidates,
        kept=kept,
        max_magnitude=largest,
        corner_max_error=corner_error,
        fallback_triangles=blend.fallback_counts.total,
        seconds=time.perf_counter() - start,
    )
    return current, report
