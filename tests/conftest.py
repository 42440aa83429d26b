"""Suite-wide settings: the suite runs as 2 pytest-xdist workers on 2 cores, so each uses one torch thread
(more threads per worker oversubscribe the cores and make small tensor ops many times slower)."""

from __future__ import annotations

import torch

torch.set_num_threads(1)
