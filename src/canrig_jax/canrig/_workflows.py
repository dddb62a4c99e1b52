"""What an artist does with CANRig (sections 7.1-7.4), all on the one forward pass ``deform``.

- **Pose A to B, direct** (section 7.1): handles on chosen vertices of A, displacements
  B[h] - A[h], base shape A, one forward pass (``direct_edit``).
- **Pose A to B, fitted** (``fit_displacements``): the displacements that minimise the mesh
  error ||rig(A, d) - B||^2 (optionally weighted by a region, plus ``penalty`` ||d||^2),
  started from the direct displacements, by the rig's own solve (``AbstractHandleRig.fit``:
  for the attention rig ``optimistix.least_squares`` on its exact structured Jacobian,
  ``_attention_fit.py``; LSMR for the linear ``LocalFitRig``). The answer is the best of
  {fitted, direct, zero} by the reported error (the
  mean per-vertex Euclidean error over the region), so a fit is never worse than the direct
  pass nor than the base shape, exactly.
- **Iterative layers** (section 7.4, ``iterative_layers``): each layer's base shape is the
  previous layer's output; with fitting the error is non-increasing exactly.
- **Clip editing** (section 7.2, ``clip_edit``): one frame's handle displacements faded in and
  out over a window by a smoothstep curve, each frame its own base shape; frames outside the
  window are returned untouched (bit-identical).
- **Dialogue replacement** (section 7.2, ``dialogue_replacement``): per frame, handles around
  the mouth move to the target clip's positions, base shape the source frame, ``jax.vmap``
  over frames.

The rig's model may be any handle rig (``_handle_rig.py``: a trained CANRig, a ``LocalFitRig``,
a ``PBSRig``): every workflow runs on each through its ``deform`` and ``fit``. Units follow
the rig (ICT: cm). Inputs are validated in plain Python before any jit work.
"""

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Float32, Float64, Int, PyTree, Shaped
from scipy.sparse.csgraph import dijkstra

from .._checks import check_points
from .._threads import blocking_single_threaded_blas
from ..rig import BlendshapeRig
from ._handle_rig import AbstractHandleRig, FitOptions, FitState, HandleEdit, Handles
from ._layout import DENSE, Layout
from ._rig import NeuralRig, call_blas_safe, deform


class FitSolution(eqx.Module):
    """Result of ``fit_displacements``.

    Attributes:
        displacements: (H, 3) the chosen displacements (cm); never NaN.
        shape: (V, 3) the rig's shape with them.
        error: () mean per-vertex Euclidean error to the target over the region (cm).
        direct_error: () the same for the starting (direct) displacements.
        base_error: () the same for zero displacements (the base shape itself).
        chosen: 0 fitted, 1 direct (start), 2 zero: the lowest error, ties to the lower code.
        result: the solver's ``optimistix.RESULTS`` (successful or why not).
        steps: the solver's number of steps.
    """

    displacements: Float[Array, "H 3"]
    shape: Float[Array, "V 3"]
    error: Float[Array, ""]
    direct_error: Float[Array, ""]
    base_error: Float[Array, ""]
    chosen: Int[Array, ""]
    result: optx.RESULTS
    steps: Int[Array, ""]


def region_error(
    shape: Float[Array, "V 3"], target: Float[Array, "V 3"], region: Float[Array, " V"]
) -> Float[Array, ""]:
    """Mean per-vertex Euclidean distance, weighted by ``region`` (cm)."""
    distance = jnp.linalg.norm(shape - target, axis=-1)
    return jnp.sum(distance * region) / jnp.maximum(jnp.sum(region), 1e-12)


@eqx.filter_jit
def fit_displacements(
    model: AbstractHandleRig,
    queries: PyTree,
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    target: Float[Array, "V 3"],
    region: Float[Array, " V"],
    layout: Layout = DENSE,
    options: FitOptions = FitOptions(),
) -> FitSolution:
    """The handle displacements whose shape best matches ``target``: minimises
    sum_v region_v ||deform(edit with d)_v - target_v||^2 + penalty ||d||^2 over d by the
    rig's own solve (``model.fit``, see ``FitOptions``), started from ``edit.displacements``,
    and keeps the best of {fitted, direct, zero} displacements. ``queries``:
    ``model.prepare(canonical)``. Use a ``PartsLayout`` (``FIT_PARTS``) for speed with the
    attention rig. Pure and jit/vmap-able; validate with ``NeuralRig.edit``. The attention
    rig's Cholesky runs in SciPy's OpenBLAS: call it inside
    ``canrig_jax._threads.single_threaded_blas()`` (as ``pose_a_to_b`` does) or it may be
    several times slower next to XLA's threads."""
    state = model.fit(queries, canonical, edit, target, region, layout, options)
    return _best_of(edit, target, region, state)


