"""Readable pure-PyTorch tile rasterizer: the oracle for the compiled kernel and the portable fallback.

Gradients come from autograd. Work is vectorised over chunks of tiles: every tile of a chunk gets its depth-
sorted Gaussian list padded to the chunk's longest list, and all pixels x Gaussians of the chunk are evaluated
at once.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from worldtree.render.projection import TILE, tile_rect

ALPHA_MAX = 0.99  # cap on a single Gaussian's alpha
ALPHA_MIN = 1.0 / 255.0  # alphas below this are skipped
T_MIN = 1e-4  # compositing stops before transmittance would drop below this
CHUNK_ELEMENTS = 1 << 22  # pixels x Gaussians evaluated per chunk (bounds the memory of one step)
CHECKPOINT_ELEMENTS = (
    1 << 25
)  # above this many pixel x Gaussian pairs per frame, recompute chunks in backward


def bin_gaussians(means2d: Tensor, depths: Tensor, radii: Tensor, width: int, height: int):
    """Tile lists: (gauss_ids [M] int64, tile_start [n_tiles] int64, tile_count [n_tiles] int64).

    ``gauss_ids[tile_start[t] : tile_start[t] + tile_count[t]]`` are the Gaussians whose bounding square
    touches tile t (row-major tile order), front to back (ties by index). Only radii > 0 are binned.
    """
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    dev = means2d.device
    ids = torch.nonzero(radii > 0).squeeze(1)
    ids = ids[torch.argsort(depths.detach()[ids], stable=True)]
    x0, x1, y0, y1 = tile_rect(means2d.detach()[ids], radii[ids], width, height)
    span_x = x1 - x0
    counts = span_x * (y1 - y0)
    total = int(counts.sum())
    which = torch.repeat_interleave(torch.arange(len(ids), device=dev), counts)
    local = torch.arange(total, device=dev) - (torch.cumsum(counts, 0) - counts)[which]
    tile = (y0[which] + local // span_x[which]) * tw + x0[which] + local % span_x[which]
    perm = torch.argsort(tile, stable=True)  # stable: keeps front-to-back order within a tile
    tile_count = torch.bincount(tile[perm], minlength=tw * th)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    return ids[which[perm]], tile_start, tile_count


def rasterize_reference(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    radii: Tensor,
    background: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite screen-space Gaussians front to back; returns rgb [H, W, 3], alpha [H, W], depth [H, W].

    means2d [N, 2] px, conics [N, 3] (a, b, c) of the inverse covariance, opacities [N], colors [N, 3],
    depths [N] camera z, radii [N] int (0 = skip), background [3]. Per pixel, in depth order:
    alpha = min(0.99, o exp(-q/2)) with q the conic's quadratic form; skipped when the exponent is positive or
    alpha < 1/255; compositing stops before T would fall below 1e-4. rgb = sum w c + T bg, alpha = 1 - T,
    depth = sum w z with w = alpha T.
    """
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    n_tiles = tw * th
    dev, dt = means2d.device, means2d.dtype
    gids, tile_start, tile_count = bin_gaussians(means2d, depths, radii, width, height)

    # Row N is padding: zero opacity, so its alpha is 0 and it is always skipped.
    pad = torch.zeros(1, 1, dtype=dt, device=dev)
    mu = torch.cat([means2d, pad.expand(1, 2)])
    con = torch.cat([conics, pad.expand(1, 3)])
    opa = torch.cat([opacities, pad[0]])
    # Channels composited together: r, g, b, z.
    feat = torch.cat([torch.cat([colors, depths[:, None]], 1), pad.expand(1, 4)])
    n = means2d.shape[0]

    # Pixel centres of one tile, offsets 0..15 (OpenCV convention: centre of pixel (i, j) is (j, i)).
    off = torch.arange(TILE, device=dev, dtype=dt)

    # Chunks of tiles with similar list lengths (sorted by length) keep the padding small.
    order = torch.argsort(tile_count, stable=True)
    counts = tile_count[order].tolist()
    chunks = []
    t0 = 0
    while t0 < n_tiles:
        t1 = t0 + 1
        while t1 < n_tiles and (t1 - t0 + 1) * max(counts[t1], 1) * TILE * TILE <= CHUNK_ELEMENTS:
            t1 += 1
        chunks.append((order[t0:t1], max(counts[t1 - 1], 1)))
        t0 = t1
    # Large frames: recompute each chunk during backward instead of keeping its [tiles, 256, K] intermediates
    # (slower by about half, but the memory of a step stays at one chunk's worth).
    total = sum(len(tiles) * kmax * TILE * TILE for tiles, kmax in chunks)
    recompute = (
        torch.is_grad_enabled()
        and total > CHECKPOINT_ELEMENTS
        and any(t.requires_grad for t in (mu, con, opa, feat))
    )
    out_chunks = []
    for tiles, kmax in chunks:
        args = (tiles, kmax, tw, tile_start, tile_count, gids, n, mu, con, opa, feat, off)
        out_chunks.append(
            checkpoint(_rasterize_tiles, *args, use_reentrant=False) if recompute else _rasterize_tiles(*args)
        )
    # [n_tiles, 256, 5] back in row-major tile order: r, g, b, z, T
    out = torch.cat(out_chunks)[torch.argsort(order)]
    out = out.reshape(th, tw, TILE, TILE, 5).permute(0, 2, 1, 3, 4).reshape(th * TILE, tw * TILE, 5)
    out = out[:height, :width]
    T = out[..., 4]
    rgb = out[..., :3] + T[..., None] * background
    return rgb, 1.0 - T, out[..., 3]


