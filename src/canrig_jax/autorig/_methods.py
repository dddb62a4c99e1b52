"""The auto-rig methods, one family: what ``auto_rig(vertices, faces, method=...)`` runs.

A method is a small, immutable ``eqx.Module`` (its template or network are fields). ``auto_rig``
takes the steps every method shares — the head's orientation decided or refused, the ICT
landmarks placed when the method ``needs_landmarks``, the artist's style fitted, the blinks
closed, ARKit names — and asks the method for one thing: ``displacements(head, dataset)``, the
(P, V, 3) displacement of every pose on the head turned into the convention (centimetres, +y up,
facing +z). Concrete methods are final (never subclassed); the two network methods share their
code through ``AbstractNetworkMethod``, the one door to the RigAnyFace network (``generate``).

- ``Transfer()``: template transfer — the template's expressions carried onto the head by
  anchored deformation transfer (Sumner & Popović 2004; per pose, the vertices whose carried
  displacement is below ``ANCHOR_CM`` stay still). The template is the ICT rig with its
  combination poses (correctives) unless a ``Template`` of the user's is given.
- ``RigAnyFaceNetwork()``: RigAnyFace (Ma et al. 2025), the packaged default network.
- ``TransferResidual()``: anchored transfer plus a RigAnyFace residual trained on it.
"""

import abc
import dataclasses
import os
from pathlib import Path
from typing import ClassVar, NamedTuple

import equinox as eqx
import numpy as np
from equinox import AbstractClassVar, AbstractVar
from jaxtyping import ArrayLike, Bool, Float, Int

from .._metrics import CM_TO_MM
from ..mesh import MeshOperators, closest_point_correspondence
from ..rig import UNIT_IN_CM, BlendshapeRig, deformation_transfer
from ._data import AutorigDataset, PoseSet, head_correspondence, transfer_poses
from ._evaluation import STATIC_MM
from ._landmarks import place_landmarks
from ._model import RigAnyFace
from ._rig import DEFAULT_MEMORY_BUDGET, DEFAULT_POSE_CHUNK, GeneratedRig, generate_rig
from ._train import DEFAULT_CHECKPOINT, RESIDUAL_CHECKPOINT, load_riganyface

ANCHOR_CM = STATIC_MM / CM_TO_MM
"""Anchored transfer: per pose, target vertices whose carried displacement is shorter than
this (0.01 mm, the evaluation's static threshold) stay exactly still."""


@dataclasses.dataclass(frozen=True)
class UprightHead:
    """What ``auto_rig`` hands a method: the head turned into the convention.

    Attributes:
        vertices: (V, 3) float64, centimetres, +y up, facing +z; faces: (F, 3) triangles.
        landmarks: (68,) the ICT Multi-PIE landmarks on the head (None when the method
            does not ``needs_landmarks`` and none were given).
        skin: (V,) bool, the head's largest component (``skin_of``).
    """

    vertices: Float[np.ndarray, "V 3"]
    faces: Int[np.ndarray, "F 3"]
    landmarks: Int[np.ndarray, " L"] | None
    skin: Bool[np.ndarray, " V"]


class PoseDisplacements(NamedTuple):
    """What a method returns: every pose on the upright head.

    Attributes:
        displacements: (P, V, 3) centimetres, in the convention's frame (float32 or float64,
            as the method computes them).
        poses: the ``PoseSet`` (the first A poses single shapes, the rest combinations that
            become correctives), or None for a linear rig of ``names`` (P = A).
        names: the A single shapes' names in the method's own convention (ICT's
            ``browDown_L``, or a template's).
    """

    displacements: Float[np.ndarray, "P V 3"]
    poses: PoseSet | None
    names: tuple[str, ...]


class AbstractAutoRigMethod(eqx.Module):
    """An auto-rig method: the displacement of every pose on an upright head.

    Attributes:
        name: class constant, the method's name in results and on the command line
            (``canrig autorig --method NAME``).
        needs_landmarks: class constant: True when the method places the ICT landmarks on
            the head (and so reads the ICT source, ``dataset``); False when it runs from the
            package alone.
    """

    name: AbstractClassVar[str]
    needs_landmarks: AbstractClassVar[bool]

    @abc.abstractmethod
    def displacements(self, head: UprightHead, dataset: AutorigDataset | None) -> PoseDisplacements:
        """Every pose on ``head`` (centimetres, the convention's frame). ``dataset``: the ICT
        source (None only for a method that does not ``needs_landmarks``)."""

    def loaded(self) -> "AbstractAutoRigMethod":
        """This method with what it reads from disk read once (a network's checkpoint), for
        many heads (``auto_rig_heads``); the default: the method itself."""
        return self