def _best_of(
    edit: HandleEdit,
    target: Float[Array, "V 3"],
    region: Float[Array, " V"],
    state: FitState,
) -> FitSolution:
    """The ``FitSolution`` of the best of {fitted, direct, zero} displacements by the
    reported error; a non-finite fit falls back to the direct displacements."""
    fitted, fitted_shape, direct_shape = state.fitted, state.fitted_shape, state.direct_shape
    result, steps = state.result, state.steps
    start = edit.displacements
    finite = jnp.all(jnp.isfinite(fitted)) & jnp.all(jnp.isfinite(fitted_shape))
    fitted = jnp.where(finite, fitted, start)
    # the candidates' shapes: the fitted one from the solver, the direct one the start's
    # pass, and zero displacements reproduce the base exactly (zero-preserving MLPs; a
    # LocalFitRig is linear in d)
    fitted_shape = jnp.where(finite, fitted_shape, direct_shape)
    candidates = jnp.stack([fitted, start, jnp.zeros_like(start)])
    shapes = jnp.stack([fitted_shape, direct_shape, edit.base])
    errors = jax.vmap(region_error, (0, None, None))(shapes, target, region)
    errors = jnp.where(jnp.isfinite(errors), errors, jnp.inf)
    chosen = jnp.argmin(errors)
    return FitSolution(
        displacements=candidates[chosen],
        shape=shapes[chosen],
        error=errors[chosen],
        direct_error=errors[1],
        base_error=errors[2],
        chosen=chosen,
        result=result,
        steps=steps,
    )


# --------------------------------------------------------------------------- checks


def _check_region(
    rig: NeuralRig, region: Shaped[ArrayLike, " V"] | None, name: str = "region"
) -> Float[Array, " V"]:
    if region is None:
        return jnp.ones(rig.n_vertices, jnp.float32)
    region = np.asarray(region)
    if region.shape != (rig.n_vertices,):
        raise ValueError(f"{name}: expected shape ({rig.n_vertices},), got {region.shape}")
    region = region.astype(np.float32)  # bool masks become 0/1 weights
    if not np.all(np.isfinite(region)) or region.min() < 0:
        raise ValueError(f"{name}: expected finite weights >= 0")
    if not region.sum() > 0:
        raise ValueError(f"{name}: selects no vertex (all weights are 0)")
    return jnp.asarray(region)


def _check_clip(
    rig: NeuralRig, clip: Float[ArrayLike, "F V 3"], name: str
) -> Float32[np.ndarray, "F V 3"]:
    return check_points(name, clip, rig.n_vertices, frames=True)


def direct_displacements(
    source: Float[ArrayLike, "V 3"], target: Float[ArrayLike, "V 3"], handles: Handles
) -> Float32[np.ndarray, "H 3"]:
    """(H, 3) target[h] - source[h] at the handle vertices (section 7.1)."""
    index = np.asarray(handles.index)
    return np.asarray(target, np.float32)[index] - np.asarray(source, np.float32)[index]


# --------------------------------------------------------------------------- pose A to B


FIT_WIDTH_MULTIPLE = 8
"""Block layouts of fitted edits round their width up to a multiple of this (not to a power
of two): a tighter layout for the Jacobian at the price of a few more compiled shapes."""

FIT_PARTS = (0.6, 0.3, 0.1)
"""Fitted edits split the blocks, sorted by how many handles reach them, into parts of these
fractions, each with its own width (``PartsLayout``): the Jacobian's cost grows with the
width and its normal matrix's with its square, and one width pads every block to the most
crowded one."""


