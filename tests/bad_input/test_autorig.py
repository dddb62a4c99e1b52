"""Bad inputs of the auto-rigger's public entry points: the network methods and their rig
generation (``RigAnyFaceNetwork.generate``), pose sets, features, ``auto_rig``."""

from __future__ import annotations

import dataclasses
import types

import jax.numpy as jnp
import numpy as np
import pytest

import canrig_jax.autorig._any_head as any_head_module  # patched: the work after the checks
import canrig_jax.autorig._data as data_module  # patched: the ICT source
import canrig_jax.autorig._methods as methods_module  # patched: every method's work
from canrig_jax.autorig import (
    RigAnyFaceNetwork,
    RigAnyFaceTrainOptions,
    Template,
    Transfer,
    TransferResidual,
    auto_rig,
    heat_kernel_signature,
    hks_times,
)
from canrig_jax.autorig._data import (
    AutorigDataset,
    PoseSet,
    fit_head_landmarks,
    pose_displacements,
    quartic_pose_set,
)
from canrig_jax.autorig._train import make_model
from canrig_jax.data import load_ict, load_mediapipe_face
from canrig_jax.mesh import decimate, fit_landmarks, mesh_operators
from canrig_jax.rig import BlendshapeRig, Corrective

from .conftest import handled, raises, run_case

NEUTRAL = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
FACES = np.array([[0, 1, 2], [0, 2, 3]])


@pytest.fixture(scope="module")
def ctx(data_dir):
    deltas = np.zeros((2, 4, 3), np.float32)
    deltas[0, 2, 2], deltas[1, 1, 1] = 0.5, -0.25
    pair = Corrective([[0, 1]], [1, 2], np.full((1, 2, 3), 0.125, np.float32))
    rig = BlendshapeRig(NEUTRAL, deltas, (pair,), ("a", "b"), FACES)
    poses = quartic_pose_set(rig, {2: 1})
    options = RigAnyFaceTrainOptions(
        width=8, n_shared=1, n_conditional=1, global_size=8, global_width=8, k=8
    )
    model = make_model(options, poses.n_basis, 1.0)
    residual = make_model(dataclasses.replace(options, residual=True), poses.n_basis, 1.0)
    face = load_mediapipe_face(data_dir)
    operators = mesh_operators(face.neutral, face.faces, k=16, cache=False)
    ict = load_ict(data_dir, parts=None)
    head = decimate(ict.neutral, ict.faces, 800)  # an ICT head: y up, facing +z, cm
    dataset = AutorigDataset(None, ict, None, [], {})  # fit_head_landmarks uses the head only
    return types.SimpleNamespace(
        rig=rig,
        poses=poses,
        model=model,
        residual=residual,
        face=face,
        operators=operators,
        head=head,
        head_operators=mesh_operators(head.vertices, head.faces, k=8, cache=False),
        dataset=dataset,
    )


BACKWARDS = np.diag([-1.0, 1.0, -1.0])  # 180 degrees about y: facing -z


def _generate(c, **kw):
    args = dict(vertices=c.face.neutral, faces=c.face.faces, k=8)
    args.update(kw)
    return RigAnyFaceNetwork((c.model, c.poses)).generate(**args)


