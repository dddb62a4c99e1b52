"""Any head to an ARKit rig (``auto_rig``): the artist's ``Style`` and its fit, the head's
orientation decided or refused (never wrong), and one Rocketbox head rigged end to end in its
own (z-up) frame."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.autorig import (
    OrientationError,
    RigAnyFaceNetwork,
    Style,
    Template,
    Transfer,
    auto_rig,
    fit_style,
    ict_pose_source,
    load_makehuman,
)
from canrig_jax.autorig._evaluation import sculpted_target_errors
from canrig_jax.autorig._landmarks import skin_of
from canrig_jax.autorig._orientation import (
    CUE_MARGIN_CM,
    axis_rotations,
    decide_orientation,
    face_cues,
    stated_orientation,
)
from canrig_jax.autorig._style import STYLE_GRID
from canrig_jax.autorig._weld import WELD_TAU, clumps, weld
from canrig_jax.data import ARKIT_NAMES, FACE, load_ict
from canrig_jax.rig import BlendshapeRig

HEADS = ("Male_Adult_08", "Female_Adult_01")
MIRROR = np.diag([-1.0, 1.0, 1.0])
Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""A y-up head facing +z turned z-up, facing -y (``vertices @ Z_UP.T``)."""
EXAMPLES = ("jawOpen", "mouthSmileLeft", "eyeBlinkLeft")


@pytest.fixture(scope="module")
def source():
    """The ICT pose source, shared by every test of the module (a few seconds, cached)."""
    return ict_pose_source(progress=False)


def _rocketbox(data_dir, name: str):
    head = np.load(data_dir / "rocketbox" / f"{name}_head.npz")
    return {
        "vertices": head["neutral"].astype(np.float64),
        "faces": head["faces"].astype(np.int64),
        "deltas": head["deltas"].astype(np.float64),
        "names": [str(n) for n in head["names"]],
        "skin": head["component_labels"] == 0,
    }


def _face_crop(vertices, faces):
    """The front of a head (y up, facing +z): z within the front 45 % of its depth and y in
    the upper 75 % of its height; the faces wholly inside, re-indexed, unused vertices
    dropped."""
    z, y = vertices[:, 2], vertices[:, 1]
    keep = (z > z.max() - 0.45 * np.ptp(z)) & (y > y.min() + 0.25 * np.ptp(y))
    inside = faces[keep[faces].all(axis=1)]
    used = np.unique(inside)
    index = np.full(len(vertices), -1)
    index[used] = np.arange(used.size)
    return vertices[used], index[inside]


@pytest.fixture(scope="module")
def heads(data_dir):
    """The two Rocketbox heads and a face crop of the first (y up, facing +z, cm)."""
    out = {}
    for name in HEADS:
        head = _rocketbox(data_dir, name)
        out[name] = (head["vertices"], head["faces"])
    out["crop"] = _face_crop(*out[HEADS[0]])
    assert out["crop"][0].shape[0] < 0.7 * out[HEADS[0]][0].shape[0]
    return out


# --- Style ------------------------------------------------------------------------------------


