"""From a trained field to a mesh file: extraction, clean-up, memory, texture, pictures.

- `neus_l0.mesh.extract`: the SDF on a grid (dense or sparse blocks), marching cubes in
  world units, vertex colours, export.
- `neus_l0.mesh.memory`: the memory an extraction needs, estimated before it runs.
- `neus_l0.mesh.cleanup`: pymeshlab clean-up.
- `neus_l0.mesh.texture`: UV atlas and texture baking.
- `neus_l0.figures.raster`: headless pictures of meshes.
"""
