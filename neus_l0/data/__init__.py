"""Scenes: the NeuS-format loader, camera rays and synthetic scenes with exact ground truth.

- `neus_l0.data.scene`: `Scene`, `load_scene`, `validate_scene`, `scene_summary`; image
  reading (RGBA: alpha as the mask) and the downscale shared with the other formats.
- `neus_l0.data.transforms`: transforms.json scenes (NeRF-synthetic, instant-ngp,
  nerfstudio): `read_transforms` (cameras, image and mask paths), `load_views` (pixels,
  undistortion); `neus_l0.formats.open.open_scene` adds the object sphere.
- `neus_l0.data.rays`: `pixel_rays`, `image_rays`, `random_rays`.
- `neus_l0.data.cameras`: projection decomposition, look-at, the optical axes' convergence,
  the DTU-like camera cap.
- `neus_l0.data.shapes`: analytic SDFs, CSG and the built-in shapes.
- `neus_l0.data.raycast`: the sphere-tracing renderer (textured, shaded, anti-aliased).
- `neus_l0.data.synthetic`: `make_scene`, which writes a NeuS-format folder + ground truth.
"""
