"""Camera rays in the normalised frame (pure tensor functions, batched, no Python loops).

Pixel (x, y) is the point (x, y) in K's frame: the pixel in row y, column x is centred on
integer coordinates (NeuS's convention). Ray directions are unit vectors.
"""

from __future__ import annotations

import torch

from neus_l0.data.scene import Scene


def pixel_rays(intrinsics: torch.Tensor, c2w: torch.Tensor,
               xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through pixel coordinates.

    Args:
        intrinsics: (B, 3, 3) upper-triangular K (K[2, 2] == 1), or (3, 3) shared by all.
        c2w: (B, 4, 4) camera-to-world poses, or (4, 4) shared by all.
        xy: (B, 2) pixel coordinates (float; integers are pixel centres).

    Returns:
        origins: (B, 3) camera centres.
        dirs: (B, 3) unit directions.
    """
    xy = xy.to(intrinsics.dtype)
    B = xy.shape[0]
    K = intrinsics.expand(B, 3, 3) if intrinsics.dim() == 2 else intrinsics
    T = c2w.expand(B, 4, 4) if c2w.dim() == 2 else c2w
    # K^-1 [x, y, 1] for an upper-triangular K, without a batched inverse; one unbind
    # gives K's entries (fewer ops than indexing each)
    k00, k01, k02, _, k11, k12, _, _, _ = K.reshape(B, 9).unbind(1)  # (B,) each
    x, y = xy.unbind(1)
    yc = (y - k12) / k11  # (B,)
    xc = (x - k02 - k01 * yc) / k00  # (B,)
    d_cam = torch.stack([xc, yc, torch.ones_like(xc)], dim=-1)  # (B, 3)
    dirs = torch.bmm(T[:, :3, :3], d_cam[..., None])[..., 0]  # (B, 3) = R d_cam
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    return T[:, :3, 3], dirs


def pixel_grid(height: int, width: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(H, W, 2) float32 pixel-centre coordinates (x, y) of an image."""
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32),
                            torch.arange(width, device=device, dtype=torch.float32),
                            indexing="ij")
    return torch.stack([xs, ys], dim=-1)


def image_rays(scene: Scene, view: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through every pixel centre of one view.

    Returns:
        origins: (H, W, 3), dirs: (H, W, 3) unit, on the scene's device.
    """
    H, W = scene.height, scene.width
    xy = pixel_grid(H, W, scene.device).reshape(-1, 2)  # (H*W, 2)
    o, d = pixel_rays(scene.intrinsics[view], scene.c2w[view], xy)
    return o.reshape(H, W, 3), d.reshape(H, W, 3)


def random_rays(scene: Scene, n_rays: int, generator: torch.Generator | None = None) -> dict:
    """A batch of rays through pixels drawn uniformly over all views and pixels.

    Args:
        scene: the loaded scene.
        n_rays: batch size B.
        generator: the random source; indices are drawn on its device and moved to the
            scene's device (keep both on the same device to avoid any transfer).

    Returns:
        dict with ``origins`` (B, 3), ``dirs`` (B, 3), ``rgb`` (B, 3), ``mask`` (B, 1),
        ``view`` (B,) int64 and ``xy`` (B, 2) int64, all on the scene's device.
    """
    dev = scene.device
    gdev = generator.device if generator is not None else dev
    n, H, W = scene.n_views, scene.height, scene.width
    flat = torch.randint(0, n * H * W, (n_rays,), generator=generator, device=gdev).to(dev)
    return rays_at(scene, flat)


def random_picks(n: int, n_rays: int, generator: torch.Generator | None,
                 device: torch.device) -> torch.Tensor:
    """(n_rays,) int64 indices drawn uniformly from [0, n) on the generator's device, moved
    to `device`."""
    gdev = generator.device if generator is not None else device
    return torch.randint(0, n, (n_rays,), generator=generator, device=gdev).to(device)


def rays_at(scene: Scene, flat: torch.Tensor) -> dict:
    """Rays and ground truth at flat pixel indices ``view * H * W + y * W + x``.

    Args:
        flat: (B,) int64 on the scene's device.

    Returns:
        the dict of `random_rays`.
    """
    H, W = scene.height, scene.width
    view = flat // (H * W)
    pix = flat % (H * W)
    y, x = pix // W, pix % W
    xy = torch.stack([x, y], dim=-1)
    xy1 = torch.nn.functional.pad(xy.to(scene.c2w.dtype), (0, 1), value=1.0)  # (B, 3)
    d = torch.bmm(scene.ray_matrices[view], xy1[..., None])[..., 0]  # (B, 3)
    return {
        "origins": scene.centres[view],
        "dirs": d / d.norm(dim=-1, keepdim=True),
        "rgb": scene.images[view, y, x],
        "mask": scene.masks[view, y, x].unsqueeze(-1),
        "view": view,
        "xy": xy,
    }
