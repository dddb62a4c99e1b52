"""An artist's style as amplitude and locality (``Style``), fitted to k of the head's own
sculpted ARKit shapes (``fit_style``) and applied to every pose the method generated
(``style_from_examples``: one step of ``auto_rig``)."""

import dataclasses
from collections.abc import Mapping

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Float32

from ..rig import arkit_channels


@dataclasses.dataclass(frozen=True)
class Style:
    """An artist's style as amplitude and locality, applied per pose: each vertex's
    displacement d of length |d| (pose peak p) becomes

        gain * d * (|d| / p) ** falloff * max(0, 1 - floor * p / |d|),

    so ``falloff`` > 0 keeps the peak and thins the tails, ``floor`` zeroes what moves less
    than that fraction of the peak (soft threshold). ``Style()`` is the identity."""

    gain: float = 1.0
    falloff: float = 0.0
    floor: float = 0.0

    def apply(self, displacements: Float[ArrayLike, "P V 3"]) -> Float32[np.ndarray, "P V 3"]:
        """(P, V, 3) displacements -> the same, styled (float32)."""
        d = np.asarray(displacements, np.float64)
        length = np.linalg.norm(d, axis=-1, keepdims=True)
        peak = length.max(axis=1, keepdims=True)
        safe_peak, safe = np.maximum(peak, 1e-12), np.maximum(length, 1e-12)
        factor = (length / safe_peak) ** self.falloff
        factor = factor * np.maximum(0.0, 1.0 - self.floor * peak / safe)
        return (self.gain * d * factor).astype(np.float32)


STYLE_GRID = {
    "falloff": (0.0, 0.5, 1.0, 2.0),
    "floor": (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7),
    "gain": tuple(np.round(np.linspace(0.3, 1.5, 25), 3)),
}
"""The styles ``fit_style`` chooses among (fixed before any measurement on evaluation
heads)."""


def fit_style(
    generated: Float[ArrayLike, "k V 3"],
    sculpted: Float[ArrayLike, "k V 3"],
    skin: Bool[ArrayLike, " V"],
) -> Style:
    """The style whose generated shapes best match the artist's, among ``STYLE_GRID``'s (4
    falloffs, 8 floors and 25 gains from 0.3 to 1.5, fixed before any measurement on evaluation
    heads).

    Args:
        generated: (k, V, 3) the method's version of the k example shapes (cm).
        sculpted: (k, V, 3) the artist's shapes (cm).
        skin: (V,) bool, the vertices scored (the head's skin).

    The score is the mean over the k shapes of each shape's skin error over what no motion
    scores on it, so a small shape (a blink) counts as much as a large one (jawOpen)."""
    generated = np.asarray(generated, np.float64)
    sculpted = np.asarray(sculpted, np.float64)
    if generated.shape != sculpted.shape or generated.ndim != 3 or generated.shape[0] < 1:
        raise ValueError(
            f"generated, sculpted: expected two (k >= 1, V, 3) arrays, got {generated.shape} "
            f"and {sculpted.shape}"
        )
    skin = np.asarray(skin, bool)
    if skin.shape != generated.shape[1:2] or not skin.any():
        raise ValueError(
            f"skin: expected ({generated.shape[1]},) bools with at least one True, got {skin.shape}"
        )
    still = np.linalg.norm(sculpted, axis=-1)[:, skin].mean(axis=1)
    if not np.all(still > 0):
        raise ValueError("sculpted: an example shape does not move the skin")
    best, best_score = Style(), np.inf
    for falloff in STYLE_GRID["falloff"]:
        for floor in STYLE_GRID["floor"]:
            shaped = Style(1.0, falloff, floor).apply(generated).astype(np.float64)
            for gain in STYLE_GRID["gain"]:
                error = np.linalg.norm(gain * shaped - sculpted, axis=-1)[:, skin].mean(axis=1)
                score = float(np.mean(error / still))
                if score < best_score:
                    best, best_score = Style(float(gain), falloff, floor), score
    return best


def _shapes_by_arkit(displacements, source_names, wanted: Mapping, rotation):
    """The method's version of each wanted ARKit shape in the head's frame (ICT's halves
    summed, as ``rename_to_arkit`` merges them): (names, (k, V, 3)); names the method lacks
    are left out."""
    channels, index = arkit_channels(source_names)  # the single poses come first
    singles = np.asarray(displacements, np.float64)[: len(source_names)]
    merged = np.zeros((len(channels), *singles.shape[1:]))
    np.add.at(merged, index, singles)
    kept = tuple(n for n in wanted if n in channels)
    if not kept:
        raise ValueError(
            f"examples: none of {sorted(wanted)} is a shape of the generated rig "
            f"({', '.join(sorted(channels)[:6])}, ...)"
        )
    return kept, np.stack([merged[channels.index(n)] @ rotation for n in kept])


def style_from_examples(
    displacements: Float[ArrayLike, "P V 3"],
    source_names: tuple[str, ...],
    sculpted: Mapping[str, Float[np.ndarray, "V 3"]],
    rotation: Float[ArrayLike, "3 3"],
    skin: Bool[ArrayLike, " V"],
) -> tuple[Style, Float32[np.ndarray, "P V 3"]]:
    """The ``Style`` fitted to the example shapes ``sculpted`` ({ARKit name: (V, 3) cm, in the
    head's own frame}) and the method's (P, V, 3) upright ``displacements`` (cm) styled by it.
    ``rotation`` turns the head's frame into the upright one; ``skin``: the vertices scored."""
    kept, generated = _shapes_by_arkit(displacements, source_names, sculpted, rotation)
    style = fit_style(generated, np.stack([sculpted[n] for n in kept]), skin)
    return style, style.apply(displacements)
