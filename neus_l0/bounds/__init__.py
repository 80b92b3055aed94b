"""Where rays can meet the surface: what narrows each ray's [near, far] before sampling.

- `neus_l0.bounds.sphere`: NeuS's near / far and the unit sphere's chord.
- `neus_l0.bounds.spans`: the `RayBounds` protocol; `ray_bounds` joins the sphere with
  the narrowing bounds; `packed_spans` packs static spans for reuse.
- `neus_l0.bounds.hull`: the visual hull carved from the masks.
- `neus_l0.bounds.points`: the SfM points' box of a `neus-l0 colmap` scene.
- `neus_l0.bounds.occupancy`: the occupancy grid kept from the SDF during training.
- `neus_l0.bounds.pixel_pool`: the pixels whose rays can reach the surface.
"""
