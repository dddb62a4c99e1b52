"""A rig's blendshapes under ARKit's names: what three.js, Ready Player Me, VRM "perfect sync"
and Live Link consumers map morph targets by (``eyeBlinkLeft``, not ICT's ``eyeBlink_L``).

ICT splits ``browInnerUp`` and ``cheekPuff`` into ``_L``/``_R`` halves; ARKit drives each as
one channel. Renaming therefore merges the halves: the ARKit shape is their sum, which is what
the ICT rig shows with both halves at the same weight."""

from collections.abc import Sequence

import numpy as np
from jaxtyping import Int64

from ..data import arkit_name_of
from ._blendshape import BlendshapeRig, Corrective


def arkit_channels(names: Sequence[str]) -> tuple[list[str], Int64[np.ndarray, " K"]]:
    """The ARKit channel of each name, in first-seen order, and (K,) the channel index of
    each input name (several names may share one: ICT's halves)."""
    channels: list[str] = []
    index = np.empty(len(names), np.int64)
    for i, name in enumerate(names):
        arkit = arkit_name_of(str(name)) or str(name)  # unknown names are kept
        if arkit not in channels:
            channels.append(arkit)
        index[i] = channels.index(arkit)
    return channels, index


def rename_to_arkit(rig: BlendshapeRig) -> BlendshapeRig:
    """The same rig with one blendshape per ARKit channel, named in ARKit's camelCase.

    Names of no ARKit shape (``arkit_name_of`` gives None: visemes, FACS units) are kept
    as they are. Shapes that share a channel (ICT's
    ``browInnerUp_L``/``_R``) are summed, so weight w on the channel gives what the source
    rig gives with w on each of them. Correctives follow their drivers; two correctives on
    the same channels are summed; a corrective driven by both halves of one channel (w_L w_R
    becomes w^2 on one channel, which a rig of distinct drivers cannot hold) is folded onto
    the remaining distinct drivers — exact at channel weights 0 and 1, the weights a capture
    spends most time near, and an approximation (w instead of w^2) between.

    Returns a new rig (same neutral, faces and units); a rig already in ARKit names comes back
    equal to itself."""
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    channels, index = arkit_channels(rig.names)
    n_vertices = int(rig.neutral.shape[0])
    deltas = np.zeros((len(channels), n_vertices, 3), np.float32)
    np.add.at(deltas, index, np.asarray(rig.deltas, np.float32))
    terms: dict[tuple[int, ...], np.ndarray] = {}
    for table in rig.correctives:
        dense = table.to_dense(n_vertices)
        for drivers, offsets in zip(np.asarray(table.indices), dense, strict=True):
            key = tuple(sorted({int(index[d]) for d in drivers}))
            if len(key) == 1:  # every driver on one channel: the product is that weight
                deltas[key[0]] += offsets
            elif key in terms:
                terms[key] = terms[key] + offsets
            else:
                terms[key] = offsets
    by_order: dict[int, list[tuple[int, ...]]] = {}
    for key in terms:
        by_order.setdefault(len(key), []).append(key)
    correctives = tuple(
        Corrective.from_dense(np.asarray(keys), np.stack([terms[k] for k in keys]))
        for _, keys in sorted(by_order.items())
    )
    return BlendshapeRig(
        np.asarray(rig.neutral),
        deltas,
        correctives,
        tuple(channels),
        None if rig.faces is None else np.asarray(rig.faces),
        rig.units,
    )