@dataclasses.dataclass(frozen=True)
class Template:
    """A rig to carry onto new heads (``Transfer(template=...)``): in centimetres, +y up,
    facing +z, with faces.

    Attributes:
        rig: the ``BlendshapeRig`` (linear: correctives are not carried).
        landmarks: (68,) its vertices at the ICT Multi-PIE landmarks (``from_rig`` fits them).
        name: shown in messages and results.
    """

    rig: BlendshapeRig
    landmarks: Int[np.ndarray, " L"]
    name: str = "template"

    @classmethod
    def from_rig(
        cls, dataset: AutorigDataset, rig: BlendshapeRig, name: str = "template"
    ) -> "Template":
        """A template from any rig with faces (cm, +y up, facing +z): its landmarks are
        fitted like a head's (``place_landmarks``)."""
        if not isinstance(rig, BlendshapeRig):
            raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
        if rig.faces is None:
            raise ValueError("rig: a template needs faces (a mesh), this rig has none")
        vertices = np.asarray(rig.neutral, np.float64) * UNIT_IN_CM[rig.units]
        landmarks, _, _ = place_landmarks(dataset, vertices, np.asarray(rig.faces))
        return cls(rig, landmarks, name)


class Transfer(AbstractAutoRigMethod):
    """Template transfer: the ICT template's expressions and combination poses (or a
    ``Template``'s shapes, a linear rig) carried onto the head by anchored deformation
    transfer (``ANCHOR_CM``). The default method (``DEFAULT_METHOD``).

    Attributes:
        template: the ``Template`` to carry from (None: the ICT source, ``dataset``).
    """

    template: Template | None = None
    name: ClassVar[str] = "transfer"
    needs_landmarks: ClassVar[bool] = True

    def __check_init__(self):
        if self.template is not None and not isinstance(self.template, Template):
            raise TypeError(
                f"template: expected a Template (Template.from_rig), got "
                f"{type(self.template).__name__}"
            )

    def displacements(self, head: UprightHead, dataset: AutorigDataset | None) -> PoseDisplacements:
        if self.template is not None:
            carried = _template_rig(self.template, head)
            return PoseDisplacements(
                np.asarray(carried.deltas, np.float64), None, tuple(carried.names)
            )
        if dataset is None:
            raise ValueError("dataset: template transfer carries the ICT source's poses")
        return PoseDisplacements(
            _anchored_transfer(dataset, head), dataset.poses, tuple(dataset.poses.basis_names)
        )


NetworkModel = tuple[RigAnyFace, PoseSet] | str | os.PathLike | None
"""A network method's ``model``: a loaded ``(RigAnyFace, PoseSet)`` (``load_riganyface(path)[:2]``),
a checkpoint's path, or None for the packaged model."""


