"""Orientation of a head: found from its shape, refused or fixed by the network
(``RigAnyFaceNetwork.generate``)."""

from __future__ import annotations

import itertools

import jax
import numpy as np
import pytest

from canrig_jax.autorig import RigAnyFaceNetwork, head_orientation, load_makehuman
from canrig_jax.autorig._data import PoseSet
from canrig_jax.autorig._model import RigAnyFace
from canrig_jax.data import ict_identity, load_ict
from canrig_jax.mesh import connected_components, decimate


def _proper_rotations() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[range(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def _about(axis: int, degrees: int) -> np.ndarray:
    c, s = np.round(np.cos(np.radians(degrees))), np.round(np.sin(np.radians(degrees)))
    i, j = [a for a in range(3) if a != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


TURNS = [(axis, degrees) for axis in range(3) for degrees in (90, 180, 270)]


@pytest.fixture(scope="module")
def ict_heads(data_dir):
    """The generic ICT head and a new identity, decimated (~1,750 and ~1,080 vertices)."""
    head = load_ict(data_dir, parts=None)
    identity = ict_identity(np.random.default_rng(11).standard_normal(100), data_dir, model=head)
    return {
        "generic": decimate(head.neutral, head.faces, 1600),
        "identity": decimate(identity, head.faces, 800),
    }


@pytest.fixture(scope="module")
def model_and_poses():
    poses = PoseSet(("a", "b", "c"), ((0,), (1,), (2,), (0, 1)))
    model = RigAnyFace(3, width=8, global_size=4, global_width=8, key=jax.random.PRNGKey(1))
    return model, poses


@pytest.mark.parametrize("name", ["generic", "identity"])
def test_every_axis_aligned_turn_of_an_ict_head_is_found(ict_heads, name):
    mesh = ict_heads[name]
    found = head_orientation(mesh.vertices, mesh.faces)
    assert found.conventional and not found.contradicts
    for r in _proper_rotations():
        turned = head_orientation(mesh.vertices @ r.T, mesh.faces)
        # the rotation found takes the turned head back to the stored one
        np.testing.assert_array_equal(turned.rotation @ r, np.eye(3))
        assert turned.contradicts == (not np.array_equal(r, np.eye(3)))


def test_makehuman_head_passes_as_it_is_stored(data_dir):
    """Evaluation only: the MakeHuman head (shoulders, 6 parts) is y up, facing +z."""
    mh = load_makehuman(data_dir)
    found = head_orientation(mh.neutral, mh.faces)
    assert found.conventional, found.describe()


@pytest.fixture(scope="module")
def upright_rig(ict_heads, model_and_poses):
    model, poses = model_and_poses
    mesh = ict_heads["identity"]
    return RigAnyFaceNetwork((model, poses)).generate(mesh.vertices, mesh.faces, k=128)


@pytest.mark.parametrize("axis, degrees", TURNS)
def test_the_network_refuses_a_turned_head(ict_heads, model_and_poses, upright_rig, axis, degrees):
    model, poses = model_and_poses
    mesh = ict_heads["identity"]
    assert not upright_rig.rotated and upright_rig.orientation.conventional
    turned = mesh.vertices @ _about(axis, degrees).T
    with pytest.raises(ValueError, match="vertices: the head seems to face") as error:
        RigAnyFaceNetwork((model, poses)).generate(turned, mesh.faces, k=128)
    assert "facing" in str(error.value) and "orientation='fix'" in str(error.value)


@pytest.mark.parametrize("axis, degrees", [(0, 90), (1, 180), (2, 270)])
def test_orientation_fix_gives_the_same_rig_turned(
    ict_heads, model_and_poses, upright_rig, axis, degrees
):
    model, poses = model_and_poses
    mesh = ict_heads["identity"]
    r = _about(axis, degrees)
    turned = (mesh.vertices @ r.T).astype(np.float32)
    fixed = RigAnyFaceNetwork((model, poses)).generate(turned, mesh.faces, k=128, orientation="fix")
    assert fixed.rotated
    # the same rig, turned: displacements rotate with the head, the neutral is as given
    np.testing.assert_allclose(fixed.displacements, upright_rig.displacements @ r.T, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(fixed.rig.neutral), turned)
    if (axis, degrees) == (1, 180):  # "trust" runs the model on the turned head: another rig
        trusted = RigAnyFaceNetwork((model, poses)).generate(
            turned, mesh.faces, k=128, orientation="trust"
        )
        assert np.abs(trusted.displacements - fixed.displacements).max() > 1e-4


def test_inconclusive_heads_pass_and_a_partly_known_turn_is_not_fixed(
    ict_heads, model_and_poses, data_dir
):
    model, poses = model_and_poses
    head = load_ict(data_dir, parts=None)
    face = np.arange(head.n_vertices) < head.part_vertex_range[0, 1]  # the face part only
    keep = face[head.faces].all(axis=1)
    mask = decimate(head.neutral[face], head.faces[keep], 1000)
    found = head_orientation(mask.vertices, mask.faces)
    # a face-only mask: left-right and forward are clear, up is not (no neck cut)
    assert (found.lateral, found.forward, found.up) == ("x", "+z", None)
    RigAnyFaceNetwork((model, poses)).generate(mask.vertices, mask.faces, k=128)  # passes the check
    turned = mask.vertices @ _about(2, 90).T
    with pytest.raises(ValueError, match="vertices: .*only partly determined"):
        RigAnyFaceNetwork((model, poses)).generate(turned, mask.faces, k=128, orientation="fix")
    # a sphere has no cue: undetermined, let through
    sphere = np.random.default_rng(0).standard_normal((200, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    from scipy.spatial import ConvexHull

    hull = ConvexHull(sphere)
    assert not head_orientation(sphere, hull.simplices).determined


def test_orientation_check_searches_a_bounded_subsample(ict_heads, monkeypatch):
    """The check stays cheap on any head: its one nearest-neighbour search (the symmetry cue)
    builds one k-d tree on at most ``max_points`` vertices and queries it once per axis with
    as many points; everything else is a linear pass. (Its time, against the operators' on
    the same head: ``benchmarks/bench_autorig.py``.)"""
    import canrig_jax.autorig._orientation as orientation_module  # patched: the k-d tree

    built, queried = [], []
    real = orientation_module.KDTree

    class CountingTree:
        def __init__(self, points, *args, **kwargs):
            built.append(len(points))
            self.tree = real(points, *args, **kwargs)

        def query(self, points, *args, **kwargs):
            queried.append(len(points))
            return self.tree.query(points, *args, **kwargs)

    monkeypatch.setattr(orientation_module, "KDTree", CountingTree)
    mesh = ict_heads["generic"]
    skin = np.bincount(connected_components(mesh.faces, mesh.n_vertices)).max()
    assert skin > 600
    head_orientation(mesh.vertices, mesh.faces)
    assert built == [skin] and queried == [skin] * 3  # the whole skin: under 4000 points
    built.clear(), queried.clear()
    head_orientation(mesh.vertices, mesh.faces, max_points=300)
    assert len(built) == 1 and 150 < built[0] <= 300
    assert queried == built * 3


def test_a_head_with_weak_cues_is_let_through_not_refused(data_dir):
    """Held-out identity 4 of the experiment (its lips stand out about as far as its nose):
    the forward cue is too weak, so the check lets it through, whole and cut below the chin
    (an earlier, looser margin refused the cut head as facing -z)."""
    from scipy.spatial import cKDTree

    head = load_ict(data_dir, parts=None)
    rng = np.random.default_rng([0, 1])  # the experiment's held-out stream
    coefficients = [rng.standard_normal(100) for _ in range(5)][-1]
    neutral = ict_identity(coefficients, data_dir, model=head)
    mesh = decimate(neutral, head.faces, 1300)
    v, f = mesh.vertices, mesh.faces
    chin = v[cKDTree(v).query(neutral[head.landmarks[8]])[1], 1]
    keep = (v[f][:, :, 1] > chin - 1.0).all(axis=1)
    kept = np.zeros(len(v), bool)
    kept[f[keep]] = True
    cut = (v[kept], (np.cumsum(kept) - 1)[f[keep]])
    for vertices, faces in ((v, f), cut):
        found = head_orientation(vertices, faces)
        assert not found.contradicts and found.lateral == "x", found.describe()


@pytest.mark.slow  # two trimmed-ICP fits, ~12 s
def test_face_placement_does_not_move_with_the_crop(ict_heads, data_dir):
    """The placement from a fit of the ICT face: on the generic head it is the bounding-box
    placement the model was trained with; cutting the neck off changes the box by > 20 %
    and the face placement by < 1 %."""
    from canrig_jax.autorig._data import AutorigDataset, face_placement
    from canrig_jax.autorig._model import normalise

    head = load_ict(data_dir, parts=None)
    dataset = AutorigDataset(None, head, None, [], {})  # face_placement uses the head only
    mesh = ict_heads["generic"]
    v, f = mesh.vertices, mesh.faces
    centre, scale = face_placement(dataset, v, f)
    _, box_centre, box_scale = normalise(v)
    assert abs(scale / box_scale - 1) < 0.01 and np.linalg.norm(centre - box_centre) < 0.2
    chin = head.neutral[head.landmarks[8], 1]
    keep = (v[f][:, :, 1] > chin - 1.0).all(axis=1)
    kept = np.zeros(len(v), bool)
    kept[f[keep]] = True
    cut_v, cut_f = v[kept], (np.cumsum(kept) - 1)[f[keep]]
    cut_centre, cut_scale = face_placement(dataset, cut_v, cut_f)
    assert abs(normalise(cut_v)[2] / box_scale - 1) > 0.2
    assert abs(cut_scale / scale - 1) < 0.01 and np.linalg.norm(cut_centre - centre) < 0.2
