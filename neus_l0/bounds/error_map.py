"""Error-map ray sampling (instant-ngp style): draw training pixels where the error is.

The pixel pool (`neus_l0.bounds.pixel_pool`) holds P pixels, grouped into K tiles of T x T
pixels of a view (`train.error_map.tile`; 1: a tile per pixel). An error map keeps a running
error per tile; every pool pixel takes its tile's error e_j, and a draw table made from them
gives pixel j the probability

    p_j = (1 - f) / P + f * e_j / sum(e)        (f: `train.error_map.fraction`)

so every pixel keeps at least (1 - f) / P, and a tile's share grows with its error and its
pool pixels. Tiles, not pixels: a run draws fewer rays than a pool holds pixels (a few
hundred thousand against millions), so most pixels of a per-pixel map would never be
measured. Errors start at 0 (the uniform draw); a tile gets the map's share once a ray of
it has been measured. A ray drawn with probability p_j carries the
importance weight ``w_j = 1 / (P p_j)``: for any per-ray loss l, E[w l] over one draw is
sum_j p_j l_j / (P p_j) = the pool's mean of l, whatever the map holds. The step weights its
colour and mask terms so (`neus_l0.train.losses.neus_loss`).

Everything is a tensor op on the pool's device: the draw is `torch.searchsorted` on a
cumulative table (float64: a pool of millions of pixels would lose the smallest
probabilities in float32), the map is updated by an index write, and the table is rebuilt
every `train.log_every` steps (less often for a large pool: `refresh_interval`); none of it
reads a value back to the host.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor


@dataclasses.dataclass
class ErrorMap:
    """A pool's running error and the draw table made from it.

    Attributes:
        error: (K,) float32 running error of each tile (starts at 0: uniform).
        tile: (P,) int64 each pool pixel's tile in [0, K).
        prob: (P,) float32 draw probability of each pool pixel under the current table.
        cdf: (P,) float64 cumulative sum of `prob` (the table `draw` searches).
        fraction: f, the share of the draw that follows the map, in [0, 1).
        decay: weight of a new error in the running error, in (0, 1].
        foreground: the share of pool pixels in the foreground (1 when masks are unused):
            the expected share of a batch that the colour term averages over.
        table_error: (K,) float32 the tiles' errors the current table was built from (a
            checkpoint keeps them, so that a resumed run draws from the same table).
    """

    error: Tensor
    tile: Tensor
    prob: Tensor
    cdf: Tensor
    fraction: float
    decay: float
    foreground: float = 1.0
    table_error: Tensor | None = None


def draw_probabilities(error: Tensor, fraction: float) -> Tensor:
    """(P,) float64 probabilities ``(1 - f) / P + f * e / sum(e)`` of (P,) errors >= 0.

    A map whose errors sum to 0 (or are not finite) gives the uniform draw.
    """
    e = error.double().clamp_min(0.0)
    e = torch.nan_to_num(e, nan=0.0, posinf=0.0)
    n = e.numel()
    total = e.sum()
    share = torch.where(total > 0, e / total.clamp_min(1e-300), torch.full_like(e, 1.0 / n))
    return (1.0 - fraction) / n + fraction * share


#: Pool pixels per step of refresh interval: rebuilding the table costs about 30 ns a pixel
#: on one CPU thread (39 ms for 1.3 M pixels, against a ~14 ms step), so a pool of P pixels
#: refreshes every P / PIXELS_PER_STEP steps at least (its cost under 1 % of the steps).
PIXELS_PER_STEP = 4000


def refresh_interval(n_pixels: int, log_every: int) -> int:
    """Steps between table rebuilds: `log_every`, or more for a pool whose rebuild would
    cost over about 1 % of the steps (``ceil(P / PIXELS_PER_STEP)``)."""
    return max(1, log_every, -(-n_pixels // PIXELS_PER_STEP))


def refresh_table(emap: ErrorMap) -> None:
    """Rebuild `emap`'s draw table (prob, cdf) from its running error, in place."""
    emap.table_error = emap.error.clone()
    _build_table(emap)


