"""Motion maths for the dynamic methods: rotations, rigid transforms, dual quaternions and skinning.

Modules (import them as namespaces, their function names overlap on purpose):

- :mod:`worldtree.motion.quaternion` -- (w, x, y, z) unit quaternions, so(3) exp/log, slerp, 6D rotations.
- :mod:`worldtree.motion.se3` -- (quaternion, translation) transforms, se(3) exp/log, weighted Procrustes.
- :mod:`worldtree.motion.dualquat` -- dual quaternions and dual-quaternion blending (DQB).
- :mod:`worldtree.motion.skinning` -- KNN to scaffold nodes, skinning weights, deformation of Gaussians.

Conventions, formulas and numerical guards: ``docs/motion.md``.
"""

from worldtree.motion import dualquat, quaternion, se3, skinning

__all__ = ["dualquat", "quaternion", "se3", "skinning"]
