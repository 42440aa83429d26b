"""LPIPS (Zhang et al. 2018), AlexNet backbone with the v0.1 linear heads, written without torchvision.

The network is the ``features`` part of torchvision's AlexNet (five conv layers; LPIPS taps the ReLU after
each) plus one 1x1 linear head per tapped layer. Weight files are located and checked by
:mod:`benchmarks.evaluation.lpips_weights`; this module only holds the arithmetic.

Inputs are images in ``[-1, 1]`` (``uint8 / 127.5 - 1``), shape ``[B, 3, H, W]``, float32.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

# (in_channels, out_channels, kernel, stride, padding) of the conv layers at torchvision's AlexNet
# `features` indices 0, 3, 6, 8, 10; max-pools (3, stride 2) follow indices 1 and 4 (and 11, unused here).
ALEXNET_CONVS: dict[int, tuple[int, int, int, int, int]] = {
    0: (3, 64, 11, 4, 2),
    3: (64, 192, 5, 1, 2),
    6: (192, 384, 3, 1, 1),
    8: (384, 256, 3, 1, 1),
    10: (256, 256, 3, 1, 1),
}
#: Channels of the five tapped ReLU outputs, i.e. of the LPIPS linear heads ``lin0`` .. ``lin4``.
LPIPS_CHANNELS = (64, 192, 384, 256, 256)
# LPIPS' ScalingLayer: maps [-1, 1] inputs to ImageNet-normalised ones, per RGB channel.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# Added to the channel norm before dividing, as LPIPS' normalize_tensor does.
_NORM_EPS = 1e-10


class AlexNetFeatures(nn.Module):
    """torchvision AlexNet ``features[0:12]``; :meth:`forward` returns the 5 ReLU outputs LPIPS taps."""

    def __init__(self) -> None:
        super().__init__()
        # Kept in a ModuleDict keyed by torchvision's index so state dict keys read "features.0.weight".
        self.convs = nn.ModuleDict(
            {
                str(i): nn.Conv2d(ci, co, k, stride=s, padding=p)
                for i, (ci, co, k, s, p) in ALEXNET_CONVS.items()
            }
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``x`` [B, 3, H, W] (ImageNet-normalised) -> five maps [B, C_l, H_l, W_l], C_l = LPIPS_CHANNELS."""
        c = self.convs
        r1 = F.relu(c["0"](x))
        r2 = F.relu(c["3"](F.max_pool2d(r1, 3, 2)))
        r3 = F.relu(c["6"](F.max_pool2d(r2, 3, 2)))
        r4 = F.relu(c["8"](r3))
        r5 = F.relu(c["10"](r4))
        return [r1, r2, r3, r4, r5]

    def load_torchvision_state_dict(self, sd: Mapping[str, torch.Tensor]) -> None:
        """Load ``features.{0,3,6,8,10}.{weight,bias}`` from a torchvision AlexNet state dict (strict).

        Keys outside ``features.`` (the classifier) are ignored; a missing key or wrong shape raises
        ``ValueError`` naming it.
        """
        own = {}
        for i, conv in self.convs.items():
            for name, param in (("weight", conv.weight), ("bias", conv.bias)):
                key = f"features.{i}.{name}"
                if key not in sd:
                    raise ValueError(f"missing key {key}")
                if tuple(sd[key].shape) != tuple(param.shape):
                    raise ValueError(f"{key} has shape {tuple(sd[key].shape)}, expected {tuple(param.shape)}")
                own[f"convs.{i}.{name}"] = sd[key]
        extra = sorted(k for k in sd if k.startswith("features.") and k not in _tv_keys())
        if extra:
            raise ValueError(f"unexpected keys {extra[:4]}: not an AlexNet features state dict")
        self.load_state_dict(own, strict=True)


def _tv_keys() -> set[str]:
    return {f"features.{i}.{n}" for i in ALEXNET_CONVS for n in ("weight", "bias")}


