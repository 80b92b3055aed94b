"""Mesh evaluation: Chamfer distance with the DTU protocol or a synthetic scene's ground truth.

Modules (all pure functions on NumPy arrays, world units):

- `pointcloud`: DTU-style triangle sampling and radius thinning of a mesh.
- `chamfer`: chunked nearest-neighbour distances and truncated means.
- `surface`: exact point-to-triangle-mesh distances (synthetic protocol).
- `dtu`: DTU evaluation files (STL points, ObsMask, Plane) and the DTU protocol.
- `synthetic`: a synthetic scene's ground truth (points, depth maps, cameras) and visibility.
- `cull`: IDR / NeuS-style culling of mesh parts outside the dilated object masks.
- `error_maps`: error-coloured PLY files.
- `io`: reading meshes / point clouds and writing PLY files, with one-line errors.
- `score`: `score_mesh`, the whole `neus-l0 eval` pipeline as one function.

`docs/EVALUATION.md` documents the protocol and the JSON that `neus-l0 eval` writes.
"""
