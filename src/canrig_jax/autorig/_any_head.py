"""Any head to an ARKit rig, one call: ``auto_rig(vertices, faces, method=...)``.

The method is an ``AbstractAutoRigMethod`` (``Transfer()``, the default;
``RigAnyFaceNetwork()``; ``TransferResidual()``; see ``_methods``): it gives the displacement
of every pose on the head turned into the convention; the steps around it are every method's
(orientation decided or refused, ICT landmarks placed on the head when the method needs them,
clumps of vertices a fraction of a millimetre apart welded to move as one (``_weld``), the rig
built in the convention and turned back, the artist's style applied, the blinks
closed, ARKit names).

Few-shot style: given ``examples`` (k of the head's own sculpted ARKit shapes), a ``Style``
(a gain, a falloff exponent and a relative floor: amplitude and locality) is fitted so the
generated versions of those k shapes match the artist's, applied to every pose, and the k
shapes themselves are taken as sculpted.
"""

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from .._warnings import warn
from ..data import arkit_name_of
from ..mesh import check_mesh
from ..rig import UNIT_IN_CM, BlendshapeRig
from . import _weld
from ._assemble import assemble
from ._blink_fit import close_blinks
from ._data import AutorigDataset
from ._landmarks import place_landmarks, skin_of
from ._methods import AUTO_RIG_METHODS, DEFAULT_METHOD, AbstractAutoRigMethod, UprightHead
from ._orientation import OrientationDecision, decide_orientation, stated_orientation
from ._rig_checks import RigCheck, check_rig
from ._style import Style, style_from_examples

NAME_STYLES = ("arkit", "source")


@dataclasses.dataclass(frozen=True)
class AutoRig:
    """What ``auto_rig`` returns.

    Attributes:
        rig: the ``BlendshapeRig`` in the head's own frame, centimetres; ARKit names unless
            ``names="source"``.
        method: the name of the method run (``AbstractAutoRigMethod.name``: "transfer",
            "raf", "transfer-residual"); style: the ``Style`` applied (``Style()`` without
            examples).
        orientation: how the head was turned for the method (``OrientationDecision``).
        landmarks: (68,) the ICT landmarks on the head (None for a method that does not
            ``needs_landmarks``, unless given);
            fit: how they were placed ("face", "inner face", "given") and the trimmed RMS (cm).
        examples: the ARKit names of the example shapes taken as sculpted (an example the
            rig has no single shape for only shapes the style, with a warning).
        seconds: wall time per step.
    """

    rig: BlendshapeRig
    method: str
    style: Style
    orientation: OrientationDecision
    landmarks: Int[np.ndarray, " L"] | None
    fit: dict
    examples: tuple[str, ...]
    seconds: dict


def _progress(progress, message):
    if progress is not None:
        progress(message)


def _check_examples(examples, n_vertices: int) -> dict[str, np.ndarray]:
    """{ARKit name: (V, 3) cm}; ValueError naming ``examples`` for unknown names, another
    topology or non-finite shapes."""
    if examples is None:
        return {}
    if isinstance(examples, BlendshapeRig):
        scale = UNIT_IN_CM[examples.units]
        pairs = zip(examples.names, np.asarray(examples.deltas), strict=True)  # no jax slicing
        items = [(n, np.asarray(d) * scale) for n, d in pairs]
    elif isinstance(examples, Mapping):
        items = list(examples.items())
    else:
        raise TypeError(
            f"examples: expected a BlendshapeRig or a {{name: (V, 3) delta}} mapping, got "
            f"{type(examples).__name__}"
        )
    out = {}
    from ..data import ARKIT_NAMES

    for name, delta in items:
        arkit = arkit_name_of(str(name))
        if arkit not in ARKIT_NAMES:
            raise ValueError(
                f"examples: {name!r} is not an ARKit shape name (e.g. jawOpen, eyeBlinkLeft)"
            )
        delta = np.asarray(delta, np.float64)
        if delta.shape != (n_vertices, 3):
            raise ValueError(
                f"examples: {name!r} has shape {delta.shape}; expected the head's topology "
                f"({n_vertices}, 3) — examples must be sculpted on this head's mesh"
            )
        if not np.all(np.isfinite(delta)):
            raise ValueError(f"examples: {name!r} has non-finite displacements")
        out[arkit] = delta
    return out


