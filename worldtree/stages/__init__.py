"""Optimisation stages of the Base dynamic method, each a small module of (config, state) -> state.

- :mod:`worldtree.stages.cameras` -- pose deltas on world-to-camera matrices, camera centres, Sim(3) helpers.
- :mod:`worldtree.stages.testview_pose` -- bring the test camera into the reconstruction frame: Sim(3) alignment
  of the given training poses onto the optimised ones, then per-frame photometric pose refinement.
- :mod:`worldtree.stages.bundle_adjust` -- tracklet bundle adjustment ("BA") of cameras, per-frame depth
  scales and static track depths.
- :mod:`worldtree.stages.static_warmup` -- static warm-up ("SW") of the background Gaussians on static pixels.

Formulas and settings: ``docs/base_method.md``.
"""
