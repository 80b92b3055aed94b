"""Pipelines: what a command does from end to end, built from the rooms below.

- `neus_l0.pipelines.render_run`: a run folder -> frames, videos and image metrics
  (`neus-l0 render`).
- `neus_l0.pipelines.demo`: the built-in scene rendered, trained, meshed, scored and drawn
  (`neus-l0 demo`).
"""
