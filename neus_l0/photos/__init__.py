"""Own photos -> NeuS-format scene: SfM with pycolmap, the object sphere, undistorted export.

- `neus_l0.photos.sfm`: feature extraction, matching and incremental mapping (pycolmap, CPU).
- `neus_l0.photos.sparse_io`: read a COLMAP sparse model (text or binary) into plain arrays;
  write one in text format.
- `neus_l0.photos.export`: undistortion to a pinhole camera and the NeuS-format writer.
- `neus_l0.photos.pipeline`: the whole chain behind `neus-l0 colmap`.

The sphere comes from `neus_l0.formats.sphere.choose_sphere`, its preview from
`neus_l0.formats.preview`.
"""