def auto_rig(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    method: AbstractAutoRigMethod | None = None,
    dataset: AutorigDataset | None = None,
    examples: BlendshapeRig | Mapping[str, Float[ArrayLike, "V 3"]] | None = None,
    up: str | None = None,
    forward: str | None = None,
    orientation: OrientationDecision | None = None,
    landmarks: Int[ArrayLike, " L"] | Sequence[int] | None = None,
    names: str = "arkit",
    progress: Callable[[str], None] | None = None,
) -> AutoRig:
    """The blendshape rig of any neutral head.

    Args:
        vertices: (V, 3) neutral head in **centimetres**, any axis-aligned orientation;
            faces: (F, 3) triangles.
        method: an ``AbstractAutoRigMethod`` (default: ``DEFAULT_METHOD``, ``Transfer()``):
            ``Transfer(template=...)`` carries a ``Template`` of the user's;
            ``RigAnyFaceNetwork(model=...)`` and ``TransferResidual(model=...)`` run a
            network other than the packaged one.
        dataset: the ICT source (``ict_pose_source()``; loaded from the data folder when
            None and the method ``needs_landmarks`` or ``landmarks`` are given; the network
            alone, ``RigAnyFaceNetwork``, runs without the data folder).
        examples: k of this head's ARKit shapes as sculpted by its artist (a
            ``BlendshapeRig`` on the head's mesh or {name: (V, 3) cm}); fits a ``Style``.
        up, forward: the head's up and forward axes ("+z", "-y"); default: decided from the
            fitted face, or refused (``OrientationError``) — never guessed.
        orientation: an ``OrientationDecision`` already made (skips the decision).
        landmarks: (68,) the ICT Multi-PIE landmarks on the head, by hand (skips their fit).
        names: "arkit" (default; ICT's halves merged, ``rename_to_arkit``) or "source" (the
            template's own names, e.g. ICT's ``browDown_L``).
        progress: called with a message before each step.

    Returns an ``AutoRig``. Raises ValueError naming the argument for bad input (TypeError
    for a ``method`` that is not an ``AbstractAutoRigMethod``), before any compiled work.
    """
    start = time.perf_counter()
    method = _check_method(method, names)
    v, faces = _check_head(vertices, faces)
    sculpted = _check_examples(examples, v.shape[0])
    orientation, landmarks = _check_placement(orientation, up, forward, landmarks, len(v))
    if dataset is None and (method.needs_landmarks or landmarks is not None):
        from ._data import ict_pose_source

        _progress(progress, "loading the ICT source rig")
        dataset = ict_pose_source(progress=False)
    seconds = {}
    if orientation is None:
        _progress(progress, "deciding the head's orientation from its face")
        t = time.perf_counter()
        orientation = decide_orientation(dataset, v, faces)  # None: the packaged template
        seconds["orientation"] = time.perf_counter() - t
    rotation = orientation.rotation
    upright = v @ rotation.T
    skin = skin_of(upright, faces)
    t = time.perf_counter()
    landmarks, fit_record = _landmarks(dataset, upright, faces, skin, landmarks, method, progress)
    seconds["landmarks"] = time.perf_counter() - t

    t = time.perf_counter()
    _progress(progress, f"building the rig ({method.name})")
    head = UprightHead(upright, np.asarray(faces), landmarks, skin)
    displacements, pose_set, source_names = method.displacements(head, dataset)
    displacements = _weld.weld(displacements, _weld.clumps(upright, faces, skin, _weld.WELD_TAU))
    seconds["method"] = time.perf_counter() - t

    style, styled = Style(), None
    if sculpted:
        style, styled = style_from_examples(displacements, source_names, sculpted, rotation, skin)
        _progress(
            progress,
            f"fitted the style of {len(sculpted)} example shapes: gain {style.gain:g}, "
            f"falloff {style.falloff:g}, floor {style.floor:g}",
        )
        styled = styled @ rotation
    rig, taken = assemble(
        v, faces, displacements @ rotation, styled, pose_set, source_names, names, sculpted
    )
    rig, fit_record["blink_gain"] = close_blinks(
        rig, up=orientation.up, forward=orientation.forward, keep=taken
    )
    seconds["total"] = time.perf_counter() - start
    return AutoRig(rig, method.name, style, orientation, landmarks, fit_record, taken, seconds)


def auto_rig_heads(
    heads: Sequence[tuple[Float[ArrayLike, "V 3"], Int[ArrayLike, "F 3"]]],
    *,
    across_processes: bool = False,
    **options,
) -> list[AutoRig]:
    """``auto_rig(vertices, faces, **options)`` of every ``(vertices, faces)`` pair in
    ``heads`` (centimetres), in order. Every head is checked first (ValueError naming
    ``heads[i]``); the ICT source and the method's network are loaded once for all
    (``AbstractAutoRigMethod.loaded``). ``options`` apply to every head (state
    ``up``/``forward`` only when all heads share their axes).

    ``across_processes``: after ``canrig_jax.distributed.initialize``, each process rigs its
    share of the heads and every process returns the whole list (``distributed.map_items``);
    each head's rig is the one a single process makes."""
    from ..distributed import map_items

    heads = list(heads)
    if not heads:
        raise ValueError("heads: expected at least one (vertices, faces) pair")
    for i, head in enumerate(heads):
        if not isinstance(head, tuple | list) or len(head) != 2:
            raise ValueError(f"heads[{i}]: expected a (vertices, faces) pair")
        try:
            _check_head(*head)
        except ValueError as error:
            raise ValueError(f"heads[{i}]: {error}") from error
    method = _check_method(options.get("method"), options.get("names", "arkit"))
    if options.get("dataset") is None and method.needs_landmarks:
        from ._data import ict_pose_source

        options["dataset"] = ict_pose_source(progress=False)
    options["method"] = method.loaded()

    def one(head):
        return auto_rig(head[0], head[1], **options)

    return map_items(one, heads) if across_processes else [one(head) for head in heads]


