"""Training NeuS: the run's state, the step, the loop and its callbacks.

- `neus_l0.train.loop`: `train(scene, cfg, run_dir)`, the loop in five stages.
- `neus_l0.train.state`: what the loop and its callbacks share, the training clock.
- `neus_l0.train.step`: one step, written to compile.
- `neus_l0.train.losses`, `schedule`: the loss terms; learning-rate and anneal schedules.
- `neus_l0.train.compile`: `train.compile`, the step through `torch.compile`.
- `neus_l0.train.callbacks`: metrics, progress, validation, checkpoints, snapshots.
- `neus_l0.train.validation`, `tensorboard`, `signals`: validation renders, TensorBoard
  events, SIGTERM / SIGINT as a flag.
"""