GENERATE_RIG = [
    raises(
        "nan-vertex",
        lambda c: _generate(c, vertices=np.where(c.face.neutral > 5, np.nan, c.face.neutral)),
        ValueError,
        "vertices",
    ),
    raises("float-faces", lambda c: _generate(c, faces=c.face.faces + 0.5), ValueError, "faces"),
    raises(
        "face-out-of-range", lambda c: _generate(c, faces=c.face.faces + 1), ValueError, "faces"
    ),
    raises("no-faces", lambda c: _generate(c, faces=np.zeros((0, 3), int)), ValueError, "faces"),
    raises(
        "not-a-model",
        lambda c: RigAnyFaceNetwork((None, c.poses)),
        TypeError,
        "model",
    ),
    raises(
        "not-a-pose-set",
        lambda c: RigAnyFaceNetwork((c.model, [[0]])),
        TypeError,
        "model",
    ),
    raises("model-not-a-pair", lambda c: RigAnyFaceNetwork(c.model), TypeError, "model"),
    raises(
        "residual-model-without-transfer",
        lambda c: RigAnyFaceNetwork((c.residual, c.poses)),
        ValueError,
        "model: a residual",
    ),
    raises(
        "plain-model-as-residual",
        lambda c: TransferResidual((c.model, c.poses)),
        ValueError,
        "model: a plain",
    ),
    raises(
        "missing-checkpoint",
        lambda c: RigAnyFaceNetwork("no/such/checkpoint.eqx").generate(
            c.face.neutral, c.face.faces
        ),
        FileNotFoundError,
        "model",
    ),
    raises(
        "residual-without-base",
        lambda c: TransferResidual((c.residual, c.poses)).generate(c.face.neutral, c.face.faces),
        ValueError,
        "base",
    ),
    raises(
        "pose-set-of-another-model",
        lambda c: RigAnyFaceNetwork(
            (c.model, PoseSet(("a", "b", "c"), ((0,), (1,), (2,))))
        ).generate(c.face.neutral, c.face.faces),
        ValueError,
        "poses",
    ),
    raises("zero-k", lambda c: _generate(c, k=0), ValueError, "k"),
    raises("zero-bucket", lambda c: _generate(c, bucket=0), ValueError, "bucket"),
    raises("zero-pose-chunk", lambda c: _generate(c, pose_chunk=0), ValueError, "pose_chunk"),
    raises(
        "tiny-memory-budget",
        lambda c: _generate(c, memory_budget=1000),
        ValueError,
        "memory_budget",
    ),
    raises(
        "base-for-a-plain-model",
        lambda c: _generate(c, base=np.zeros((c.poses.n_poses, c.face.neutral.shape[0], 3))),
        ValueError,
        "base",
    ),
    raises("unknown-loss", lambda c: RigAnyFaceTrainOptions(loss="l3"), ValueError, "loss"),
    raises(
        "negative-static-weight",
        lambda c: RigAnyFaceTrainOptions(static_weight=-1.0),
        ValueError,
        "static_weight",
    ),
    raises(
        "head-in-metres",
        lambda c: fit_landmarks(
            c.face.neutral, np.arange(10), np.ones(468, bool), c.face.neutral / 100, c.face.faces
        ),
        ValueError,
        "target_vertices",
    ),
    raises(
        "unknown-orientation",
        lambda c: _generate(c, orientation="guess"),
        ValueError,
        "orientation",
    ),
    raises(
        "head-facing-backwards",
        lambda c: _generate(c, vertices=c.head.vertices @ BACKWARDS, faces=c.head.faces),
        ValueError,
        "vertices",
    ),
    raises(
        "head-stored-z-up",
        lambda c: _generate(
            c, vertices=c.head.vertices[:, [0, 2, 1]] * [1, -1, 1], faces=c.head.faces
        ),
        ValueError,
        "vertices",
    ),
    raises(
        "fix-with-operators-of-the-stored-head",
        lambda c: _generate(
            c,
            vertices=c.head.vertices @ BACKWARDS,
            faces=c.head.faces,
            orientation="fix",
            operators=c.head_operators,
        ),
        ValueError,
        "operators",
    ),
    raises(
        "zero-placement-scale",
        lambda c: _generate(c, placement=([0, 0, 0], 0.0)),
        ValueError,
        "placement",
    ),
    raises(
        "nan-placement-centre",
        lambda c: _generate(c, placement=([np.nan, 0, 0], 1.0)),
        ValueError,
        "placement",
    ),
    raises(
        "operators-of-another-mesh",
        lambda c: _generate(c, vertices=NEUTRAL, faces=FACES, operators=c.operators),
        ValueError,
        "operators",
    ),
]


@pytest.mark.parametrize("case", GENERATE_RIG)
def test_network_methods_and_generate(case, ctx):
    run_case(case, ctx)