def _check_method(method, names) -> AbstractAutoRigMethod:
    """The method to run (``DEFAULT_METHOD`` for None); TypeError naming ``method`` for
    anything but an ``AbstractAutoRigMethod`` (a name is the command line's)."""
    if names not in NAME_STYLES:
        raise ValueError(f"names: expected one of {NAME_STYLES}, got {names!r}")
    if method is None:
        return DEFAULT_METHOD
    if not isinstance(method, AbstractAutoRigMethod):
        methods = ", ".join(f"autorig.{cls.__name__}()" for cls in AUTO_RIG_METHODS)
        got = f"the string {method!r}" if isinstance(method, str) else type(method).__name__
        raise TypeError(
            f"method: expected an auto-rig method ({methods}), got {got}; a method's name "
            "is for the command line (canrig autorig --method NAME)"
        )
    return method


def _check_head(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 cm and (F, 3) faces of a plausible head (10-60 cm)."""
    vertices, faces = check_mesh(vertices, faces)
    v = np.asarray(vertices, np.float64)
    height = float(np.ptp(v[:, np.argmax(np.ptp(v, axis=0))]))
    if not 10.0 <= height <= 60.0:
        raise ValueError(
            f"vertices: the head is {height:.3g} cm along its longest axis; a head is 10-60 "
            "cm: give it in centimetres"
        )
    return v, _without_defects(v, faces)


def _without_defects(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` less its repeated and degenerate triangles (a corner twice, or no area),
    stated in a warning with the edges that more than two triangles share (non-manifold:
    kept as given, and what they do under motion is for ``check_rig`` to show)."""
    ordered = np.sort(faces, axis=1)
    _, first = np.unique(ordered, axis=0, return_index=True)
    repeated = np.ones(len(faces), bool)
    repeated[first] = False
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    degenerate = (ordered[:, 0] == ordered[:, 1]) | (ordered[:, 1] == ordered[:, 2])
    degenerate |= area <= 1e-12 * max(float(area.max()), 1e-30)
    drop = repeated | degenerate
    kept = faces[~drop]
    edges = np.sort(np.concatenate([kept[:, [0, 1]], kept[:, [1, 2]], kept[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    shared = int((uses > 2).sum())
    if drop.any() or shared:
        warn(
            f"faces: {int(repeated.sum())} repeated and {int((degenerate & ~repeated).sum())} "
            f"degenerate triangles left out of the rig's mesh; {shared} edges shared by more "
            "than two triangles (non-manifold) kept as given"
        )
    return kept


def _check_placement(orientation, up, forward, landmarks, n_vertices: int):
    """Stated axes and given landmarks, checked before any work: (orientation or None,
    (68,) landmarks or None)."""
    if (up is None) != (forward is None):
        raise ValueError("up, forward: state both of the head's axes or neither")
    if orientation is None and up is not None:
        orientation = stated_orientation(up, forward)
    if landmarks is not None:
        landmarks = np.asarray(landmarks, np.int64)
        if landmarks.shape != (68,) or landmarks.min() < 0 or landmarks.max() >= n_vertices:
            raise ValueError(f"landmarks: expected 68 vertex indices in [0, {n_vertices})")
    return orientation, landmarks


def _landmarks(dataset, upright, faces, skin, landmarks, method, progress):
    """The ICT landmarks on the upright head and how they were placed (None for a method
    that does not ``needs_landmarks``, unless given)."""
    if landmarks is not None:
        return landmarks, {"by": "given", "rms_cm": float("nan")}
    if not method.needs_landmarks:
        return None, {"by": f"not needed ({method.name})", "rms_cm": float("nan")}
    _progress(progress, "placing the ICT landmarks on the head")
    landmarks, fit, fitted_by = place_landmarks(dataset, upright, faces, region=skin)
    return landmarks, {"by": fitted_by, "rms_cm": float(fit.rms)}


def check_auto_rig(result: "AutoRig", n_random: int = 48) -> RigCheck:
    """``check_rig`` of what ``auto_rig`` returned (an ``AutoRig``), under ``n_random`` random
    sparse poses of its own shapes, in the frame the rig was left in (turned into the
    convention, or the head's own)."""
    up, forward = result.orientation.up, result.orientation.forward
    if result.orientation.conventional:
        up, forward = "+y", "+z"
    return check_rig(result.rig, n_random=n_random, up=up, forward=forward)
