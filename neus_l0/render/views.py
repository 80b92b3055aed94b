"""One camera's render as pictures (colour, camera-frame normals, colour-mapped camera-z
depth) and the image metrics against ground truth (PSNR, SSIM); no file IO.

Images are numpy arrays on the host: float32 in [0, 1] for metrics, uint8 RGB for files.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np
import torch

from neus_l0.bounds.spans import RayBounds
from neus_l0.config.schema import Config
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.fields.model import NeuSModel
from neus_l0.render.volume import render_image
from neus_l0.sampling.upsample import build_sampler

#: PSNR of an exact match: the mean squared error is floored at 1e-10, as the bench's
#: held-out PSNR does, so a perfect image scores 100 dB (finite, valid JSON).
MSE_FLOOR = 1e-10

#: The per-view metrics `view_metrics` computes (``psnr_mask`` only with a mask).
METRICS = ("psnr", "ssim", "psnr_mask")


@dataclasses.dataclass
class ViewRender:
    """What one camera sees, on the host.

    Attributes:
        color: (H, W, 3) float32, clamped to [0, 1].
        normal: (H, W, 3) float32, the weighted SDF gradients in the camera frame (x right,
            y down, z forward; not normalised, as the validation renders show them).
        depth: (H, W) float32 camera-z depth (normalised units) of the weighted mean sample.
        weight: (H, W) float32 opacity in [0, 1].
    """

    color: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    weight: np.ndarray


def render_view(model: NeuSModel, K: torch.Tensor, c2w: torch.Tensor, size: tuple[int, int],
                cfg: Config, bounds: Sequence[RayBounds] = (),
                cos_anneal_ratio: float = 1.0) -> ViewRender:
    """Render one camera through `neus_l0.render.volume.render_image` (no jitter).

    Args:
        model: the networks (eval mode).
        K: (3, 3) intrinsics; c2w: (4, 4) pose in the normalised frame (OpenCV axes), both
            float32 on the model's device.
        size: (H, W) pixels.
        cfg: the run's config (its render and sampler settings).
        bounds: what narrows the rays (e.g. the run's visual hull).
        cos_anneal_ratio: NeuS's cos annealing (1: unbiased).

    Returns:
        a `ViewRender`.
    """
    H, W = size
    o, d = pixel_rays(K, c2w, pixel_grid(H, W, K.device).reshape(-1, 2))
    out = render_image(model, o.reshape(H, W, 3), d.reshape(H, W, 3), cfg.render,
                       build_sampler(cfg.sampler), cos_anneal_ratio, bounds=bounds)
    rot = c2w[:3, :3]  # camera -> world
    normal = out["normal"] @ rot  # (H, W, 3) world -> camera: n^T R = (R^T n)^T
    depth = out["depth"] * (d.reshape(H, W, 3) @ rot[:, 2])  # ray length -> camera z

    def host(t: torch.Tensor) -> np.ndarray:
        return t.detach().float().cpu().numpy()

    return ViewRender(color=host(out["color"].clamp(0, 1)), normal=host(normal),
                      depth=host(depth), weight=host(out["weight_sum"].clamp(0, 1)))


def to_uint8(img: np.ndarray) -> np.ndarray:
    """(...) float in [0, 1] -> uint8 (rounded, clipped)."""
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def normal_picture(normal: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame normals -> (H, W, 3) uint8 RGB as ``n / 2 + 1/2``."""
    return to_uint8(normal * 0.5 + 0.5)


def depth_picture(depth: np.ndarray, weight: np.ndarray, near: float, far: float) -> np.ndarray:
    """Camera-z depth colour-mapped (OpenCV's turbo: near red, far blue) over [near, far],
    faded to black by the opacity.

    Args:
        depth: (H, W) camera-z; weight: (H, W) opacity in [0, 1]; near < far.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    closeness = np.clip((far - depth) / (far - near), 0.0, 1.0)  # near -> 1 (red)
    bgr = cv2.applyColorMap(to_uint8(closeness), cv2.COLORMAP_TURBO)
    rgb = bgr[..., ::-1].astype(np.float32) * np.clip(weight, 0.0, 1.0)[..., None]
    return (rgb + 0.5).astype(np.uint8)


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    """PSNR (dB) of colours in [0, 1]; the MSE is floored at `MSE_FLOOR` (100 dB at most).

    Args:
        pred, gt: (H, W, 3) float.
        mask: (H, W) bool: average over these pixels only.

    Returns:
        the PSNR, or None when `mask` selects no pixel.
    """
    err = ((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2).mean(-1)  # (H, W)
    if mask is not None:
        if not mask.any():
            return None
        err = err[mask]
    return -10.0 * math.log10(max(float(err.mean()), MSE_FLOOR))


#: SSIM's window: Gaussian, standard deviation 1.5 pixels, 11x11 (Wang et al. 2004, and
#: what NeRF papers and nerfstudio report).
SSIM_SIGMA = 1.5
SSIM_WINDOW = 11


def ssim(pred: np.ndarray, gt: np.ndarray) -> float | None:
    """Mean SSIM of (H, W, 3) colours in [0, 1] with the field's window: an 11x11 Gaussian
    of sigma 1.5 (`SSIM_WINDOW`, `SSIM_SIGMA`), population covariances, channels averaged;
    None for images under 11 pixels a side."""
    from skimage.metrics import structural_similarity

    if min(pred.shape[0], pred.shape[1]) < SSIM_WINDOW:
        return None
    # truncate: the Gaussian is cut at (SSIM_WINDOW // 2) / sigma deviations -> 11 taps
    return float(structural_similarity(
        np.asarray(gt, np.float64), np.asarray(pred, np.float64), channel_axis=-1,
        data_range=1.0, gaussian_weights=True, sigma=SSIM_SIGMA, use_sample_covariance=False,
        truncate=(SSIM_WINDOW // 2) / SSIM_SIGMA))


def view_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """PSNR and SSIM of one view (and the PSNR inside `mask` when one is given).

    Args:
        pred, gt: (H, W, 3) float in [0, 1]; mask: (H, W) bool foreground, or None.

    Returns:
        ``{"psnr", "ssim"}`` (and ``"psnr_mask"``), floats or None (see `psnr`, `ssim`).
    """
    out = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    if mask is not None:
        out["psnr_mask"] = psnr(pred, gt, mask)
    return out


def mean_metrics(per_view: Sequence[dict]) -> dict:
    """The mean of each metric (`METRICS`) over the views where it is a number (None where
    it is in none); other keys of the per-view dicts are ignored."""
    means = {}
    for k in METRICS:
        if any(k in m for m in per_view):
            vals = [m[k] for m in per_view if isinstance(m.get(k), float)]
            means[k] = float(np.mean(vals)) if vals else None
    return means
