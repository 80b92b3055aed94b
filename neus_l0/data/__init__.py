"""Scenes in memory: the `Scene` container, cameras, rays, view pairing and splits, SfM points.

- `neus_l0.data.scene`: `Scene`, `scene_summary`.
- `neus_l0.data.cameras`: projection decomposition, look-at, the optical axes' convergence,
  the DTU-like camera cap.
- `neus_l0.data.rays`: `pixel_rays`, `image_rays`, `random_rays`.
- `neus_l0.data.views`: which file is which view (pairing by the number in the name).
- `neus_l0.data.split`: the training / held-out split of views (`split_views`, `subset_scene`).
- `neus_l0.data.points`: SfM points on disk.

The formats on disk are read by `neus_l0.formats`; synthetic scenes come from
`neus_l0.synthetic`.
"""
