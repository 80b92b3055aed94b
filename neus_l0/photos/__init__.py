"""Own photos -> NeuS-format scene: SfM with pycolmap, the object sphere, undistorted export.

- `neus_l0.photos.sfm`: feature extraction, matching and incremental mapping (pycolmap, CPU).
- `neus_l0.photos.sparse_io`: read a COLMAP sparse model (text or binary) into plain arrays;
  write one in text format.
- `neus_l0.photos.sphere`: the object sphere from sparse points and optical axes (pure math).
- `neus_l0.photos.align`: Umeyama similarity alignment and pose errors (pure math).
- `neus_l0.photos.export`: undistortion to a pinhole camera and the NeuS-format writer.
- `neus_l0.photos.preview`: the sphere preview PNG (matplotlib, off-screen).
"""
