"""One contract for every auto-rig method (``METHODS``), on a small ICT head (a held-out
identity, decimated to ~1,100 vertices, every part kept): what ``displacements`` returns
(every pose, in centimetres, on the upright head), what ``auto_rig`` makes of it for the head
stored z-up (the rig in the head's own frame: its neutral and faces, the method's shapes
turned with the head, the method's names or ARKit's, exactly the neutral at zero weight,
centimetres), and bad input refused naming the argument before any work.

A new method is tested by adding one instance to ``METHODS``;
``test_every_method_class_is_listed`` fails until it is.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import canrig_jax.autorig._methods as methods_module
from canrig_jax import autorig
from canrig_jax._commands import AUTORIG_METHODS
from canrig_jax.autorig import (
    AbstractAutoRigMethod,
    AbstractNetworkMethod,
    RigAnyFaceNetwork,
    Template,
    Transfer,
    TransferResidual,
    auto_rig,
    ict_pose_source,
)
from canrig_jax.autorig._landmarks import place_landmarks, skin_of
from canrig_jax.autorig._methods import UprightHead
from canrig_jax.autorig._weld import WELD_TAU, clumps, weld
from canrig_jax.data import ARKIT_NAMES, ict_identity, load_ict
from canrig_jax.mesh import decimate
from canrig_jax.rig import BlendshapeRig, evaluate, rename_to_arkit

pytestmark = pytest.mark.filterwarnings(  # the decimated head has 4 non-manifold edges
    "ignore:faces. 0 repeated and 0 degenerate"
)
Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""A y-up head facing +z stored z-up, facing -y (``vertices @ Z_UP.T``)."""
FROM_A_TEMPLATE = "Transfer-from-a-template"
HEAD_VERTICES = 800
"""The decimation target: ~1,100 vertices, all 56 of ICT's parts kept (the contract's
properties do not depend on the size; the operators' dense eigensolve does, cubically)."""

METHODS = (
    Transfer(),
    FROM_A_TEMPLATE,  # Transfer(template=...): Transfer()'s own single shapes as the template
    RigAnyFaceNetwork(),
    TransferResidual(),
)
"""Every method as the contract runs it (the template case is built from the test head)."""


def _id(case) -> str:
    return case if isinstance(case, str) else type(case).__name__


CASES = [pytest.param(case, id=_id(case)) for case in METHODS]


@pytest.fixture(scope="module")
def source():
    return ict_pose_source(progress=False)


@pytest.fixture(scope="module")
def head(data_dir, source):
    """A held-out ICT identity, decimated (cm, +y up, facing +z), its skin and landmarks."""
    ict = load_ict(data_dir, parts=None)
    identity = ict_identity(np.random.default_rng(7).standard_normal(100), data_dir, model=ict)
    mesh = decimate(identity, ict.faces, HEAD_VERTICES)
    vertices = np.asarray(mesh.vertices, np.float32).astype(np.float64)  # float32 exactly
    _, once = np.unique(np.sort(mesh.faces, axis=1), axis=0, return_index=True)
    faces = np.asarray(mesh.faces)[np.sort(once)]  # no repeated triangle (auto_rig drops them)
    skin = skin_of(vertices, faces)
    landmarks, _, _ = place_landmarks(source, vertices, faces, region=skin)
    return UprightHead(vertices, faces, landmarks, skin)


