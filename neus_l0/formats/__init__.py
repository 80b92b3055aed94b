"""Scene formats -> a `neus_l0.data.scene.Scene`: the one door every command loads a user's
scene through, above `data/` (the container) and `bounds/` (the visual hull the sphere needs).

- `neus_l0.formats.neus`: the NeuS format (`load_scene`, `validate_scene`), image reading
  (RGBA: alpha as the mask) and the downscale shared with the other formats.
- `neus_l0.formats.transforms`: transforms.json scenes (NeRF-synthetic, instant-ngp,
  nerfstudio): `read_transforms`, `load_views`.
- `neus_l0.formats.open`: `open_scene` (NeuS format or transforms.json, by what the folder
  holds), `scene_format`, `summarise` (what `neus-l0 inspect` prints).
- `neus_l0.formats.sphere`: the object sphere (``scale_mat``) of formats that give none:
  ``sphere.json``, the masks' visual hull, SfM points or the cameras' look-at point.
- `neus_l0.formats.preview`: the sphere drawn over the views (a PNG to check it by eye).
"""
