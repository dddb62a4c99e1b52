"""A Live Link Face capture (LLV example ``dao.gesichter``, BSD-2-Clause): 52 ARKit
blendshape weights plus head and eye rotations per frame, 60 fps."""

import dataclasses
import os
from collections.abc import Sequence

import numpy as np
from jaxtyping import Float, Float32, Int

from .._warnings import warn
from ._names import retarget_weights
from ._paths import data_file, read_arrays


@dataclasses.dataclass(frozen=True)
class LiveLinkCapture:
    """Per-frame ARKit weights and head/eye rotations of one capture.

    Attributes:
        weights: (T, 52) float32 blendshape weights, unitless, 0..1.
        names: 52 channel names in Unreal's ``EARFaceBlendShape`` order (``EyeBlinkLeft``).
        head_eye_rotations: (T, 9) float32 head and eye yaw/pitch/roll as the app records
            them (|value| < 0.5 here; the source does not state units).
        rotation_names: the 9 rotation channel names (``HeadYaw``, ..., ``RightEyeRoll``).
        frame_number: (T,) int64 timecode frame numbers; they can jump (gaps).
        fps: frames per second of the timecode.
        sub_frame: (T,) fraction of a frame of each timecode (None when unknown).
        blendshape_count: the ``BlendShapeCount`` column of a Live Link Face CSV (None when
            the capture did not come from one).
    """

    weights: Float32[np.ndarray, "T K"]
    names: tuple[str, ...]
    head_eye_rotations: Float32[np.ndarray, "T R"]
    rotation_names: tuple[str, ...]
    frame_number: Int[np.ndarray, " T"]
    fps: float
    sub_frame: Float[np.ndarray, " T"] | None = None
    blendshape_count: int | None = None

    @property
    def n_frames(self) -> int:
        return int(self.weights.shape[0])

    def weights_for(
        self, target_names: Sequence[str], missing: str = "raise"
    ) -> Float32[np.ndarray, "T K"]:
        """(T, K) float32 weights for a rig with channels ``target_names``, matched by ARKit
        name through ``retarget_weights`` (which warns about the take's channels the rig does
        not read). With ``missing="zero"``, the rig's channels the take lacks get weight 0 and
        are named in a warning; ``missing="raise"`` makes them an error."""
        out, report = retarget_weights(self.weights, self.names, target_names, missing=missing)
        if report.missing_target:
            absent = list(report.missing_target)
            warn(
                f"the take has no channel for {len(absent)} of the rig's "
                f"{len(target_names)} shapes, which stay at weight 0: {absent}",
            )
        return out


def load_livelinkface(data_dir: str | os.PathLike | None = None) -> LiveLinkCapture:
    """Load ``livelinkface/dao_livelinkface.npz``: 180 frames at 60 fps (3 s).

    Args:
        data_dir: data folder (else ``$CANRIG_DATA``, else ``../shared/data``).
    """
    path = data_file("livelinkface/dao_livelinkface.npz", data_dir)
    z = read_arrays(
        path,
        (
            "anim_weights",
            "names",
            "head_eye_rotations",
            "rotation_names",
            "frame_number",
            "sub_frame",
            "fps",
        ),
    )
    return LiveLinkCapture(
        weights=z["anim_weights"].astype(np.float32),
        names=tuple(str(n) for n in z["names"]),
        head_eye_rotations=z["head_eye_rotations"].astype(np.float32),
        rotation_names=tuple(str(n) for n in z["rotation_names"]),
        frame_number=z["frame_number"].astype(np.int64),
        fps=float(z["fps"]),
        sub_frame=z["sub_frame"].astype(np.float64),
    )