def pose_a_to_b(
    rig: NeuralRig,
    handles: Handles,
    source: Float[ArrayLike, "V 3"],
    target: Float[ArrayLike, "V 3"],
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    *,
    fit: bool = False,
    region: Shaped[ArrayLike, " V"] | None = None,
    options: FitOptions = FitOptions(),
    beta: float | None = None,
    dense: bool = False,
) -> FitSolution:
    """Deform pose A (``source``, the base shape) towards pose B (``target``) with handles:
    direct (B[h] - A[h], one forward pass) or, with ``fit``, the displacements that best
    match B over ``region`` (bool or weights (V,), default every vertex). Returns a
    ``FitSolution`` either way (direct: ``chosen`` 1, ``steps`` 0)."""
    source = rig.check_base(source, "source")
    target = rig.check_base(target, "target")
    region = _check_region(rig, region)
    edit = rig.edit(
        handles,
        direct_displacements(source, target, handles),
        radius,
        falloff,
        base=source,
        beta=beta,
    )
    # the fit's Jacobian and normal matrix grow with the layout's width (linearly and
    # quadratically): parts of their own widths, multiples of 8, not one power of two
    if dense:
        layout = DENSE
    elif fit:
        layout = rig.layout(handles, radius, falloff, multiple=FIT_WIDTH_MULTIPLE, parts=FIT_PARTS)
    else:
        layout = rig.layout(handles, radius, falloff)
    if fit:
        # one BLAS thread while the fit's Cholesky runs (see canrig_jax._threads)
        return blocking_single_threaded_blas(
            fit_displacements,
            rig.model,
            rig.queries,
            rig.canonical,
            edit,
            target,
            region,
            layout,
            options,
        )
    return call_blas_safe(rig.model, _direct_solution, rig, edit, target, region, layout)


@eqx.filter_jit
def _direct(model, queries, canonical, edit, target, region, layout):
    shape = deform(model, queries, canonical, edit, layout)
    error = region_error(shape, target, region)
    return shape, error, region_error(edit.base, target, region)


def _direct_solution(rig, edit, target, region, layout) -> FitSolution:
    shape, error, base_error = _direct(
        rig.model, rig.queries, rig.canonical, edit, target, region, layout
    )
    return FitSolution(
        displacements=edit.displacements,
        shape=shape,
        error=error,
        direct_error=error,
        base_error=base_error,
        chosen=jnp.asarray(1),
        result=optx.RESULTS.successful,
        steps=jnp.asarray(0),
    )


# --------------------------------------------------------------------------- layers


@dataclasses.dataclass(frozen=True)
class LayerResult:
    """What ``iterative_layers`` returns (its docstring lists the fields)."""

    solutions: tuple[FitSolution, ...]

    @property
    def errors(self) -> Float64[np.ndarray, " L"]:
        """(L,) each layer's error (cm)."""
        return np.array([float(s.error) for s in self.solutions])

    @property
    def shape(self) -> Float[Array, "V 3"]:
        """(V, 3) the last layer's shape."""
        return self.solutions[-1].shape


def iterative_layers(
    rig: NeuralRig,
    source: Float[ArrayLike, "V 3"],
    target: Float[ArrayLike, "V 3"],
    schedule: Sequence[tuple[Handles, float]],
    falloff: float,
    *,
    fit: bool = False,
    region: Shaped[ArrayLike, " V"] | None = None,
    options: FitOptions = FitOptions(),
) -> LayerResult:
    """Layered edits (section 7.4): layer i places ``schedule[i] = (handles, radius)`` on the
    previous layer's output (the first on ``source``) and moves them towards ``target``.
    With ``fit`` each layer's error is <= the previous one's, exactly (zero displacements
    reproduce the base, and the fit returns the best of fitted, direct and zero).

    Returns:
        A ``LayerResult``: ``solutions``, each layer's ``FitSolution`` in order; ``errors``
        (L,), each layer's error (cm); ``shape`` (V, 3), the last layer's shape.
    """
    schedule = list(schedule)
    if not schedule:
        raise ValueError("schedule: expected at least one (handles, radius) layer")
    for i, layer in enumerate(schedule):
        if not (isinstance(layer, tuple) and len(layer) == 2 and isinstance(layer[0], Handles)):
            raise ValueError(f"schedule[{i}]: expected a (Handles, radius) pair, got {layer!r}")
    current = rig.check_base(source, "source")
    solutions = []
    for handles, radius in schedule:
        solution = pose_a_to_b(
            rig,
            handles,
            current,
            target,
            radius,
            falloff,
            fit=fit,
            region=region,
            options=options,
        )
        solutions.append(solution)
        current = solution.shape
    return LayerResult(tuple(solutions))