class _Methods:
    """Each case's ``auto_rig`` on the head stored z-up (axes stated; the landmarks given to
    the methods that need them; the method's own names), run once, with what ``auto_rig``
    handed the method's ``displacements`` (the upright head) and what it returned: the
    contract's checks share one run per method. Within these runs the anchored transfer of
    the ICT poses, a pure function of the upright head, is computed once and reused by
    ``TransferResidual`` (the same head: asserted array-equal)."""

    def __init__(self, head, source):
        self.head, self.source, self.runs, self.transfers = head, source, {}, []

    def method(self, case) -> AbstractAutoRigMethod:
        if case != FROM_A_TEMPLATE:
            return case
        displacements, poses, names = self.displacements(Transfer())
        rig = BlendshapeRig(
            self.head.vertices.astype(np.float32),
            np.asarray(displacements[: poses.n_basis], np.float32),
            (),
            names,
            self.head.faces,
        )
        return Transfer(template=Template(rig, self.head.landmarks, "transfer"))

    def _anchored_transfer(self, real):
        def once(dataset, head):
            for seen, done in self.transfers:
                if dataset is self.source and _same_head(seen, head):
                    return done.copy()
            done = real(dataset, head)
            self.transfers.append((head, done.copy()))
            return done

        return once

    def run(self, case):
        """(``auto_rig``'s result, the head its method was given, what the method's
        ``displacements`` returned on it)."""
        if _id(case) not in self.runs:
            method = self.method(case)
            cls, calls = type(method), []
            real = cls.displacements

            def spied(self_, head, dataset):
                out = real(self_, head, dataset)
                calls.append((head, out))
                return out

            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(cls, "displacements", spied)
                patch.setattr(
                    methods_module,
                    "_anchored_transfer",
                    self._anchored_transfer(methods_module._anchored_transfer),
                )
                result = auto_rig(
                    (self.head.vertices @ Z_UP.T).astype(np.float32),
                    self.head.faces,
                    method=method,
                    dataset=self.source,
                    landmarks=self.head.landmarks if method.needs_landmarks else None,
                    up="+z",
                    forward="-y",
                    names="source",
                )
            [(given, out)] = calls  # the method is run once, on one head
            self.runs[_id(case)] = (result, given, out)
        return self.runs[_id(case)]

    def displacements(self, case):
        return self.run(case)[2]


def _same_head(a: UprightHead, b: UprightHead) -> bool:
    return all(
        np.array_equal(x, y) if x is not None and y is not None else x is y
        for x, y in zip(
            (a.vertices, a.faces, a.landmarks, a.skin),
            (b.vertices, b.faces, b.landmarks, b.skin),
            strict=True,
        )
    )


@pytest.fixture(scope="module")
def methods(head, source):
    return _Methods(head, source)


# --- the family --------------------------------------------------------------------------------


def test_every_method_class_is_listed():
    listed = {type(m) for m in METHODS if not isinstance(m, str)}
    assert listed == set(autorig.AUTO_RIG_METHODS)


def test_methods_are_final_subclasses_of_the_abstract_base():
    listed = autorig.AUTO_RIG_METHODS
    for cls in listed:
        assert issubclass(cls, AbstractAutoRigMethod)
        # abstract or final: no listed (concrete) method derives from another listed one
        assert not any(issubclass(cls, other) for other in listed if other is not cls), cls
        assert isinstance(cls.name, str) and isinstance(cls.needs_landmarks, bool)
    assert len({cls.name for cls in listed}) == len(listed)
    assert isinstance(autorig.DEFAULT_METHOD, AbstractAutoRigMethod)


def test_the_command_line_table_names_every_method_by_its_name():
    """``canrig autorig --method NAME``: one table, name -> class, each under its ``name``."""
    classes = {name: getattr(autorig, cls) for name, cls in AUTORIG_METHODS.items()}
    assert set(classes.values()) == set(autorig.AUTO_RIG_METHODS)
    assert all(cls.name == name for name, cls in classes.items())


def test_network_methods_read_their_packaged_checkpoint():
    for cls in autorig.AUTO_RIG_METHODS:
        if issubclass(cls, AbstractNetworkMethod):
            network, poses = cls().network()
            assert bool(network.residual) == cls.residual
            loaded = cls().loaded()
            assert loaded.model[0] is not None and loaded.model[1] == poses


# --- the contract ------------------------------------------------------------------------------


@pytest.mark.parametrize("case", CASES)
def test_displacements_are_every_pose_in_centimetres(case, methods, head, source):
    displacements, poses, names = methods.displacements(case)
    n_poses = len(names) if poses is None else poses.n_poses
    assert displacements.shape == (n_poses, len(head.vertices), 3)
    assert displacements.dtype in (np.float32, np.float64)
    assert np.all(np.isfinite(displacements))
    if poses is not None:
        assert names == poses.basis_names and poses.labels == source.poses.labels
    # centimetres: the jaw opens by about a centimetre or two at the chin
    jaw = np.linalg.norm(displacements[names.index("jawOpen")], axis=-1)
    assert 0.5 < jaw.max() < 5.0, jaw.max()
    assert np.median(jaw) < 0.05 * jaw.max()  # most of the head stays still