def _build_table(emap: ErrorMap) -> None:
    """(prob, cdf) from `emap.table_error` at `emap.fraction`."""
    p = draw_probabilities(emap.table_error[emap.tile], emap.fraction)
    emap.prob = p.float()
    emap.cdf = torch.cumsum(p, 0)


def map_state(emap: ErrorMap) -> dict:
    """What a checkpoint keeps of `emap`: the running errors, the errors its table was
    built from and its share (the tiles and the table follow from them and the pool)."""
    return {"error": emap.error.detach().cpu().clone(),
            "table_error": emap.table_error.detach().cpu().clone(),
            "fraction": float(emap.fraction)}


def restore_map(emap: ErrorMap, state: dict) -> bool:
    """Load `map_state`'s `state` into `emap` and rebuild its table as it was, in place.

    Returns:
        False (nothing loaded) when the state's tiles are not this map's (another pool,
        another tile size): the map then starts uniform.
    """
    error, table = state.get("error"), state.get("table_error")
    if not (isinstance(error, Tensor) and isinstance(table, Tensor)
            and error.shape == table.shape == emap.error.shape):
        return False
    emap.error = error.to(emap.error).clone()
    emap.table_error = table.to(emap.error).clone()
    share = state.get("fraction", emap.fraction)
    if isinstance(share, (int, float)) and 0.0 <= share < 1.0:  # else the config's stays
        emap.fraction = float(share)
    _build_table(emap)
    return True


def new_error_map(tile: Tensor, fraction: float, decay: float,
                  foreground: float = 1.0) -> ErrorMap:
    """An error map over pool pixels in (P,) int64 tiles ``0..K-1``, errors 0 (uniform)."""
    n_tiles = int(tile.max()) + 1 if tile.numel() else 0
    emap = ErrorMap(torch.zeros(n_tiles, device=tile.device), tile, torch.empty(0),
                    torch.empty(0), fraction, decay, foreground)
    refresh_table(emap)
    return emap


def draw(emap: ErrorMap, n_rays: int, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """Draw `n_rays` pool indices from the table, with replacement.

    Args:
        emap: the map (its table on the pool's device).
        generator: the source of the uniforms (on any device; they move to the table's).

    Returns:
        (n_rays,) int64 pool indices and (n_rays,) float32 importance weights 1 / (P p).
    """
    cdf = emap.cdf
    gdev = generator.device if generator is not None else cdf.device
    u = torch.rand(n_rays, generator=generator, dtype=torch.float64, device=gdev).to(cdf.device)
    idx = torch.searchsorted(cdf, u * cdf[-1], right=True).clamp_max(cdf.numel() - 1)
    return idx, importance_weights(emap.prob, idx)


def importance_weights(prob: Tensor, idx: Tensor) -> Tensor:
    """(B,) weights ``1 / (P p[idx])`` of (B,) indices drawn with (P,) probabilities `prob`."""
    return 1.0 / (prob.numel() * prob[idx])


def update_errors(emap: ErrorMap, idx: Tensor, ray_error: Tensor) -> None:
    """Blend the (B,) errors of the rays at (B,) pool indices into their tiles' running
    errors, in place: ``e <- (1 - decay) e + decay * err`` (a tile hit by several rays of
    the batch keeps one of them)."""
    err = torch.nan_to_num(ray_error.detach().float(), nan=0.0, posinf=0.0).clamp_min(0.0)
    t = emap.tile[idx]
    emap.error[t] = torch.lerp(emap.error[t], err, emap.decay)


def pixel_tiles(pixels: Tensor, height: int, width: int, size: int) -> Tensor:
    """(P,) int64 tiles ``0..K-1`` of (P,) flat pixel indices ``view * H * W + y * W + x``:
    pixels share a tile when they lie in the same `size` x `size` block of the same view
    (numbered in order of first appearance of the blocks' sorted ids)."""
    view = pixels // (height * width)
    y, x = (pixels % (height * width)) // width, pixels % width
    cols = -(-width // size)
    rows = -(-height // size)
    block = view * (rows * cols) + (y // size) * cols + x // size
    return torch.unique(block, return_inverse=True)[1]
