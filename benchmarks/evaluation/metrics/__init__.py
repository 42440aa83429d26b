"""Image-quality metrics and the evaluation protocols built from them.

- :mod:`.psnr` — :func:`psnr`, :func:`masked_psnr` (batched, float64).
- :mod:`.ssim` — :func:`ssim_box` (scikit-image defaults), :func:`ssim_box_1d` (1-D vectors),
  :func:`ssim_gaussian_masked` (DyCheck).
- :mod:`.avge` — :func:`avge`.
- :mod:`.protocols` — :class:`Protocol`, :func:`get_protocol`; protocols in :mod:`.protocol_worldtree`
  and :mod:`.protocol_dycheck`.

Torch is imported by these modules; import them only where metrics are computed.
"""

from benchmarks.evaluation.metrics.avge import avge
from benchmarks.evaluation.metrics.protocols import METRICS, PROTOCOL_NAMES, Protocol, get_protocol
from benchmarks.evaluation.metrics.psnr import masked_psnr, psnr
from benchmarks.evaluation.metrics.ssim import ssim_box, ssim_box_1d, ssim_gaussian_masked

__all__ = [
    "METRICS",
    "PROTOCOL_NAMES",
    "Protocol",
    "avge",
    "get_protocol",
    "masked_psnr",
    "psnr",
    "ssim_box",
    "ssim_box_1d",
    "ssim_gaussian_masked",
]
