"""Experiments: runs of the whole method measured against each other (`neus-l0 bench`,
`neus-l0 study`, the tools that compare configurations).

- `sweep`: the grid of runs (scene x sampler x budget x seed), the output layout, resumable
  results (``results.csv`` / ``results.json``), the local backend; `ray_backend`: the same
  runs as Ray tasks; `runner`: one run (train -> mesh -> Chamfer -> held-out PSNR) in its own
  process; `progress`: the sweep's progress bars; `results`: the table's columns and files;
  `plots`: figures and the Markdown table in ``DIR/plots/``.
- `arms`: two configurations side by side (`tools/bench_fast_vs_neus.py`): Chamfer curves
  from snapshot checkpoints, the verdict, table and plot.
- `oracle` / `oracle_report`: NeuS's up-sampling on analytic SDFs, every sampler, exactly
  (`neus-l0 study sampling`).
- `fork` / `fork_report`: the samplers continued from one trained state (`neus-l0 study fork`);
  `frontier`: Chamfer against time per sample budget (`neus-l0 study frontier`).
- `photos_align` / `photos_compare`: the own-photos chain against ground truth
  (`tools/photos_chain.py`).
"""
