"""Diagnostics of a fitted model: measurements that read a trained model to say how right it is.

A module here may import any part of the library (the model, motion, rendering); nothing in the library
imports it back, so a diagnostic never ties two model sub-packages together (``tests/test_layering.py``).

- :mod:`worldtree.diagnostics.model_tracks` -- 2D tracks of the dynamic Gaussians carried by the fitted
  scaffold, compared with exact motion by ``benchmarks.speed.motion_proof``.
"""