# --------------------------------------------------------------------------- clips


def smoothstep_fade(n_frames: int, frame: int, half_window: int) -> Float32[np.ndarray, " F"]:
    """(F,) weight of an edit at ``frame`` faded in and out over ``half_window`` frames on
    each side: 1 at the frame, smoothstep 3x^2 - 2x^3 of x = 1 - |f - frame| / (half + 1)
    inside, 0 outside; both ends have zero slope (no velocity jump)."""
    f = np.arange(n_frames, dtype=np.float64)
    x = np.clip(1.0 - np.abs(f - frame) / (half_window + 1.0), 0.0, 1.0)
    return (x * x * (3.0 - 2.0 * x)).astype(np.float32)


@eqx.filter_jit
def _edit_frames(model, queries, canonical, edit, bases, displacements, layout):
    """deform of one edit over frames: each frame its own base and displacements."""

    def one(base, d):
        return deform(model, queries, canonical, edit.with_base(base).with_displacements(d), layout)

    return jax.vmap(one)(bases, displacements)


@dataclasses.dataclass(frozen=True)
class ClipEdit:
    """What ``clip_edit`` returns (its docstring lists the fields)."""

    clip: Float32[np.ndarray, "F V 3"]
    fade: Float32[np.ndarray, " F"]
    window: tuple[int, int]


def clip_edit(
    rig: NeuralRig,
    clip: Float[ArrayLike, "F V 3"],
    frame: int | np.integer,
    handles: Handles,
    displacements: Float[ArrayLike, "H 3"],
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    half_window: int | np.integer,
    *,
    beta: float | None = None,
) -> ClipEdit:
    """Edit ``clip`` at ``frame`` with ``displacements`` at the handles, faded in and out
    over ``half_window`` frames on each side (``smoothstep_fade``), each frame its own base
    shape (section 7.2). Frames outside the window are the input frames, untouched.

    Returns:
        A ``ClipEdit``: ``clip`` (F, V, 3) float32, the edited clip; ``fade`` (F,), each
        frame's fade weight (0 outside the window, 1 at ``frame``); ``window``, the first and
        the last frame of the window.
    """
    clip = _check_clip(rig, clip, "clip")
    n = len(clip)
    if isinstance(frame, bool) or not isinstance(frame, int | np.integer) or not 0 <= frame < n:
        raise ValueError(f"frame: expected an integer frame index in [0, {n}), got {frame!r}")
    if isinstance(half_window, bool) or not isinstance(half_window, int | np.integer):
        raise ValueError(f"half_window: expected an integer >= 0, got {half_window!r}")
    if half_window < 0 or frame - half_window < 0 or frame + half_window >= n:
        raise ValueError(
            f"half_window: the fade window [{frame - half_window}, {frame + half_window}] must "
            f"lie inside the clip's frames [0, {n - 1}]"
        )
    edit = rig.edit(handles, displacements, radius, falloff, base=clip[frame], beta=beta)
    layout = rig.layout(handles, radius, falloff)
    fade = smoothstep_fade(n, int(frame), int(half_window))
    lo, hi = frame - half_window, frame + half_window + 1
    scaled = fade[lo:hi, None, None] * np.asarray(edit.displacements)[None]
    edited = call_blas_safe(
        rig.model,
        _edit_frames,
        rig.model,
        rig.queries,
        rig.canonical,
        edit,
        jnp.asarray(clip[lo:hi]),
        jnp.asarray(scaled),
        layout,
    )
    out = clip.copy()
    out[lo:hi] = np.asarray(edited)
    return ClipEdit(out, fade, (lo, hi - 1))


# --------------------------------------------------------------------------- dialogue


@eqx.filter_jit
def _fit_frames(model, queries, canonical, edit, bases, targets, region, layout, options):
    def one(base, target):
        index = edit.index
        start = edit.with_base(base).with_displacements(target[index] - base[index])
        return fit_displacements(model, queries, canonical, start, target, region, layout, options)

    return jax.vmap(one)(bases, targets)


