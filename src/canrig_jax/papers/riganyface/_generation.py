"""A generated rig as a product: the time to generate one (cold and warm) and its glTF 2.0
round trip."""

from pathlib import Path

import numpy as np

from ...autorig._data import PoseSet
from ...autorig._model import RigAnyFace
from ...autorig._rig import generate_rig
from ...data import ICTFaceModel
from ...mesh import decimate
from ...rig import BlendshapeRig, export_gltf, load_gltf_rig


def rig_timing(model: RigAnyFace, poses: PoseSet, head: ICTFaceModel, repeats: int = 9) -> dict:
    """Seconds to generate the rig of ``head`` (the generic ICT head: ``neutral``, ``faces``)
    decimated to ~1,750 vertices: cold (the first call: compile + operators + network) and
    warm (the median over ``repeats`` calls, alternating two triangulations of similar size
    so no operator is reused), with the warm operators, network and orientation parts."""
    if repeats < 1:
        raise ValueError(f"repeats: expected >= 1, got {repeats}")
    timing_head = decimate(head.neutral, head.faces, 1600)
    timing_other = decimate(head.neutral, head.faces, 1620)
    cold = generate_rig(model, poses, timing_head.vertices, timing_head.faces)  # compile + ops
    warm = [
        generate_rig(model, poses, mesh.vertices, mesh.faces).seconds
        for mesh in [timing_other, timing_head] * (repeats // 2) + [timing_head]
    ]
    return {
        "vertices": timing_head.n_vertices,
        "poses": poses.n_poses,
        "cold": cold.seconds["total"],
        "warm": float(np.median([w["total"] for w in warm])),
        "warm_operators": float(np.median([w["operators"] for w in warm])),
        "warm_network": float(np.median([w["network"] for w in warm])),
        "warm_orientation": float(np.median([w.get("orientation", 0.0) for w in warm])),
        "warm_repeats": len(warm),
    }


def gltf_round_trip(rig: BlendshapeRig, path: str | Path) -> dict:
    """Export ``rig`` as glTF 2.0 to ``path`` (``export_gltf``) and read it back
    (``load_gltf_rig``): the file's name, its morph targets (blendshapes and corrective
    terms), the largest absolute difference of neutral, deltas and dense correctives after
    the reload (the rig's units), and whether the names and faces came back equal."""
    path = Path(path)
    export_gltf(rig, path)
    reloaded = load_gltf_rig(path)
    differences = [
        np.abs(np.asarray(reloaded.neutral) - np.asarray(rig.neutral)).max(),
        np.abs(np.asarray(reloaded.deltas) - np.asarray(rig.deltas)).max(),
        *(
            np.abs(
                np.asarray(a.to_dense(rig.n_vertices)) - np.asarray(b.to_dense(rig.n_vertices))
            ).max()
            for a, b in zip(reloaded.correctives, rig.correctives, strict=True)
        ),
    ]
    return {
        "file": path.name,
        "morph_targets": len(reloaded.names)
        + sum(c.indices.shape[0] for c in reloaded.correctives),
        "max_abs_difference_cm": float(max(differences)),
        "names_equal": tuple(reloaded.names) == tuple(rig.names),
        "faces_equal": bool(np.array_equal(np.asarray(reloaded.faces), np.asarray(rig.faces))),
    }
