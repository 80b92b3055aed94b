"""Scenes: the NeuS-format loader, camera rays and synthetic scenes with exact ground truth.

- `neus_l0.data.scene`: `Scene`, `load_scene`, `validate_scene`.
- `neus_l0.data.rays`: `pixel_rays`, `image_rays`, `random_rays`.
- `neus_l0.data.cameras`: projection decomposition, look-at, the DTU-like camera cap.
- `neus_l0.data.shapes`: analytic SDFs, CSG and the built-in shapes.
- `neus_l0.data.raycast`: the sphere-tracing renderer (textured, shaded, anti-aliased).
- `neus_l0.data.synthetic`: `make_scene`, which writes a NeuS-format folder + ground truth.
"""