class LPIPS(nn.Module):
    """LPIPS distance, AlexNet v0.1. Call :meth:`distance` or :meth:`distance_map`.

    Build with :meth:`from_state_dicts` (or :func:`benchmarks.evaluation.lpips_weights.load_lpips` for files). The module
    is put in eval mode and has no trainable use here; LPIPS' dropout before each head is the identity at
    evaluation.
    """

    def __init__(self) -> None:
        super().__init__()
        self.net = AlexNetFeatures()
        # One 1x1 conv without bias per tapped layer: the "linear heads" lin0..lin4.
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in LPIPS_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        for p in self.parameters():
            p.requires_grad_(False)
        # oneDNN convolutions are markedly faster on the CPU in channels-last layout; loading copies
        # values into these tensors and .to(device) keeps the layout.
        self.to(memory_format=torch.channels_last)
        self.eval()

    @classmethod
    def from_state_dicts(
        cls, alexnet_sd: Mapping[str, torch.Tensor], lin_sd: Mapping[str, torch.Tensor]
    ) -> LPIPS:
        """Build from a torchvision AlexNet state dict and an LPIPS ``alex.pth`` state dict (strict keys)."""
        m = cls()
        m.net.load_torchvision_state_dict(alexnet_sd)
        m.load_lin_state_dict(lin_sd)
        return m

    def load_lin_state_dict(self, sd: Mapping[str, torch.Tensor]) -> None:
        """Load ``lin{l}.model.1.weight`` [1, C_l, 1, 1] for l = 0..4; any other key or shape is a ValueError."""
        expected = {f"lin{i}.model.1.weight": (1, c, 1, 1) for i, c in enumerate(LPIPS_CHANNELS)}
        extra = sorted(set(sd) - set(expected))
        if extra:
            raise ValueError(f"unexpected keys {extra[:4]}: not an LPIPS v0.1 alex.pth")
        for i, (key, shape) in enumerate(expected.items()):
            if key not in sd:
                raise ValueError(f"missing key {key}")
            if tuple(sd[key].shape) != shape:
                raise ValueError(f"{key} has shape {tuple(sd[key].shape)}, expected {shape}")
            self.lins[i].weight.data.copy_(sd[key])

    def _layer_diffs(self, x0: torch.Tensor, x1: torch.Tensor) -> list[torch.Tensor]:
        """Per layer, the head applied to squared differences of unit-normalised features: [B, 1, H_l, W_l]."""
        cl = torch.channels_last
        f0 = self.net(((x0 - self.shift) / self.scale).contiguous(memory_format=cl))
        f1 = self.net(((x1 - self.shift) / self.scale).contiguous(memory_format=cl))
        out = []
        for lin, a, b in zip(self.lins, f0, f1, strict=True):
            a = a / (a.square().sum(1, keepdim=True).sqrt() + _NORM_EPS)
            b = b / (b.square().sum(1, keepdim=True).sqrt() + _NORM_EPS)
            out.append(lin((a - b).square()))
        return out

    @torch.no_grad()
    def distance(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """LPIPS of image pairs: ``x0``, ``x1`` [B, 3, H, W] in [-1, 1] -> [B] (spatial mean per layer, summed)."""
        return sum(d.mean(dim=(2, 3)) for d in self._layer_diffs(x0, x1))[:, 0]

    @torch.no_grad()
    def distance_map(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """LPIPS map: each layer's map bilinearly upsampled to [H, W] (align_corners=False), summed -> [B, H, W]."""
        size = x0.shape[-2:]
        maps = [
            F.interpolate(d, size=size, mode="bilinear", align_corners=False)
            for d in self._layer_diffs(x0, x1)
        ]
        return sum(maps)[:, 0]


def random_state_dicts(seed: int = 0) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Random weights in the two real file formats, for tests and timings without the real files.

    Returns (torchvision-style AlexNet state dict with ``features.*`` and a stand-in ``classifier.*`` entry,
    LPIPS ``alex.pth``-style dict of non-negative heads). He-scaled convolutions keep activations alive.
    """
    g = torch.Generator().manual_seed(seed)
    alex: dict[str, torch.Tensor] = {}
    for i, (ci, co, k, _, _) in ALEXNET_CONVS.items():
        alex[f"features.{i}.weight"] = torch.randn(co, ci, k, k, generator=g) * (2.0 / (ci * k * k)) ** 0.5
        alex[f"features.{i}.bias"] = torch.randn(co, generator=g) * 0.1
    alex["classifier.1.weight"] = torch.randn(8, 4, generator=g)
    alex["classifier.1.bias"] = torch.randn(8, generator=g)
    lin = {
        f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(LPIPS_CHANNELS)
    }
    return alex, lin