POSE_SETS = [
    raises(
        "singles-not-first", lambda c: PoseSet(("a", "b"), ((1,), (0,))), ValueError, "combinations"
    ),
    raises(
        "index-out-of-range",
        lambda c: PoseSet(("a", "b"), ((0,), (1,), (0, 2))),
        ValueError,
        "combinations",
    ),
    raises(
        "repeated-index",
        lambda c: PoseSet(("a", "b"), ((0,), (1,), (1, 1))),
        ValueError,
        "combinations",
    ),
    raises(
        "more-than-the-rig-has", lambda c: quartic_pose_set(c.rig, {2: 2}), ValueError, "per_order"
    ),
    raises("negative-count", lambda c: quartic_pose_set(c.rig, {2: -1}), ValueError, "per_order"),
    raises("not-a-rig", lambda c: quartic_pose_set(NEUTRAL), TypeError, "rig"),
    raises(
        "names-differ",
        lambda c: pose_displacements(c.rig, PoseSet(("x", "y"), ((0,), (1,)))),
        ValueError,
        "rig",
    ),
    handled(
        "pair-pose-includes-its-corrective",
        lambda c: pose_displacements(c.rig, c.poses),
        lambda d, c: np.testing.assert_allclose(
            d[2],
            np.asarray(c.rig.deltas).sum(0) + np.array([0, 0.125, 0.125, 0])[:, None] * [1, 1, 1],
            atol=1e-6,
        ),
    ),
]


@pytest.mark.parametrize("case", POSE_SETS)
def test_pose_sets(case, ctx):
    run_case(case, ctx)


FEATURES = [
    raises(
        "negative-time",
        lambda c: heat_kernel_signature(c.operators, np.array([-1.0, 1.0])),
        ValueError,
        "times",
    ),
    raises(
        "nan-time",
        lambda c: heat_kernel_signature(c.operators, np.array([np.nan])),
        ValueError,
        "times",
    ),
    raises(
        "complex-time",
        lambda c: heat_kernel_signature(c.operators, np.array([1j])),
        TypeError,
        "times",
    ),
    raises(
        "no-times", lambda c: heat_kernel_signature(c.operators, np.zeros(0)), ValueError, "times"
    ),
    raises(
        "nan-eigenvalues", lambda c: hks_times(np.array([0.0, np.nan])), ValueError, "eigenvalues"
    ),
    raises("all-zero-eigenvalues", lambda c: hks_times(np.zeros(4)), ValueError, "eigenvalues"),
    raises("zero-times", lambda c: hks_times(np.array([0.0, 1.0, 2.0]), 0), ValueError, "n_times"),
    handled(
        "time-zero-is-the-squared-eigenvectors",
        lambda c: heat_kernel_signature(c.operators, jnp.zeros(1)),
        lambda h, c: np.testing.assert_allclose(
            np.asarray(h)[:, 0],
            np.sum(np.asarray(c.operators.eigenvectors) ** 2, axis=1),
            rtol=1e-5,
        ),
    ),
]


@pytest.mark.parametrize("case", FEATURES)
def test_features(case, ctx):
    run_case(case, ctx)


HEADS = [
    raises(
        "no-face-on-the-head",
        lambda c: fit_head_landmarks(c.dataset, *_sphere(12.0)),
        ValueError,
        "vertices",
    ),
    raises(
        "head-facing-backwards",
        lambda c: fit_head_landmarks(c.dataset, c.head.vertices @ BACKWARDS, c.head.faces),
        ValueError,
        "vertices",
    ),
]


def _sphere(radius_cm: float):
    from scipy.spatial import ConvexHull

    points = np.random.default_rng(0).standard_normal((400, 3))
    points *= radius_cm / np.linalg.norm(points, axis=1, keepdims=True)
    return points, ConvexHull(points).simplices


@pytest.mark.slow  # each runs the landmark fit (~7 s) before its error
@pytest.mark.parametrize("case", HEADS)
def test_head_landmarks(case, ctx):
    run_case(case, ctx)


@pytest.mark.slow  # runs the landmark fit (~7 s) before its error
def test_head_in_metres_is_warned_and_refused_naming_the_argument(ctx):
    with pytest.warns(UserWarning, match="vertices: .*centimetres"):
        with pytest.raises(ValueError, match="vertices"):
            fit_head_landmarks(ctx.dataset, ctx.head.vertices / 100.0, ctx.head.faces)


# --- auto_rig: every bad argument refused before the ICT source, the orientation or the
# landmarks are reached (those are patched to fail the test if they are) -----------------------