class AbstractNetworkMethod(AbstractAutoRigMethod):
    """A method that runs the RigAnyFace network; ``generate`` is the network's one door.

    Attributes:
        model: ``(RigAnyFace, PoseSet)``, a checkpoint path, or None (``checkpoint``).
        checkpoint: class constant, the packaged model of the method.
        residual: class constant: True when the network predicts a correction on top of
            anchored transfer (the model's own ``residual`` must agree).
    """

    model: AbstractVar[NetworkModel]
    checkpoint: AbstractClassVar[Path]
    residual: AbstractClassVar[bool]

    def __check_init__(self):
        model = self.model
        if model is None or isinstance(model, str | os.PathLike):
            return
        if not (isinstance(model, tuple) and len(model) == 2):
            raise TypeError(
                f"model: expected (RigAnyFace, PoseSet), a checkpoint path or None, got "
                f"{type(model).__name__}"
            )
        network, poses = model
        if not isinstance(network, RigAnyFace):
            raise TypeError(f"model: expected (RigAnyFace, PoseSet), got {type(network).__name__}")
        if not isinstance(poses, PoseSet):
            raise TypeError(f"model: expected (RigAnyFace, PoseSet), got {type(poses).__name__}")
        self._check_residual(network)

    def _check_residual(self, network: RigAnyFace) -> None:
        if bool(network.residual) != self.residual:
            want = "TransferResidual" if network.residual else "RigAnyFaceNetwork"
            kind = "a residual (on transfer)" if network.residual else "a plain"
            raise ValueError(
                f"model: {kind} RigAnyFace network belongs to autorig.{want}, not "
                f"{type(self).__name__}"
            )

    def network(self) -> tuple[RigAnyFace, PoseSet]:
        """The ``(RigAnyFace, PoseSet)`` this method runs (read from its checkpoint unless
        given loaded)."""
        if isinstance(self.model, tuple):
            return self.model
        path = Path(self.checkpoint if self.model is None else self.model)
        if not path.is_file():
            raise FileNotFoundError(f"model: RigAnyFace checkpoint {path} not found")
        network, poses, _ = load_riganyface(path)
        self._check_residual(network)
        return network, poses

    def loaded(self) -> "AbstractNetworkMethod":
        return dataclasses.replace(self, model=self.network())

    def generate(
        self,
        vertices: Float[ArrayLike, "V 3"],
        faces: Int[ArrayLike, "F 3"],
        *,
        k: int = 128,
        operators: MeshOperators | None = None,
        cache: str | os.PathLike | bool | None = False,
        memory_budget: int = DEFAULT_MEMORY_BUDGET,
        bucket: int = 256,
        pose_chunk: int | None = DEFAULT_POSE_CHUNK,
        base: Float[ArrayLike, "P V 3"] | None = None,
        orientation: str = "check",
        placement: tuple[Float[ArrayLike, " 3"], float] | None = None,
    ) -> GeneratedRig:
        """The network's rig of a neutral head already in its convention (+y up, facing +z;
        any triangulation, any parts, any units: the rig comes back in the head's).

        Args:
            vertices: (V, 3) neutral head; faces: (F, 3) triangles.
            k: eigenpairs for the operators (the model's training value).
            operators: precomputed operators of the *normalised* head (skips their cost).
            cache: operator disk cache (``False``: compute, a cold start; ``mesh_operators``).
            memory_budget: refuse heads whose activations would exceed this many bytes.
            bucket: pad vertex, face and operator sizes up to a multiple of this, so heads
                of similar size share one compiled network (padding does not change the
                result).
            pose_chunk: poses per pass through the network's conditional blocks (``None``:
                all at once); the result does not depend on it, the speed and memory do.
            base: for ``TransferResidual`` only, and needed there: (P, V, 3) base
                displacements of every pose in the head's units (``transfer_poses``).
            orientation: the model expects +y up and +z forward (ICT). ``"check"``
                (default): refuse a head whose shape clearly faces elsewhere
                (``head_orientation``: mirror symmetry, the nose tip, eyes and neck cut;
                ~15 ms at 1,700 vertices); ``"fix"``: turn such a head into the convention
                for the model and the predictions back (the rig stays in the head's frame);
                ``"trust"``: no check. Heads whose cues are inconclusive (a sphere, a
                face-only mask's up direction) pass: ``auto_rig`` (``canrig autorig``)
                decides the orientation from a fit of the face, or refuses, and never lets a
                head through on a guess.
            placement: ``(centre (3,), scale)`` to normalise the head with instead of its
                bounding box (``face_placement``: from a fit of the ICT face, not from where
                the head was cropped); the head's frame, its units.

        Returns a ``GeneratedRig``: the rig (deltas named after the basis expressions,
        correctives for the combination poses), every pose's displacement, timings. Raises
        ValueError for a head without faces, non-finite or ill-shaped input, a pose set that
        does not match the model, a head too large for ``memory_budget``, or (``"check"``) a
        head that faces elsewhere.
        """
        network, poses = self.network()
        return generate_rig(
            network,
            poses,
            vertices,
            faces,
            k=k,
            operators=operators,
            cache=cache,
            memory_budget=memory_budget,
            bucket=bucket,
            pose_chunk=pose_chunk,
            base=base,
            orientation=orientation,
            placement=placement,
        )

    def _network_poses(
        self, head: UprightHead, dataset: AutorigDataset | None, base: np.ndarray | None
    ) -> PoseDisplacements:
        """Every pose the network predicts on the upright head (its orientation trusted:
        ``auto_rig`` decided it)."""
        network, poses = self.network()
        if dataset is not None and poses.labels != dataset.poses.labels:
            raise ValueError("model: its pose set is not the ICT source's (dataset)")
        generated = generate_rig(
            network, poses, head.vertices, head.faces, base=base, orientation="trust"
        )
        displacements = np.asarray(generated.displacements, np.float64)
        return PoseDisplacements(displacements, poses, tuple(poses.basis_names))


