"""The run folder on disk: what training leaves behind and what later commands read.

- `neus_l0.run.checkpoints`: atomic checkpoints, the resume, the trained model of a run.
- `neus_l0.run.lock`: one writer per run folder.
"""
