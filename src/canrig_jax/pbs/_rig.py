"""A CANRig-PBS network with its patch basis as a handle rig (``canrig.AbstractHandleRig``):
bound to a mesh by ``canrig.NeuralRig``, it runs every CANRig workflow (pose A to B direct and
fitted, layers, clip editing, dialogue replacement) on the whole head.

The network predicts each patch's PBS weights from the handles' displacements, their masks
evaluated at the patch's seed vertex (``edit.distance`` at the seeds: the geodesic distances
of the ``NeuralRig``'s edge graph), and the base shape's patch means; the shape is
S = S_base + W_layout S_pred S_basis (``pbs_delta_shape``). Zero displacements give the base
exactly, and a vertex whose every covering patch has its seed outside every clamped mask does
not move (``support``). ``fit`` is the family's default: Gauss-Newton with the autodiff
Jacobian. Units follow the mesh (ICT: cm).
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..canrig import AbstractHandleRig, HandleEdit, influence_mask
from ..canrig._layout import DENSE, Layout, Local
from ._basis import PatchLayout, check_basis
from ._model import AbstractCANRigPBS, patch_means, pbs_delta_shape


class PBSRig(AbstractHandleRig):
    """A trained CANRig-PBS network (any of its variants), its patch layout and basis offsets
    (B - 1, V, 3) as a handle rig. Build it with ``pbs_rig``."""

    network: AbstractCANRigPBS
    layout: PatchLayout
    basis: Float[Array, "Bm1 V 3"]

    @property
    def clamp(self) -> float:
        return self.network.encoder.clamp

    @property
    def lapack_in_forward(self) -> bool:  # the local prior factors every patch's system
        return self.network.local_prior

    def check_mesh(self, n_vertices: int) -> None:
        if self.layout.n_vertices != n_vertices:
            raise ValueError(
                f"canonical: {n_vertices} vertices, the PBSRig's layout has "
                f"{self.layout.n_vertices}"
            )

    def prepare(self, canonical: Float[Array, "V 3"]) -> Float[Array, "heads P d"]:
        """The patches' queries at their seeds' canonical positions."""
        return self.network.encode_patches(canonical[self.layout.seeds])

    def seed_mask(self, edit: HandleEdit) -> Float[Array, "P H"]:
        """The handles' clamped influence at each patch's seed (only the P seed rows of the
        (V, H) distances are read)."""
        distance = edit.distance[self.layout.seeds]
        return influence_mask(distance, edit.radius, edit.falloff, self.clamp)

    def support(self, edit: HandleEdit) -> Bool[Array, " V"]:
        """The vertices covered by a patch whose seed lies inside some clamped mask."""
        reached = jnp.any(self.seed_mask(edit) > 0, axis=-1)
        covered = self.layout.vertex_weights > 0
        return jnp.any(covered & reached[self.layout.vertex_patches], axis=-1)

    def deform(
        self,
        prepared: Float[Array, "heads P d"],
        canonical: Float[Array, "V 3"],
        edit: HandleEdit,
        layout: Layout = DENSE,
        local: Local | None = None,
    ) -> Float[Array, "V 3"]:
        del layout, local  # no per-vertex attention to lay out
        net = self.network
        weights = net(
            prepared,
            patch_means(self.layout, edit.base),
            canonical[edit.index],
            edit.base[edit.index],
            edit.displacements,
            self.seed_mask(edit),
            edit.beta,
            handle_basis=self.basis[:, edit.index] if net.local_prior else None,
        )
        return pbs_delta_shape(self.layout, edit.base, self.basis, weights)


def pbs_rig(
    network: AbstractCANRigPBS, layout: PatchLayout, basis: Float[ArrayLike, "Bm1 V 3"]
) -> PBSRig:
    """A ``PBSRig``, validated: ``network`` a CANRig-PBS variant (the Shape Transformer has no
    masks: not a handle rig), ``basis`` offsets from the neutral on the layout's mesh with one
    weight per network output."""
    if not isinstance(network, AbstractCANRigPBS):
        raise TypeError(
            f"network: expected a CANRig-PBS network (PerPatchPBS, BaseMultipliedPBS, "
            f"NoModulationPBS), got {type(network).__name__}"
        )
    basis = check_basis(basis, layout.n_vertices)
    n_out = network.patch_mlp.layers[-1].weight.shape[-2]
    if basis.shape[0] != n_out:
        raise ValueError(f"basis: {basis.shape[0]} offsets, the network predicts {n_out} weights")
    # pyright reads the family's AbstractVar ``clamp`` as an __init__ field (equinox types it
    # as Annotated); here it is a property, not a field
    return PBSRig(  # pyright: ignore[reportCallIssue]
        network=network, layout=layout, basis=jnp.asarray(np.asarray(basis), jnp.float32)
    )