def dialogue_replacement(
    rig: NeuralRig,
    source: Float[ArrayLike, "F V 3"],
    target: Float[ArrayLike, "F V 3"],
    handles: Handles,
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    *,
    fit: bool = False,
    region: Shaped[ArrayLike, " V"] | None = None,
    options: FitOptions = FitOptions(),
    beta: float | None = None,
) -> Float32[np.ndarray, "F V 3"]:
    """Replace the mouth of ``source`` with that of ``target`` (section 7.2), frame by frame
    (``jax.vmap``): handles (around the mouth and chin) move to the target frame's positions,
    base shape the source frame; with ``fit``, the displacements that best match the target
    over ``region`` (e.g. a mouth mask). Vertices outside every clamped mask keep the source
    frame exactly. Returns (F, V, 3)."""
    source = _check_clip(rig, source, "source")
    target = _check_clip(rig, target, "target")
    if source.shape != target.shape:
        raise ValueError(
            f"target: expected the source's shape {source.shape} (frame by frame), got "
            f"{target.shape}"
        )
    weights = _check_region(rig, region)
    index = np.asarray(handles.index)
    displacements = target[:, index] - source[:, index]
    edit = rig.edit(handles, displacements[0], radius, falloff, base=source[0], beta=beta)
    if fit:
        layout = rig.layout(handles, radius, falloff, multiple=FIT_WIDTH_MULTIPLE, parts=FIT_PARTS)
        solutions = blocking_single_threaded_blas(
            _fit_frames,
            rig.model,
            rig.queries,
            rig.canonical,
            edit,
            jnp.asarray(source),
            jnp.asarray(target),
            weights,
            layout,
            options,
        )
        return np.asarray(solutions.shape)
    layout = rig.layout(handles, radius, falloff)
    out = call_blas_safe(
        rig.model,
        _edit_frames,
        rig.model,
        rig.queries,
        rig.canonical,
        edit,
        jnp.asarray(source),
        jnp.asarray(displacements),
        layout,
    )
    return np.asarray(out)


def interior_vertices(
    rig: NeuralRig, region: Shaped[ArrayLike, " V"], margin: float
) -> Int[np.ndarray, " N"]:
    """Vertices of the boolean ``region`` (V,) whose geodesic distance to every vertex
    outside it exceeds ``margin`` (cm): handles there, with ``influence_reach`` <= margin,
    cannot move anything outside the region."""
    region = np.asarray(region, bool)
    if region.shape != (rig.n_vertices,):
        raise ValueError(f"region: expected shape ({rig.n_vertices},), got {region.shape}")
    outside = np.flatnonzero(~region)
    if len(outside) == 0:
        return np.flatnonzero(region)
    if not region.any():
        raise ValueError("region: selects no vertex")
    if not margin >= 0:
        raise ValueError(f"margin: expected >= 0, got {margin}")
    distance = dijkstra(rig.graph, directed=False, indices=outside, min_only=True)
    return np.flatnonzero(region & (distance > margin))


def expression_region(
    rig: BlendshapeRig,
    include: Sequence[str] = ("jaw", "mouth"),
    exclude: Sequence[str] = ("eye", "brow"),
    threshold: float = 0.1,
) -> Bool[np.ndarray, " V"]:
    """(V,) bool: the vertices that some expression whose name starts with one of
    ``include`` moves by more than ``threshold`` (rig units; ICT: 0.1 cm = 1 mm) and that no
    expression starting with one of ``exclude`` moves that much. On ICT the default is the
    mouth region: lips, chin, jaw line and cheeks, without the eyelids."""
    names = tuple(rig.names)
    deltas = np.asarray(rig.deltas)
    moved = np.linalg.norm(deltas, axis=-1) > threshold  # (K, V)

    def any_of(prefixes):
        rows = [i for i, n in enumerate(names) if n.startswith(tuple(prefixes))]
        return moved[rows].any(axis=0) if rows else np.zeros(deltas.shape[1], bool)

    if not any(n.startswith(tuple(include)) for n in names):
        raise ValueError(f"include: no expression of the rig starts with {tuple(include)}")
    return any_of(include) & ~any_of(exclude)


def max_acceleration(clip: Float[ArrayLike, "F V 3"]) -> float:
    """The largest per-vertex second difference ||x_{f+1} - 2 x_f + x_{f-1}|| of a clip
    (units per frame^2); 0 for fewer than 3 frames."""
    clip = np.asarray(clip, np.float64)
    if len(clip) < 3:
        return 0.0
    second = clip[2:] - 2.0 * clip[1:-1] + clip[:-2]
    return float(np.linalg.norm(second, axis=-1).max())
