"""Where the fine samples go: NeuS's up-sampling and the draws it can use.

- `neus_l0.sampling.kernels`: pure tensor functions (NeRF's `sample_pdf`, the L0-Sampler
  `sample_l0`, `sample_l0_sections`, NeuS's exact section CDF). Imports nothing of neus_l0.
- `neus_l0.sampling.upsample`: NeuS's up-sampling rounds `up_sample(sdf_fn, ...)`, which
  know no model, and the draw as a one-method `Sampler` chosen by name from one registry.
"""
