"""ICT loaders against the npz extraction, ICT-FaceKit's raw OBJ files and NumPy references."""

from __future__ import annotations

import io
import json
import os
import warnings

import numpy as np
import pytest
import trimesh

import canrig_jax.data._paths as paths_module  # patched: the default folder
from canrig_jax.data import FACE, ict_identity, load_ict, load_ict_obj_folder
from canrig_jax.data._ict import ICT_PARTS, load_identity_modes
from canrig_jax.data._paths import ENV_VAR, resolve_data_dir

RAW = "ict-facekit/raw"


@pytest.fixture(scope="module")
def npz(data_dir):
    with np.load(data_dir / "ict-facekit/expressions.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def head(data_dir):
    return load_ict(data_dir)


@pytest.fixture(scope="module")
def raw_model(data_dir):
    return load_ict_obj_folder(data_dir / RAW)


def _triangle_set(faces):
    return {tuple(t) for t in np.sort(np.asarray(faces), axis=1).tolist()}


# --- load_ict_obj_folder ------------------------------------------------------------------


def test_obj_folder_default_names_are_the_present_objs_in_json_order(raw_model):
    assert raw_model.names == ("jawOpen", "mouthSmile_L")
    assert raw_model.deltas.shape == (2, 26719, 3)


def test_obj_folder_geometry_matches_npz(raw_model, npz):
    np.testing.assert_allclose(raw_model.neutral, npz["neutral"], rtol=0, atol=1e-5)
    for k, name in enumerate(raw_model.names):
        i = list(npz["names"]).index(name)
        np.testing.assert_allclose(raw_model.deltas[k], npz["deltas"][i], rtol=0, atol=1e-5)
    assert np.linalg.norm(raw_model.deltas[0], axis=1).max() > 4.0  # jawOpen: chin ~4.2 cm


def test_obj_folder_faces_match_npz_and_trimesh(raw_model, npz, data_dir):
    assert raw_model.faces.shape == (52220, 3)
    assert _triangle_set(raw_model.faces) == _triangle_set(npz["faces"])
    np.testing.assert_array_equal(raw_model.faces, npz["faces"])  # same fan order too
    # trimesh's own triangulation of the per-material groups covers the same triangles
    text = (data_dir / RAW / "generic_neutral_mesh.obj").read_text()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        groups = trimesh.exchange.obj.load_obj(
            io.StringIO(text), maintain_order=True, skip_materials=True, group_material=False
        )["geometry"].values()
    tris = []
    for g in groups:
        f = np.asarray(g["faces"])
        tris.append(f if f.shape[1] == 3 else np.concatenate([f[:, [0, 1, 2]], f[:, [2, 3, 0]]]))
    assert _triangle_set(np.concatenate(tris)) == _triangle_set(raw_model.faces)


def test_obj_folder_parts_components_landmarks(raw_model, npz, data_dir):
    assert raw_model.part_names == tuple(str(n) for n in npz["part_names"])
    np.testing.assert_array_equal(raw_model.part_vertex_range, npz["part_vertex_range"])
    assert [[n, a, b] for n, a, b in ICT_PARTS] == json.loads(
        (data_dir / "ict-facekit/expressions.json").read_text()
    )["parts_from_README"]
    labels, ref = raw_model.component_labels, npz["component_labels"]
    n_comp = len(np.unique(ref))
    assert n_comp == 56 and len(np.unique(labels)) == n_comp
    assert len(set(zip(labels.tolist(), ref.tolist(), strict=True))) == n_comp  # same partition
    np.testing.assert_array_equal(raw_model.landmarks, npz["landmarks_multipie68"])


def test_obj_folder_names_and_errors(data_dir, tmp_path):
    raw = data_dir / RAW
    for f in ("generic_neutral_mesh.obj", "vertex_indices.json", "mouthSmile_L.obj"):
        os.symlink(raw / f, tmp_path / f)
    model = load_ict_obj_folder(tmp_path)
    assert model.names == ("mouthSmile_L",)
    with pytest.raises(FileNotFoundError, match="jawOpen"):
        load_ict_obj_folder(tmp_path, names=["mouthSmile_L", "jawOpen"])
    (tmp_path / "jawOpen.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="jawOpen"):
        load_ict_obj_folder(tmp_path, names=["jawOpen"])
    with pytest.raises(FileNotFoundError, match="folder"):
        load_ict_obj_folder(tmp_path / "absent")
    (tmp_path / "vertex_indices.json").unlink()
    with pytest.raises(FileNotFoundError, match="vertex_indices.json"):
        load_ict_obj_folder(tmp_path)


# --- load_ict part selection ---------------------------------------------------------------


def test_face_part(data_dir, head):
    face = load_ict(data_dir, parts=FACE)
    assert face.neutral.shape == (9409, 3) and face.deltas.shape == (53, 9409, 3)
    assert face.faces.min() >= 0 and face.faces.max() < 9409
    np.testing.assert_array_equal(face.neutral, head.neutral[:9409])
    kept = head.faces[np.all(head.faces < 9409, axis=1)]  # independent filter
    np.testing.assert_array_equal(face.faces, kept)
    ok = face.landmarks >= 0
    np.testing.assert_array_equal(face.vertex_ids[face.landmarks[ok]], head.landmarks[ok])


def test_two_parts_keep_model_order(data_dir, head):
    two = load_ict(data_dir, parts=["Eyeball left", "Face"])
    assert two.part_names == ("Face", "Eyeball left")
    ids = np.concatenate([np.arange(0, 9409), np.arange(21451, 23021)])
    np.testing.assert_array_equal(two.vertex_ids, ids)
    np.testing.assert_array_equal(two.neutral, head.neutral[ids])
    np.testing.assert_array_equal(two.deltas, head.deltas[:, ids])
    np.testing.assert_array_equal(two.part_vertex_range, [[0, 9409], [9409, 10979]])
    assert two.faces.min() >= 0 and two.faces.max() < 10979
    remapped = {tuple(t) for t in np.sort(two.vertex_ids[two.faces], axis=1).tolist()}
    ref = head.faces[np.all(np.isin(head.faces, ids), axis=1)]
    assert remapped == _triangle_set(ref)


def test_unknown_part_raises(data_dir):
    with pytest.raises(ValueError, match="Nose"):
        load_ict(data_dir, parts=["Face", "Nose"])


def test_part_mask_is_the_parts_vertex_ranges(data_dir, head):
    mask = head.part_mask(["Teeth", "Face"])
    selected = load_ict(data_dir, parts=["Face", "Teeth"])
    np.testing.assert_array_equal(np.flatnonzero(mask), selected.vertex_ids)
    np.testing.assert_array_equal(head.part_mask("Face"), np.arange(head.n_vertices) < 9409)
    with pytest.raises(ValueError, match="--attach: unknown part name.*Nose"):
        head.part_mask(["Face", "Nose"], argument="--attach")
    with pytest.raises(ValueError, match="parts: expected at least one"):
        head.part_mask([])


# --- ict_identity ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def modes(data_dir):
    return load_identity_modes(data_dir)


def test_identity_zero_is_neutral(data_dir, head):
    np.testing.assert_array_equal(ict_identity(np.zeros(100), data_dir, model=head), head.neutral)


def test_identity_linear_against_tensordot(data_dir, head, modes):
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal(10), rng.standard_normal(10)
    ref = head.neutral.astype(np.float64) + np.tensordot(a, modes[:10].astype(np.float64), 1)
    got = ict_identity(a, data_dir, model=head)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)
    sum_ab = ict_identity(a + b, data_dir, model=head) - head.neutral
    parts = (got - head.neutral) + (ict_identity(b, data_dir, model=head) - head.neutral)
    np.testing.assert_allclose(sum_ab, parts, rtol=0, atol=1e-5)
    face = head.select(FACE)
    np.testing.assert_allclose(ict_identity(a, data_dir, model=face), got[:9409], atol=1e-6)


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "bad", [np.zeros((2, 3)), np.zeros(0), np.zeros(101), np.array([0.0, np.nan])]
)
def test_identity_rejects_bad_coefficients(data_dir, head, bad):
    with pytest.raises(ValueError, match="coefficients"):
        ict_identity(bad, data_dir, model=head)


# --- resolve_data_dir ---------------------------------------------------------------------


def test_argument_wins_over_env(monkeypatch, tmp_path):
    arg, env = tmp_path / "arg", tmp_path / "env"
    arg.mkdir()
    env.mkdir()
    monkeypatch.setenv(ENV_VAR, str(env))
    assert resolve_data_dir(arg) == arg
    assert resolve_data_dir() == env


def test_env_wins_over_default(monkeypatch, tmp_path):
    monkeypatch.setattr(paths_module, "DEFAULT_DATA_DIR", tmp_path / "default")
    (tmp_path / "default").mkdir()
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert resolve_data_dir() == tmp_path / "default"
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    assert resolve_data_dir() == tmp_path


def test_missing_folder_message_names_all_three(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError) as info:
        resolve_data_dir()
    message = str(info.value)
    for expected in ("data_dir", "CANRIG_DATA", "../shared/data", "nowhere"):
        assert expected in message
    with pytest.raises(FileNotFoundError, match="argument"):
        resolve_data_dir(tmp_path / "missing")
