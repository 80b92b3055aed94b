"""Volume rendering of a ray batch: coarse samples, up-sampling, NeuS's unbiased opacity,
compositing with the background (`neus_l0.render.volume`: `render_rays`, `render_image`).
"""