def _poses(seed: int = 0, p: int = 3, v: int = 300) -> np.ndarray:
    """(P, V, 3) displacements with lengths spread over two decades."""
    rng = np.random.default_rng(seed)
    direction = rng.standard_normal((p, v, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    return direction * rng.uniform(0.01, 1.0, (p, v, 1)) ** 2


def test_default_style_is_the_identity():
    d = _poses()
    np.testing.assert_allclose(Style().apply(d), d, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("falloff, floor", [(0.0, 0.0), (1.0, 0.2), (2.0, 0.5)])
def test_style_gain_scales_linearly(falloff, floor):
    d = _poses(1)
    one = Style(1.0, falloff, floor).apply(d)
    assert np.abs(one).max() > 0.1
    for gain in (0.3, 1.5):
        np.testing.assert_allclose(
            Style(gain, falloff, floor).apply(d), gain * one, rtol=1e-5, atol=1e-7
        )


@pytest.mark.parametrize(
    "gain, falloff, floor", [(1.0, 0.0, 0.0), (0.7, 1.0, 0.3), (1.3, 2.0, 0.6)]
)
def test_style_keeps_each_pose_peak_and_zeroes_below_the_floor(gain, falloff, floor):
    d = _poses(2)
    d[1] *= 10.0  # poses of different sizes: the peak and floor are per pose
    out = Style(gain, falloff, floor).apply(d)
    length = np.sqrt((d**2).sum(axis=-1))
    out_length = np.sqrt((out.astype(np.float64) ** 2).sum(axis=-1))
    for pose in range(d.shape[0]):
        peak_vertex = int(np.argmax(length[pose]))
        peak = length[pose, peak_vertex]
        np.testing.assert_allclose(
            out_length[pose, peak_vertex], gain * peak * (1 - floor), rtol=1e-5
        )
        below = length[pose] < floor * peak
        assert np.all(out[pose, below] == 0.0)
        # every displacement keeps its direction (a non-negative multiple of itself)
        dot = (out[pose] * d[pose]).sum(axis=-1)
        assert np.all(dot >= -1e-7)
        np.testing.assert_allclose(
            out_length[pose] * length[pose], np.abs(dot), rtol=1e-4, atol=1e-9
        )


def test_style_closed_form_on_a_line():
    """Lengths 1, 0.5, 0.1 (peak 1), gain 2, falloff 1, floor 0.2: lengths 2 * 1 * 0.8,
    2 * 0.5 * 0.5 * 0.6 and 0 (below the floor)."""
    d = np.array([[[1.0, 0, 0], [0, 0.5, 0], [0, 0, -0.1]]])
    out = Style(2.0, 1.0, 0.2).apply(d)
    np.testing.assert_allclose(out[0], [[1.6, 0, 0], [0, 0.3, 0], [0, 0, 0]], atol=1e-6)


def test_style_of_a_still_pose_is_still():
    d = np.zeros((2, 5, 3))
    d[1, 2] = [0.0, 1.0, 0.0]
    out = Style(1.2, 1.0, 0.3).apply(d)
    assert np.all(np.isfinite(out))
    assert np.all(out[0] == 0.0)
    np.testing.assert_allclose(out[1, 2], [0.0, 1.2 * 0.7, 0.0], rtol=1e-6)


@pytest.mark.parametrize(
    "gain, falloff, floor",
    [
        (STYLE_GRID["gain"][10], 0.0, 0.0),
        (STYLE_GRID["gain"][3], 0.5, 0.2),
        (STYLE_GRID["gain"][20], 2.0, 0.6),
        (STYLE_GRID["gain"][14], 1.0, 0.4),
    ],
)
def test_fit_style_recovers_a_grid_style(gain, falloff, floor):
    generated = _poses(4, p=3, v=400)
    sculpted = Style(float(gain), falloff, floor).apply(generated)
    skin = np.ones(400, bool)
    skin[::7] = False
    found = fit_style(generated, sculpted, skin)
    np.testing.assert_allclose(found.apply(generated), sculpted, rtol=1e-5, atol=1e-6)
    assert (found.falloff, found.floor) == (falloff, floor)
    assert found.gain == pytest.approx(float(gain))


@pytest.mark.bad_input
def test_fit_style_shape_errors_name_the_arguments():
    generated = _poses(5, p=2, v=50)
    with pytest.raises(ValueError, match="generated, sculpted"):
        fit_style(generated, generated[:1], np.ones(50, bool))
    with pytest.raises(ValueError, match="generated, sculpted"):
        fit_style(generated[0], generated[0], np.ones(50, bool))
    with pytest.raises(ValueError, match="skin"):
        fit_style(generated, generated, np.ones(49, bool))
    with pytest.raises(ValueError, match="sculpted"):
        fit_style(generated, np.zeros_like(generated), np.ones(50, bool))


# --- orientation ------------------------------------------------------------------------------


def _turned(vertices, faces, index: int, mirrored: bool):
    """The head turned by ``axis_rotations()[index]`` (then mirrored x -> -x, faces
    reversed), and the proper rotation ``decision.rotation @ (mirror) @ turn`` must equal."""
    turn = axis_rotations()[index]
    moved = vertices @ turn.T
    if mirrored:
        return moved @ MIRROR, faces[:, ::-1], turn, MIRROR
    return moved, faces, turn, np.eye(3)


def _decided_or_refused(source, vertices, faces, index: int, mirrored: bool) -> bool:
    """Asserts the decision undoes the turn (True), or is refused (False); never wrong."""
    moved, moved_faces, turn, mirror = _turned(vertices, faces, index, mirrored)
    try:
        decision = decide_orientation(source, moved, moved_faces)
    except OrientationError as refusal:
        assert "vertices" in str(refusal)
        return False
    # the mirror of an upright head is upright: the decision turns it back upright
    np.testing.assert_allclose(decision.rotation @ mirror @ turn, mirror, atol=1e-9)
    assert decision.source == "fitted"
    return True


SAMPLE = [
    (HEADS[0], 0, False),
    (HEADS[0], 5, False),
    (HEADS[0], 11, True),
    (HEADS[1], 17, False),
    (HEADS[1], 3, True),
    (HEADS[1], 22, True),
    ("crop", 8, False),
    ("crop", 14, True),
]


@pytest.mark.parametrize("head, index, mirrored", SAMPLE)
def test_orientation_is_recovered_never_wrong(source, heads, head, index, mirrored):
    decided = _decided_or_refused(source, *heads[head], index, mirrored)
    if head != "crop":
        assert decided, "a plain Rocketbox head was refused"


@pytest.fixture(scope="module")
def ict_face_mask(data_dir):
    """The ICT face part alone (no back of the head, no neck): a face-only mask, cm."""
    face = load_ict(data_dir, parts=FACE)
    return face.neutral.astype(np.float64), face.faces.astype(np.int64)


TIES = [("ict", 0, False), ("ict", 9, True), ("crop", 2, False), ("crop", 20, True)]


@pytest.mark.parametrize("head, index, mirrored", TIES)
def test_a_tie_on_a_face_mask_is_settled_by_the_faces_own_cues(
    source, heads, ict_face_mask, monkeypatch, head, index, mirrored
):
    """With every refined rotation counted as fitting "almost equally" (``AGREE_RATIO``
    raised), the face's cues alone pick the one upright orientation of a face-only mask."""
    monkeypatch.setattr("canrig_jax.autorig._orientation.AGREE_RATIO", 1e9)
    vertices, faces = ict_face_mask if head == "ict" else heads[head]
    moved, moved_faces, turn, mirror = _turned(vertices, faces, index, mirrored)
    decision = decide_orientation(source, moved, moved_faces)
    np.testing.assert_allclose(decision.rotation @ mirror @ turn, mirror, atol=1e-9)
    assert decision.fit["settled_by"] == "face cues"
    forward, up = face_cues(vertices, np.eye(3))  # upright: both cues clear the margin
    assert min(forward, up) > CUE_MARGIN_CM
    upside_down = np.diag([-1.0, -1.0, 1.0])
    assert face_cues(vertices, upside_down)[1] < -CUE_MARGIN_CM
    assert face_cues(vertices, np.diag([-1.0, 1.0, -1.0]))[0] < -CUE_MARGIN_CM  # from behind


def test_a_tie_the_cues_cannot_settle_is_refused(source, ict_face_mask, monkeypatch):
    """Where no tied orientation shows both cues (an up cue of 0, as of a mask cut at the
    nose), the tie stays a refusal naming up= and forward=; a planed-down nose is refused too
    (the ICT face no longer fits it)."""
    monkeypatch.setattr("canrig_jax.autorig._orientation.AGREE_RATIO", 1e9)
    vertices, faces = ict_face_mask
    monkeypatch.setattr(
        "canrig_jax.autorig._orientation.face_cues",
        lambda vertices, to_convention: (face_cues(vertices, to_convention)[0], 0.0),
    )
    with pytest.raises(OrientationError, match="do not settle it.*up= and forward="):
        decide_orientation(source, vertices, faces)
    flat = vertices.copy()
    outer = np.abs(flat[:, 0] - np.median(flat[:, 0])) > 0.3 * np.ptp(flat[:, 0])
    flat[:, 2] = np.minimum(flat[:, 2], flat[outer, 2].max())
    with pytest.raises(OrientationError, match="up= and forward="):
        decide_orientation(source, flat, faces)


@pytest.mark.slow  # 48 orientations x 3 heads, ~1 s each
@pytest.mark.parametrize("head", [*HEADS, "crop"])
def test_every_orientation_and_mirror_is_recovered_or_refused(source, heads, head):
    decided = [
        _decided_or_refused(source, *heads[head], index, mirrored)
        for mirrored in (False, True)
        for index in range(len(axis_rotations()))
    ]
    if head != "crop":
        assert all(decided)


@pytest.mark.slow  # 48 orientations, ~1 s each
def test_makehuman_head_every_orientation_and_mirror_is_recovered(source, data_dir):
    """An evaluation head of another style (MakeHuman; no threshold is tuned on it)."""
    head = load_makehuman(data_dir)
    vertices, faces = head.neutral.astype(np.float64), head.faces.astype(np.int64)
    for mirrored in (False, True):
        for index in range(len(axis_rotations())):
            assert _decided_or_refused(source, vertices, faces, index, mirrored)


def _about_vertical(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_a_head_turned_off_the_axes_is_refused_or_snapped_to_the_nearest(source, heads):
    vertices, faces = heads[HEADS[0]]
    with pytest.raises(OrientationError, match="vertices"):
        decide_orientation(source, vertices @ _about_vertical(30.0).T, faces)
    # a few degrees off: the nearest axis-aligned orientation (here upright already)
    decision = decide_orientation(source, vertices @ _about_vertical(10.0).T, faces)
    np.testing.assert_allclose(decision.rotation, np.eye(3))
    assert decision.fit["off_axis_degrees"] == pytest.approx(10.0, abs=3.0)


def test_axis_rotations_are_the_24_proper_axis_permutations():
    rotations = axis_rotations()
    assert rotations.shape == (24, 3, 3)
    assert len({r.tobytes() for r in rotations}) == 24
    for r in rotations:
        np.testing.assert_allclose(r @ r.T, np.eye(3))
        assert np.linalg.det(r) == pytest.approx(1.0)
        assert np.all(np.sort(np.abs(r), axis=None) == [0] * 6 + [1] * 3)


def test_stated_orientation_turns_a_z_up_head_facing_minus_y_upright():
    decision = stated_orientation("+z", "-y")
    r = decision.rotation
    np.testing.assert_allclose(r @ [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])  # its up -> +y
    np.testing.assert_allclose(r @ [0.0, -1.0, 0.0], [0.0, 0.0, 1.0])  # its forward -> +z
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ Z_UP, np.eye(3))  # undoes the turn the tests store with
    assert (decision.up, decision.forward, decision.source) == ("+z", "-y", "stated")
    assert stated_orientation("y", "+z").conventional


@pytest.mark.parametrize(
    "up, forward, names",
    [
        ("w", "+z", "up"),
        ("+y", "+q", "forward"),
        ("+y", "++z", "forward"),
        ("+z", "-z", "up, forward"),
    ],
)
def test_stated_orientation_bad_axes_name_the_argument(up, forward, names):
    with pytest.raises(ValueError, match=names):
        stated_orientation(up, forward)


def test_decide_orientation_needs_both_axes_or_neither(source, heads):
    vertices, faces = heads[HEADS[0]]
    for up, forward in (("+y", None), (None, "+z")):
        with pytest.raises(ValueError, match="up, forward"):
            decide_orientation(source, vertices, faces, up=up, forward=forward)
    stated = decide_orientation(source, vertices @ Z_UP.T, faces, up="+z", forward="-y")
    np.testing.assert_allclose(stated.rotation, stated_orientation("+z", "-y").rotation)


def test_a_sphere_is_refused(source):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4)
    with pytest.raises(OrientationError, match="vertices"):
        decide_orientation(source, sphere.vertices * 10.0, sphere.faces)  # 20 cm across


# --- auto_rig end to end on a z-up Rocketbox head ----------------------------------------------


@pytest.fixture(scope="module")
def z_up_head(data_dir):
    head = _rocketbox(data_dir, HEADS[0])
    head["vertices"] = head["vertices"] @ Z_UP.T
    head["deltas"] = head["deltas"] @ Z_UP.T
    head["examples"] = {n: head["deltas"][head["names"].index(n)] for n in EXAMPLES}
    return head


@pytest.fixture(scope="module")
def plain_rig(source, z_up_head):
    """k = 0: template transfer (no network to compile), orientation and landmarks found."""
    return auto_rig(z_up_head["vertices"], z_up_head["faces"], method=Transfer(), dataset=source)


@pytest.fixture(scope="module")
def styled_rig(source, z_up_head, plain_rig):
    """k = 3 examples (the orientation and landmarks of the k = 0 run reused)."""
    return auto_rig(
        z_up_head["vertices"],
        z_up_head["faces"],
        method=Transfer(),
        dataset=source,
        examples=z_up_head["examples"],
        orientation=plain_rig.orientation,
        landmarks=plain_rig.landmarks,
    )


def _shape(rig, name: str) -> np.ndarray:
    return np.asarray(rig.deltas[rig.names.index(name)], np.float64)


def test_auto_rig_is_in_the_heads_own_frame_with_arkit_names(plain_rig, z_up_head):
    rig = plain_rig.rig
    assert plain_rig.method == "transfer"
    np.testing.assert_allclose(plain_rig.orientation.rotation @ Z_UP, np.eye(3), atol=1e-9)
    np.testing.assert_array_equal(np.asarray(rig.neutral), z_up_head["vertices"].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(rig.faces), z_up_head["faces"])
    assert rig.units == "cm"
    assert set(rig.names) <= set(ARKIT_NAMES) and len(set(rig.names)) == len(rig.names) == 51
    assert plain_rig.style == Style()
    assert plain_rig.landmarks.shape == (68,)


def test_jaw_opens_down_in_the_heads_frame_and_moves_the_lower_face(plain_rig, z_up_head):
    jaw = _shape(plain_rig.rig, "jawOpen")
    skin = z_up_head["skin"]
    mean = jaw[skin].mean(axis=0)
    assert mean[2] < 0 and abs(mean[2]) > np.abs(mean[:2]).max()  # down is -z on this head
    length = np.linalg.norm(jaw, axis=1)
    height = z_up_head["vertices"][:, 2]
    lower = skin & (height < np.median(height[skin]))
    upper = skin & ~lower
    assert length[lower].mean() > 3 * length[upper].mean()


def test_examples_are_taken_and_their_style_improves_the_other_shapes(
    plain_rig, styled_rig, z_up_head
):
    for name in EXAMPLES:
        np.testing.assert_array_equal(
            _shape(styled_rig.rig, name), z_up_head["examples"][name].astype(np.float32)
        )
    assert set(styled_rig.examples) == set(EXAMPLES)
    assert styled_rig.style != Style()
    others = [n for n in styled_rig.rig.names if n in z_up_head["names"] and n not in EXAMPLES]
    assert len(others) == 48
    truth = np.stack([z_up_head["deltas"][z_up_head["names"].index(n)] for n in others])
    skin = z_up_head["skin"]

    def error(result):
        predicted = np.stack([_shape(result.rig, n) for n in others])
        return sculpted_target_errors(predicted, truth, skin)["skin_mae_mm"]

    assert error(styled_rig) < error(plain_rig)
    # the style is applied to every pose, not only the examples: the other shapes changed
    assert not np.allclose(
        _shape(styled_rig.rig, "browDownLeft"), _shape(plain_rig.rig, "browDownLeft")
    )


@pytest.mark.slow
def test_examples_are_taken_under_the_sources_names_too(source, z_up_head, plain_rig):
    result = auto_rig(
        z_up_head["vertices"],
        z_up_head["faces"],
        dataset=source,
        examples=z_up_head["examples"],
        orientation=plain_rig.orientation,
        landmarks=plain_rig.landmarks,
        names="source",
    )
    assert "eyeBlink_L" in result.rig.names and "browInnerUp_L" in result.rig.names
    for source_name, arkit in (("eyeBlink_L", "eyeBlinkLeft"), ("mouthSmile_L", "mouthSmileLeft")):
        np.testing.assert_array_equal(
            _shape(result.rig, source_name), z_up_head["examples"][arkit].astype(np.float32)
        )


def test_a_template_carried_onto_its_own_head_gives_its_shapes_back(
    source, z_up_head, plain_rig, data_dir
):
    """The Rocketbox rig as a ``Template`` (y up; some of its 68 landmarks share a vertex on
    this coarse mesh) carried onto the same head stored z-up: every shape comes back turned,
    and examples sculpted as generated fit the identity style."""
    upright = np.load(data_dir / "rocketbox" / f"{HEADS[0]}_head.npz")
    names = tuple(z_up_head["names"])
    rig = BlendshapeRig(upright["neutral"], upright["deltas"], (), names, upright["faces"])
    landmarks = plain_rig.landmarks  # the same topology: the head's landmarks are the template's
    assert np.unique(landmarks).size < 68
    result = auto_rig(
        z_up_head["vertices"],
        z_up_head["faces"],
        dataset=source,
        method=Transfer(template=Template(rig, landmarks, "rocketbox")),
        landmarks=landmarks,
        up="+z",
        forward="-y",
        examples=z_up_head["examples"],
    )
    assert result.rig.names == names  # ARKit already, tongueOut kept
    assert result.orientation.source == "stated"
    assert result.style == Style()
    got = np.asarray(result.rig.deltas, np.float64)
    # the template's own shapes, with the head's clumps moving as one (``_weld``)
    skin = skin_of(z_up_head["vertices"], z_up_head["faces"])
    labels = clumps(z_up_head["vertices"], z_up_head["faces"], skin, WELD_TAU)
    want = weld(z_up_head["deltas"], labels)
    for name in z_up_head["examples"]:  # the examples are taken as sculpted
        want[names.index(name)] = z_up_head["deltas"][names.index(name)]
    error = np.linalg.norm(got - want, axis=-1).max(axis=1)
    peak = np.linalg.norm(want, axis=-1).max(axis=1)
    # the blinks are closed on the lid (close_blinks may scale the welded blink), as in the
    # method contract (tests/autorig/test_methods.py)
    bad = [(n, e, p) for n, e, p in zip(names, error, peak, strict=True)
           if e > 0.05 * p + 1e-4 and not n.startswith("eyeBlink")]  # fmt: skip
    assert not bad, bad


def test_the_packaged_orientation_template_is_the_ict_inner_face(source):
    """The points packaged for ``decide_orientation`` are the ones computed from the data
    folder's ICT head (so a wheel without the data decides alike)."""
    from canrig_jax.autorig._orientation import orientation_points

    np.testing.assert_array_equal(orientation_points(), orientation_points(source))


@pytest.mark.slow
def test_raf_runs_without_the_data_folder(z_up_head, monkeypatch):
    """The network method needs neither the ICT source rig nor the landmark fit: with both
    made to fail, it still decides the orientation (packaged template) and builds the rig
    in the head's own frame."""
    from canrig_jax.autorig import _any_head, _data

    def unavailable(*args, **kwargs):
        raise AssertionError("the data folder was read")

    monkeypatch.setattr(_data, "ict_pose_source", unavailable)
    monkeypatch.setattr(_any_head, "place_landmarks", unavailable)
    result = auto_rig(z_up_head["vertices"], z_up_head["faces"], method=RigAnyFaceNetwork())
    assert result.orientation.up == "+z" and result.orientation.forward == "-y"
    assert result.landmarks is None and result.rig.n_blendshapes == 51
    np.testing.assert_array_equal(result.rig.neutral, np.float32(z_up_head["vertices"]))
    jaw = _shape(result.rig, "jawOpen")
    assert jaw[:, 2].sum() < 0  # the jaw drops along the head's own down (-z)


def test_repeated_and_degenerate_triangles_are_left_out_and_stated(heads):
    """A head with garbage triangles (each of 20 repeated, 40 with a corner twice, 10 fins on
    an existing edge): the rig's mesh is the head's own triangles and the fins (kept, named as
    non-manifold edges), and the warning says how many of each."""
    from canrig_jax.autorig._any_head import _without_defects

    vertices, faces = heads[HEADS[1]]
    rng = np.random.default_rng(0)
    pick = rng.choice(len(faces), 40, replace=False)
    fins = np.c_[faces[pick[:10], :2], rng.choice(len(vertices), 10)]
    garbage = np.vstack([faces, faces[pick[:20]][:, ::-1], faces[pick][:, [0, 0, 1]], fins])
    with pytest.warns(UserWarning, match=r"20 repeated and 40 degenerate.*non-manifold"):
        kept = _without_defects(vertices, garbage)
    expected = np.vstack([faces, fins])
    assert {tuple(f) for f in kept} == {tuple(f) for f in expected}
    assert len(kept) == len(expected)