@pytest.mark.parametrize("case", CASES)
def test_auto_rig_is_the_methods_rig_in_the_heads_frame(case, methods, head):
    method = methods.method(case)
    result, given, (displacements, poses, names) = methods.run(case)
    rig = result.rig
    # the method ran on the upright head: the test's own, exactly (the landmarks where the
    # method needs them)
    np.testing.assert_array_equal(given.vertices, head.vertices)
    np.testing.assert_array_equal(given.faces, head.faces)
    np.testing.assert_array_equal(given.skin, head.skin)
    if method.needs_landmarks:
        np.testing.assert_array_equal(given.landmarks, head.landmarks)
    else:
        assert given.landmarks is None
    assert result.method == type(method).name
    assert result.orientation.up == "+z" and result.orientation.forward == "-y"
    turned = (head.vertices @ Z_UP.T).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(rig.neutral), turned)
    np.testing.assert_array_equal(np.asarray(rig.faces), head.faces)
    assert rig.units == "cm" and rig.names == names
    assert rig.deltas.shape == (len(names), len(head.vertices), 3)
    # every shape is the method's with its clumps welded, turned with the head (the blinks
    # are closed on the lid)
    labels = clumps(head.vertices, head.faces, head.skin, WELD_TAU)
    welded = weld(np.asarray(displacements, np.float64), labels)
    for i, name in enumerate(names):
        if not name.startswith("eyeBlink"):
            want = welded[i] @ Z_UP.T
            np.testing.assert_allclose(np.asarray(rig.deltas[i]), want, atol=1e-5, err_msg=name)
    # zero weight is the neutral, exactly; combination poses become correctives
    zero = evaluate(rig, jnp.zeros(rig.n_blendshapes))
    np.testing.assert_array_equal(np.asarray(zero), turned)
    assert bool(rig.correctives) == (poses is not None)
    assert (result.landmarks is None) == (not method.needs_landmarks)
    # ARKit names (the default): ICT's halves merged, each name once
    arkit = rename_to_arkit(rig).names
    assert set(arkit) <= set(ARKIT_NAMES) and len(set(arkit)) == len(arkit) >= 50


def test_a_template_on_its_own_head_gives_its_shapes_back(methods):
    own, _, _ = methods.displacements(Transfer())
    carried, poses, names = methods.displacements(FROM_A_TEMPLATE)
    assert poses is None and carried.shape == (len(names), *own.shape[1:])
    np.testing.assert_allclose(carried, own[: len(names)], atol=1e-3)


BAD_METHODS = [
    pytest.param(lambda: Transfer(template="ict"), TypeError, "template", id="Transfer"),
    pytest.param(
        lambda: RigAnyFaceNetwork(model=(None, None)), TypeError, "model", id="RigAnyFaceNetwork"
    ),
    pytest.param(lambda: TransferResidual(model=3), TypeError, "model", id="TransferResidual"),
]


@pytest.mark.bad_input
@pytest.mark.parametrize("build, error, name", BAD_METHODS)
def test_a_method_refuses_bad_fields_naming_them(build, error, name):
    with pytest.raises(error, match=name):
        build()


@pytest.mark.bad_input
@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_refused_naming_it_before_any_work(case, methods, head, monkeypatch):
    """A head in metres, and a method given by its name, are refused naming the argument
    before the method does any work (its work is patched to fail the test)."""
    method = methods.method(case)

    def reached(*args, **kwargs):
        raise AssertionError("the method's work was reached")

    for name in ("_anchored_transfer", "_template_rig", "generate_rig"):
        monkeypatch.setattr(methods_module, name, reached)
    with pytest.raises(ValueError, match="vertices"):
        auto_rig(head.vertices / 100.0, head.faces, method=method)
    with pytest.raises(TypeError, match="method"):
        auto_rig(head.vertices, head.faces, method=type(method).name)
    if isinstance(method, AbstractNetworkMethod):
        with pytest.raises(FileNotFoundError, match="model"):
            type(method)(model="no/such/checkpoint.eqx").network()
