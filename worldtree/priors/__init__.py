"""2D priors of a monocular video: optical flow, long-term tracks, depth, epipolar errors and dynamic masks.

Classical priors run offline on the CPU (OpenCV DIS flow, Lucas-Kanade tracks, plane-sweep stereo, Sampson
errors); priors computed elsewhere (Metric3D, CoTracker, RAFT, SAM2 masks) can be imported instead. One entry
point, :func:`compute_priors`, returns a :class:`Priors` and caches results by inputs and settings.

The settings (:mod:`worldtree.priors.config`) import nothing heavy; the rest loads on first use, so that a
CLI can read the defaults for its ``--help`` without importing OpenCV or torch.
"""

from worldtree.priors.config import (
    DepthConfig,
    DepthImportConfig,
    EpiConfig,
    FlowConfig,
    PriorsConfig,
    TrackConfig,
)

__all__ = [
    "DepthConfig",
    "DepthImportConfig",
    "EpiConfig",
    "FlowConfig",
    "Priors",
    "PriorsConfig",
    "TrackConfig",
    "compute_priors",
]


def __getattr__(name: str):
    if name in ("Priors", "compute_priors"):
        from worldtree.priors import api

        return getattr(api, name)
    raise AttributeError(f"module 'worldtree.priors' has no attribute {name!r}")
