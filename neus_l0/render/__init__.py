"""Volume rendering of a ray batch: coarse samples, up-sampling, NeuS's unbiased opacity,
compositing with the background (`neus_l0.render.volume`: `render_rays`, `render_image`).

Novel views: camera paths (`neus_l0.render.cameras`: a turntable orbit fitted to the
training cameras, resized intrinsics), one camera as colour / normal / depth pictures and
the image metrics (`neus_l0.render.views`), and a run folder rendered to frames, videos and
metrics (`neus_l0.pipelines.render_run.render_run`, behind `neus-l0 render`).
"""
