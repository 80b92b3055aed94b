"""Synthetic scenes with exact ground truth: analytic shapes, a sphere-tracing renderer and the
scene writer (`neus-l0 synth`, the demo, the benchmarks).

- `neus_l0.synthetic.shapes`: analytic SDFs, CSG and the built-in shapes.
- `neus_l0.synthetic.raycast`: the sphere-tracing renderer (textured, shaded, anti-aliased).
- `neus_l0.synthetic.meshes`: a mesh file as a surface the renderer traces.
- `neus_l0.synthetic.scene`: `make_scene`, which writes a NeuS-format folder + ground truth.
"""