def _rasterize_tiles(tiles, kmax, tw, tile_start, tile_count, gids, n, mu, con, opa, feat, off):
    """Tiles [nt] (indices) -> [nt, 256, 5] (accumulated r, g, b, z and final transmittance)."""
    dev = mu.device
    slot = torch.arange(kmax, device=dev)
    # idx[t, k]: k-th Gaussian of tile t, or the padding row n past the end of its list.
    if len(gids) == 0:
        idx = torch.full((len(tiles), kmax), n, device=dev, dtype=torch.long)
    else:
        idx = torch.clamp(tile_start[tiles, None] + slot, max=len(gids) - 1)
        idx = torch.where(slot < tile_count[tiles, None], gids[idx], n)
    # Pixel coordinates: dx depends only on the column and dy only on the row, so the quadratic form is built
    # from [nt, 1, 16, K] and [nt, 16, 1, K] pieces and only the cross term is evaluated per pixel.
    x = ((tiles % tw) * TILE).to(mu.dtype)[:, None] + off  # [nt, 16] column centres
    y = ((tiles // tw) * TILE).to(mu.dtype)[:, None] + off  # [nt, 16] row centres
    m = mu[idx]  # [nt, K, 2]
    cn = con[idx]  # [nt, K, 3]
    dx = (x[:, :, None] - m[:, None, :, 0])[:, None]  # [nt, 1, 16, K]
    dy = (y[:, :, None] - m[:, None, :, 1])[:, :, None]  # [nt, 16, 1, K]
    a, b, c = (cn[:, None, None, :, i] for i in range(3))
    power = (-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy).flatten(1, 2)  # [nt, 256, K], row-major pixels
    alpha = torch.clamp(opa[idx][:, None, :] * torch.exp(power), max=ALPHA_MAX)
    alpha = torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        # Gaussian k is composited iff T after it stays >= T_MIN (T only decreases, so this is a prefix).
        used = torch.cumprod(1.0 - alpha, -1) >= T_MIN
    alpha = alpha * used
    # T after each Gaussian; log space because cumsum's backward is far cheaper than cumprod's (1 - alpha >= 0.01).
    trans = torch.exp(torch.cumsum(torch.log1p(-alpha), -1))
    t_before = torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], -1)
    w = alpha * t_before
    acc = w @ feat[idx]  # [nt, 256, 4]
    return torch.cat([acc, trans[..., -1:]], -1)
