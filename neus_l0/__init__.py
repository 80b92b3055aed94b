"""neus-l0: NeuS surface reconstruction with the L0-Sampler.

The sampler kernels (`neus_l0.sampling.kernels`) are dependency-light and usable on their
own::

    from neus_l0.sampling.kernels import sample_l0
    t_fine = sample_l0(t, weights, n_samples=64, kind="exp")
"""

__version__ = "0.1.0"
