"""One contract for every inverse-rig method (``METHOD_CASES``), on the real rigs: ict-quartic
and the linear ICT rig (no correctives), driven by real Live Link Face frames, and on a small
synthetic rig with pair, triplet and quad correctives, so the contract also runs without the
data folder.

A new method is tested by adding one instance to ``METHOD_CASES``;
``test_every_method_class_is_listed`` fails until it is.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from canrig_jax import inverse
from canrig_jax.rig import evaluate

METHOD_CASES = (
    inverse.QuarticCD(alpha=0.5, passes=4),
    inverse.QuarticCD(alpha=0.5, passes=3, tol=0.0, newton=False, order="random"),
    inverse.QuarticNewton(alpha=0.5, iterations=4),
    inverse.TemporalNewton(alpha=0.5, smoothness=0.0),  # the per-frame contract holds
    inverse.LinearCD(alpha=0.5, passes=4),
    inverse.Seol(),
    inverse.Joshi(),
    inverse.Cetinaslan(alpha=0.5),
    inverse.LMMM(alpha=0.5, iterations=6),
    inverse.JaxoptLBFGSB(alpha=0.5, maxiter=8),
    # exclusive pairs resolved by re-solving, and a left/right tie (indices valid on every rig)
    inverse.Constrained(
        inverse.QuarticNewton(alpha=0.5, iterations=4),
        exclusive=((0, 1), (2, 3)),
        ties=((4, 5),),
        tie_weight=0.5,
    ),
    # the production terms: L2, temporal (off outside a warm Stream), one gain and offset
    inverse.Constrained(
        inverse.QuarticNewton(alpha=0.5, iterations=4),
        exclusive=((0, 1),),
        l2_weight=0.1,
        temporal_weight=1.0,
        multipliers=1.2,
        offsets=0.02,
    ),
)


def _id(method) -> str:
    name = type(method).__name__ + ("-random" if getattr(method, "order", "") == "random" else "")
    return name + ("-production" if getattr(method, "multipliers", None) is not None else "")


CASES = [
    pytest.param(
        m,
        id=_id(m),
        # L-BFGS-B's compile alone is ~30 s: its contract runs in -m slow
        marks=[pytest.mark.slow] if isinstance(m, inverse.JaxoptLBFGSB) else [],
    )
    for m in METHOD_CASES
]
FAST_ON_LINEAR = (inverse.QuarticCD, inverse.LMMM, inverse.Cetinaslan)
"""Methods run on the linear rig by default (LMMM used to return NaN there); the others on
the linear rig are in ``-m slow`` (the default run is shared by the whole suite)."""


def test_every_method_class_is_listed():
    assert {type(m) for m in METHOD_CASES} == set(inverse.METHODS)


def test_methods_are_final_subclasses_of_the_abstract_base():
    for cls in inverse.METHODS:
        assert issubclass(cls, inverse.AbstractInverseMethod)
        # abstract or final: no listed (concrete) method derives from another listed one
        assert not any(issubclass(cls, other) for other in inverse.METHODS if other is not cls), cls


@pytest.fixture(
    scope="module",
    # the default run holds every method to the contract on the synthetic rig (no data folder)
    # and the linear ICT rig; on ict-quartic in -m slow (the claims tests are its evidence)
    params=["synthetic", pytest.param("ict_quartic", marks=pytest.mark.slow), "ict_linear"],
)
def case(request):
    if request.param == "synthetic":
        rig = request.getfixturevalue("synthetic_rig")
        problem = inverse.prepare(rig)
        weights = np.random.default_rng(1).uniform(0, 1, (3, rig.n_blendshapes))
        weights[weights < 0.5] = 0.0  # sparse, as real frames are
    else:
        if request.param == "ict_quartic":
            rig = request.getfixturevalue("ict_quartic")
            problem = request.getfixturevalue("ict_quartic_problem")
        else:
            rig = request.getfixturevalue("ict_face")
            problem = inverse.prepare(rig)
        weights = request.getfixturevalue("livelink_weights")[[20, 90, 150]]
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(rig, weights))
    noise = np.random.default_rng(0).normal(0, np.sqrt(0.03), clean.shape)
    return rig, problem, (clean + noise).astype(np.float32)


@pytest.mark.parametrize("method", CASES)
def test_contract(case, method):
    """jit + vmap (``solve_sequence``) agree with one ``solve`` per frame; Solution shapes;
    finite weights in the box; the reported objective is the method's objective computed
    independently through ``evaluate``; result codes; no NaN on a rig without correctives."""
    rig, problem, targets = case
    if not rig.correctives and not isinstance(method, FAST_ON_LINEAR):
        pytest.skip("in -m slow: test_contract_on_the_linear_rig")
    _check_contract(rig, problem, targets, method)


@pytest.mark.slow
@pytest.mark.parametrize("method", CASES)
def test_contract_on_the_linear_rig(ict_face, livelink_weights, method):
    problem = inverse.prepare(ict_face)
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(ict_face, livelink_weights[[20, 90, 150]]))
    noise = np.random.default_rng(0).normal(0, np.sqrt(0.03), clean.shape)
    _check_contract(ict_face, problem, (clean + noise).astype(np.float32), method)


def _check_contract(rig, problem, targets, method):
    t, k = targets.shape[0], rig.n_blendshapes
    batch = inverse.solve_sequence(problem, targets, method)
    assert batch.weights.shape == (t, k) and batch.objective.shape == (t,)
    assert batch.history.ndim == 2 and batch.history.shape[0] == t
    assert batch.stats["steps"].shape == (t,) and batch.stats["converged"].shape == (t,)
    weights = np.asarray(batch.weights, np.float64)
    assert np.all(np.isfinite(weights)), weights
    assert np.all(weights >= 0) and np.all(weights <= method.upper)
    results = np.asarray(batch.result._value)
    success, capped = (
        int(r._value) for r in (optx.RESULTS.successful, optx.RESULTS.max_steps_reached)
    )
    codes = {success, capped}
    if isinstance(method, inverse.JaxoptLBFGSB):  # its line search can fail first
        codes.add(int(optx.RESULTS.stagnation._value))
    assert set(results.tolist()) <= codes, results
    converged = np.asarray(batch.stats["converged"])
    np.testing.assert_array_equal(results == success, converged)

    meshes = np.asarray(jax.vmap(evaluate, (None, 0))(rig, batch.weights), np.float64)
    data = 0.5 * ((meshes - targets.astype(np.float64)) ** 2).sum(axis=(1, 2))
    l1 = method.alpha * weights.sum(1) if method.penalises_l1 else 0.0
    np.testing.assert_allclose(np.asarray(batch.objective), data + l1, rtol=2e-4)

    keys = jax.random.split(jax.random.key(0), t)  # solve_sequence's keys: one per frame
    for frame in (0, t - 1):
        single = inverse.solve(problem, targets[frame], method, key=keys[frame])
        assert single.weights.shape == (k,) and single.history.shape == batch.history.shape[1:]
        # the same minimisation one frame at a time (vmap changes float rounding, so the
        # weights of an unconverged run may drift where E is flat; E itself agrees)
        np.testing.assert_allclose(
            float(single.objective), float(batch.objective[frame]), rtol=2e-3
        )


@pytest.mark.parametrize("method", CASES)
def test_bad_input_is_reported_before_any_compilation(ict_quartic_problem, method):
    problem = ict_quartic_problem
    target = np.asarray(problem.neutral)
    with pytest.raises(ValueError, match="target"):
        inverse.solve(problem, target[:-1], method)
    with pytest.raises(ValueError, match="target"):
        inverse.solve(problem, np.where(np.arange(3) == 1, np.nan, target), method)
    with pytest.raises(ValueError, match="init"):
        inverse.solve(problem, target, method, init=np.zeros(3))
    with pytest.raises(ValueError, match="init"):
        inverse.solve(problem, target, method, init=np.full(problem.n_blendshapes, np.nan))
    with pytest.raises(ValueError, match=r"targets: frames \[1\]"):
        bad = np.stack([target, target * np.nan, target])
        inverse.solve_sequence(problem, bad, method, warm_start=True)
    with pytest.raises(TypeError, match="method"):
        inverse.solve(problem, target, type(method).__name__)
    with pytest.raises(TypeError, match="method"):
        inverse.solve(problem, target, type(method))
    with pytest.raises(TypeError, match="problem"):
        inverse.solve(problem.columns, target, method)
    with pytest.raises(TypeError, match="key"):
        inverse.solve(problem, target, method, key=0)


def test_hyper_parameters_are_checked_at_construction():
    for make, argument in [
        (lambda: inverse.QuarticCD(alpha=-1.0), "alpha"),
        (lambda: inverse.QuarticCD(alpha=float("nan")), "alpha"),
        (lambda: inverse.QuarticCD(passes=0), "passes"),
        (lambda: inverse.QuarticCD(tol=-0.1), "tol"),
        (lambda: inverse.QuarticCD(order="sideways"), "order"),
        (lambda: inverse.LinearCD(upper=0.0), "upper"),
        (lambda: inverse.Seol(order="random"), "order"),
        (lambda: inverse.Cetinaslan(alpha=-2.0), "alpha"),
        (lambda: inverse.LMMM(iterations=0), "iterations"),
        (lambda: inverse.QuarticNewton(iterations=0), "iterations"),
        (lambda: inverse.QuarticNewton(line_steps=0), "line_steps"),
        (lambda: inverse.QuarticNewton(tol=1.0), "tol"),
        (lambda: inverse.QuarticNewton(upper=-1.0), "upper"),
        (lambda: inverse.JaxoptLBFGSB(objective="mesh"), "objective"),
    ]:
        with pytest.raises(ValueError, match=argument):
            make()


def test_prepare_reports_rigs_it_cannot_solve(ict_face):
    empty = type(ict_face)(ict_face.neutral, jnp.zeros((0, ict_face.n_vertices, 3)))
    with pytest.raises(ValueError, match="no blendshapes"):
        inverse.prepare(empty)
    with pytest.raises(TypeError, match="rig"):
        inverse.prepare(np.zeros((3, 3)))
    zero = type(ict_face)(
        ict_face.neutral, ict_face.deltas.at[3].set(0.0), (), ict_face.names, ict_face.faces
    )
    with pytest.raises(ValueError, match=ict_face.names[3]):
        inverse.prepare(zero)
    with pytest.warns(UserWarning, match=ict_face.names[3]):
        dropped = inverse.prepare(zero, drop_zero_shapes=True)
    assert dropped.rig.names == ict_face.names[:3] + ict_face.names[4:]
    # the smaller problem recovers a pose of the shapes it kept
    pose = np.zeros(ict_face.n_blendshapes, np.float32)
    pose[[0, 10, 20]] = (0.3, 0.7, 0.5)
    target = evaluate(zero, pose)
    solution = inverse.solve(dropped, target, inverse.LinearCD(passes=200, tol=1e-7))
    np.testing.assert_allclose(np.asarray(solution.weights), np.delete(pose, 3), atol=2e-3)
