"""A blendshape rig as UsdSkel blend shapes, and a take as a SkelAnimation (usd-core, optional).

``export_usd(rig, path)`` writes one skinned mesh under a ``SkelRoot``: the neutral as the
mesh's points (the rig's units, ``metersPerUnit`` set from them, y up), one ``BlendShape`` per
blendshape with its ``offsets`` and ``pointIndices`` (only the vertices it moves), bound with
``skel:blendShapes`` / ``skel:blendShapeTargets``, a one-joint ``Skeleton`` the mesh is fully
weighted to, and, given ``weights``, a ``SkelAnimation`` with the blend-shape weights at each
time (``timeCodesPerSecond`` = fps). UsdSkel blend shapes are linear: the rig's correctives are
not written. ``load_usd_rig`` reads one back (through usd-core) as a ``BlendshapeRig``.

usd-core is an optional extra: ``pip install "canrig_jax[usd]"`` (or ``pip install usd-core``).
"""

import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float, Float32

from .._io import atomic_path, check_output_path
from ._blendshape import BlendshapeRig

USD_SUFFIXES = (".usda", ".usdc", ".usd")
_METRES = {"mm": 0.001, "cm": 0.01, "dm": 0.1, "m": 1.0}
_IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt
    except ImportError as error:
        raise ImportError(
            f"USD output needs usd-core ({error}): pip install usd-core (the [usd] extra)"
        ) from error
    return Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt


def export_usd(
    rig: BlendshapeRig,
    path: str | os.PathLike,
    *,
    weights: Float[ArrayLike, "T K"] | None = None,
    fps: float = 60.0,
    times: Float[ArrayLike, " T"] | None = None,
) -> Path:
    """Write ``rig`` (and, with ``weights``, its animation) as UsdSkel, atomically.

    Args:
        rig: a rig with faces; its blendshape names must be USD identifiers (ARKit's are).
        path: a ``.usda`` (text), ``.usdc`` or ``.usd`` (binary) file.
        weights: (T, K) blend-shape weights over time (``canrig animate -o OUT.usda``).
        fps: the time codes per second; times: (T,) seconds of each frame (default: T frames
            ``1/fps`` apart).
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    target = check_output_path(path)
    if target.suffix.lower() not in USD_SUFFIXES:
        raise ValueError(f"path: expected one of {USD_SUFFIXES}, got {target.name}")
    if rig.faces is None:
        raise ValueError("rig: USD export needs a rig with faces")
    bad = [n for n in rig.names if not _IDENTIFIER.match(n)]
    if bad:
        raise ValueError(f"rig: blendshape names must be USD identifiers, not {bad[:5]}")
    frames = None
    if weights is not None:
        frames = np.asarray(weights, np.float64)
        if frames.ndim != 2 or frames.shape[1] != rig.n_blendshapes:
            raise ValueError(f"weights: expected (T, {rig.n_blendshapes}), got {frames.shape}")
        if not np.all(np.isfinite(frames)):
            raise ValueError("weights: contains non-finite values")
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps: expected a positive frame rate, got {fps}")
        seconds = np.arange(len(frames)) / fps if times is None else np.asarray(times, float)
        if seconds.shape != (len(frames),):
            raise ValueError(f"times: expected ({len(frames)},) seconds")
    _pxr()  # usd-core is there, before anything is written
    with atomic_path(target) as tmp:
        layer_path = tmp.with_suffix(target.suffix)  # USD picks the format from the suffix
        try:
            _write_stage(rig, layer_path, frames, seconds if frames is not None else None, fps)
            os.replace(layer_path, tmp)
        finally:
            if layer_path.exists():
                layer_path.unlink()
    return target


def _write_stage(rig: BlendshapeRig, layer_path: Path, frames, seconds, fps) -> None:
    Gf, _, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    stage = Usd.Stage.CreateNew(str(layer_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, _METRES.get(rig.units, 0.01))
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())
    skeleton = UsdSkel.Skeleton.Define(stage, "/Rig/Skeleton")
    skeleton.CreateJointsAttr(Vt.TokenArray(["root"]))
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Face")
    neutral = np.asarray(rig.neutral, np.float32)
    faces = np.asarray(rig.faces, np.int32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(neutral))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    deltas = np.asarray(rig.deltas, np.float32)
    targets = []
    for name, delta in zip(rig.names, deltas, strict=True):
        moved = np.flatnonzero(np.any(delta != 0, axis=1)).astype(np.int32)
        shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(name))
        shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(delta[moved])))
        shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved))
        targets.append(shape.GetPath())
    binding.CreateBlendShapesAttr(Vt.TokenArray(list(rig.names)))
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    if frames is not None:
        _add_animation(stage, skeleton, rig.names, frames, seconds, fps)
    stage.GetRootLayer().Save()


def _add_animation(stage, skeleton, names: Sequence[str], frames, seconds, fps) -> None:
    _, _, _, _, UsdSkel, Vt = _pxr()
    animation = UsdSkel.Animation.Define(stage, skeleton.GetPath().AppendChild("Take"))
    animation.CreateJointsAttr(Vt.TokenArray(["root"]))
    animation.CreateBlendShapesAttr(Vt.TokenArray(list(names)))
    attribute = animation.CreateBlendShapeWeightsAttr()
    for second, row in zip(seconds, frames, strict=True):
        attribute.Set(Vt.FloatArray.FromNumpy(row.astype(np.float32)), float(second * fps))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()]
    )
    stage.SetTimeCodesPerSecond(fps)
    stage.SetStartTimeCode(float(seconds[0] * fps))
    stage.SetEndTimeCode(float(seconds[-1] * fps))


def load_usd_rig(
    path: str | os.PathLike,
) -> tuple[BlendshapeRig, Float32[np.ndarray, "T K"] | None]:
    """(the rig, the (T, K) animation weights or None) of a file ``export_usd`` wrote, read
    through usd-core's UsdSkel API."""
    _, _, Usd, UsdGeom, UsdSkel, _ = _pxr()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: USD file {path} not found")
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Rig/Face"))
    neutral = np.asarray(mesh.GetPointsAttr().Get(), np.float32)
    faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), np.int32).reshape(-1, 3)
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    names = [str(n) for n in binding.GetBlendShapesAttr().Get()]
    deltas = np.zeros((len(names), len(neutral), 3), np.float32)
    for k, target in enumerate(binding.GetBlendShapeTargetsRel().GetTargets()):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(target))
        index = np.asarray(shape.GetPointIndicesAttr().Get(), np.int64)
        deltas[k, index] = np.asarray(shape.GetOffsetsAttr().Get(), np.float32)
    units = {v: k for k, v in _METRES.items()}.get(UsdGeom.GetStageMetersPerUnit(stage), "cm")
    rig = BlendshapeRig(neutral, deltas, (), tuple(names), faces, units=units)
    animation = stage.GetPrimAtPath("/Rig/Skeleton/Take")
    if not animation.IsValid():
        return rig, None
    attribute = UsdSkel.Animation(animation).GetBlendShapeWeightsAttr()
    samples = attribute.GetTimeSamples()
    return rig, np.stack([np.asarray(attribute.Get(t), np.float32) for t in samples])
