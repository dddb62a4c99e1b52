"""The papers' protocols: how the standard evaluations of the papers this toolkit reproduces
are run, kept apart from the toolkit itself.

One subpackage per paper, each the committed rules, sweeps, held-out splits, timing harnesses
and table makers of its experiments (``experiments/``), imported by name:

- ``canrig_jax.papers.inverse_rig``: the quartic inverse rig (Racković et al.).
- ``canrig_jax.papers.wpse``: weighted pose space editing (Seol et al.).
- ``canrig_jax.papers.canrig``: CANRig and its patch blendshapes (Mohammadi, Weiss et al.).
- ``canrig_jax.papers.riganyface``: RigAnyFace auto-rigging (Ma et al.).

The papers import the toolkit (``canrig_jax.rig``, ``inverse``, ``wpse``, ``canrig``,
``autorig``, ...); the toolkit never imports the papers.
"""

__all__: list[str] = []
