"""Simulators: a procedural scene with known edits (`synthetic-scene`) and the simulated priors
that render a known answer (`simulated-editor`, `simulated-depth`). They measure the 3D part of the
method against ground truth on a CPU; nothing below this package imports it."""
from gs_regional.sim import depth, editor, scene, splat_truth  # noqa: F401  (register components)