@pytest.fixture(scope="module")
def any_head(data_dir):
    """A Rocketbox head (cm, y up, facing +z) and a template that must never be used."""
    head = np.load(data_dir / "rocketbox" / "Male_Adult_08_head.npz")
    names = tuple(str(n) for n in head["names"])
    rig = BlendshapeRig(head["neutral"], head["deltas"], (), names, head["faces"])
    return types.SimpleNamespace(
        vertices=head["neutral"],
        faces=head["faces"],
        jaw=head["deltas"][names.index("jawOpen")],
        template=Template(rig, np.arange(68)),
        small_rig=BlendshapeRig(NEUTRAL, np.ones((1, 4, 3)), (), ("jawOpen",), FACES),
    )


@pytest.fixture
def no_work_reached(monkeypatch):
    def reached(*args, **kwargs):
        raise AssertionError("auto_rig did work before refusing its input")

    monkeypatch.setattr(data_module, "ict_pose_source", reached)
    for name in ("decide_orientation", "place_landmarks"):
        monkeypatch.setattr(any_head_module, name, reached)
    for name in ("_anchored_transfer", "_template_rig", "generate_rig"):
        monkeypatch.setattr(methods_module, name, reached)


def _auto_rig(c, **kw):
    args = dict(vertices=c.vertices, faces=c.faces)
    args.update(kw)
    return auto_rig(**args)


AUTO_RIG = [
    raises("unknown-method", lambda c: _auto_rig(c, method="fast"), TypeError, "method"),
    raises(
        "method-by-its-name",
        lambda c: _auto_rig(c, method="raf"),
        TypeError,
        "method: expected an auto-rig method (autorig.Transfer()",
    ),
    raises("method-a-class", lambda c: _auto_rig(c, method=Transfer), TypeError, "method"),
    raises("unknown-names", lambda c: _auto_rig(c, names="ict"), ValueError, "names"),
    raises(
        "template-not-a-template",
        lambda c: _auto_rig(c, method=Transfer(template=c.template.rig)),
        TypeError,
        "template",
    ),
    raises(
        "example-unknown-name",
        lambda c: _auto_rig(c, examples={"smile": c.jaw}),
        ValueError,
        "examples",
    ),
    raises(
        "example-other-topology",
        lambda c: _auto_rig(c, examples={"jawOpen": c.jaw[:-10]}),
        ValueError,
        "examples",
    ),
    raises(
        "example-rig-other-topology",
        lambda c: _auto_rig(c, examples=c.small_rig),
        ValueError,
        "examples",
    ),
    raises(
        "example-nan",
        lambda c: _auto_rig(c, examples={"jawOpen": np.where(np.abs(c.jaw) > 0.5, np.nan, c.jaw)}),
        ValueError,
        "examples",
    ),
    raises("examples-a-list", lambda c: _auto_rig(c, examples=[c.jaw]), TypeError, "examples"),
    raises(
        "head-in-metres",
        lambda c: _auto_rig(c, vertices=c.vertices / 100.0),
        ValueError,
        "vertices",
    ),
    raises(
        "head-in-millimetres",
        lambda c: _auto_rig(c, vertices=c.vertices * 10.0),
        ValueError,
        "vertices",
    ),
    raises("up-without-forward", lambda c: _auto_rig(c, up="+z"), ValueError, "up, forward"),
    raises("forward-without-up", lambda c: _auto_rig(c, forward="-y"), ValueError, "up, forward"),
    raises("unknown-up-axis", lambda c: _auto_rig(c, up="w", forward="-y"), ValueError, "up"),
    raises(
        "same-axis-twice", lambda c: _auto_rig(c, up="+z", forward="-z"), ValueError, "up, forward"
    ),
    raises(
        "landmarks-too-few",
        lambda c: _auto_rig(c, landmarks=np.arange(10)),
        ValueError,
        "landmarks",
    ),
    raises(
        "landmarks-out-of-range",
        lambda c: _auto_rig(c, landmarks=np.arange(68) + len(c.vertices) - 10),
        ValueError,
        "landmarks",
    ),
]


@pytest.mark.parametrize("case", AUTO_RIG)
def test_auto_rig(case, any_head, no_work_reached):
    run_case(case, any_head)