class RigAnyFaceNetwork(AbstractNetworkMethod):
    """RigAnyFace (Ma et al. 2025): a FACS-conditioned DiffusionNet with a global encoder
    predicts every pose; needs neither landmarks nor the data folder.

    Attributes:
        model: ``(RigAnyFace, PoseSet)``, a checkpoint path, or None: the packaged model
            (``DEFAULT_CHECKPOINT``).
    """

    model: NetworkModel = None
    name: ClassVar[str] = "raf"
    needs_landmarks: ClassVar[bool] = False
    checkpoint: ClassVar[Path] = DEFAULT_CHECKPOINT
    residual: ClassVar[bool] = False

    def displacements(self, head: UprightHead, dataset: AutorigDataset | None) -> PoseDisplacements:
        return self._network_poses(head, dataset, None)


class TransferResidual(AbstractNetworkMethod):
    """Anchored transfer (``Transfer()``'s ICT poses) plus a RigAnyFace residual trained on
    top of it.

    Attributes:
        model: a residual ``(RigAnyFace, PoseSet)``, a checkpoint path, or None: the
            packaged residual model (``RESIDUAL_CHECKPOINT``).
    """

    model: NetworkModel = None
    name: ClassVar[str] = "transfer-residual"
    needs_landmarks: ClassVar[bool] = True
    checkpoint: ClassVar[Path] = RESIDUAL_CHECKPOINT
    residual: ClassVar[bool] = True

    def displacements(self, head: UprightHead, dataset: AutorigDataset | None) -> PoseDisplacements:
        if dataset is None:
            raise ValueError("dataset: the residual is on the transfer of the ICT source's poses")
        return self._network_poses(head, dataset, _anchored_transfer(dataset, head))


def _anchored_transfer(dataset: AutorigDataset, head: UprightHead) -> np.ndarray:
    """(P, V, 3) cm: every ICT pose carried onto the upright head (anchored transfer)."""
    assert head.landmarks is not None  # placed for every method that needs them
    correspondence = head_correspondence(dataset, head.vertices, head.faces, head.landmarks)
    return transfer_poses(dataset, head, correspondence, static_below=ANCHOR_CM)


def _template_rig(template: Template, head: UprightHead) -> BlendshapeRig:
    """The template's shapes carried onto the upright head (anchored deformation transfer),
    in centimetres."""
    source = template.rig
    scale = UNIT_IN_CM[source.units]
    neutral = np.asarray(source.neutral, np.float64) * scale
    # a coarse template holds some landmarks on one vertex; the landmark spline needs each
    # template point once (a repeated point makes its system singular)
    _, first = np.unique(np.asarray(template.landmarks), return_index=True)
    once = np.sort(first)
    correspondence = closest_point_correspondence(
        neutral,
        np.asarray(source.faces),
        head.vertices,
        head.faces,
        np.asarray(template.landmarks)[once],
        np.asarray(head.landmarks)[once],
    )
    linear = BlendshapeRig(
        neutral.astype(np.float32),
        (np.asarray(source.deltas, np.float64) * scale).astype(np.float32),
        (),
        source.names,
        np.asarray(source.faces),
    )
    return deformation_transfer(linear, head.vertices, correspondence, static_below=ANCHOR_CM)


AUTO_RIG_METHODS = (Transfer, RigAnyFaceNetwork, TransferResidual)
"""Every final auto-rig method (the contract test runs each)."""
DEFAULT_METHOD = Transfer()
"""What ``auto_rig`` and ``canrig autorig`` use unless told: chosen in motion, on validation
heads only (held-out ICT identities and both Rocketbox heads, k = 0, driven by the data
folder's Live Link capture), by the rule committed in
``experiments/results/any_head_motion/RULE.md`` before it ran: transfer fails no hard rig
check (``check_rig``) on any of them; the RigAnyFace network ("raf") fails blink, eyeball,
locality, flipped-triangle and crossing checks on both Rocketbox heads (its lids and lips
fold off ICT's geometry). No method met the rule's flips bound on every head (transfer on
the Rocketbox male: 8.3 flips per frame, the artist's rig 2.8)."""
