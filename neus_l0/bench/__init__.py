"""The run-time-against-error benchmark behind `neus-l0 bench`.

* `sweep`: the grid of runs (scene x sampler x budget x seed), the output layout, resumable
  results (``results.csv`` / ``results.json``), the local backend;
* `results`: the results table's columns and its files;
* `runner`: one run (train -> mesh -> Chamfer -> held-out PSNR), in its own process;
* `holdout`: view subsets of a `Scene` for held-out PSNR;
* `sample_distance`: distance of the up-sampled (fine) samples to the true surface;
* `ray_backend`: the same runs as Ray tasks;
* `plots`: figures and the Markdown table in ``DIR/plots/``;
* `arms`: two configs compared side by side (`tools/bench_fast_vs_neus.py`): Chamfer curves
  from snapshot checkpoints, the verdict, table and plot.
"""
