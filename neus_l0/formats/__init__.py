"""Scene formats -> a `neus_l0.data.scene.Scene`: the one door every command loads a user's
scene through, above `data/` (parsing) and `bounds/` (the visual hull the sphere needs).

- `neus_l0.formats.open`: `open_scene` (NeuS format or transforms.json, by what the folder
  holds), `scene_format`, `summarise` (what `neus-l0 inspect` prints).
- `neus_l0.formats.sphere`: the object sphere (``scale_mat``) of formats that give none:
  ``sphere.json``, the masks' visual hull, SfM points or the cameras' look-at point.
"""
