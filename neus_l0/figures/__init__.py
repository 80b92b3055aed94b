"""Figures comparing samplers on pits and thin structures (`neus-l0 figures`).

- `runs`: pick the runs of one scene / budget / seed from a `neus-l0 bench` folder.
- `views`: cameras for the figures (an overview scene camera, a virtual camera per feature)
  and the crop boxes of the features.
- `render`: headless mesh renders (shaded and coloured by the distance to the true surface).
- `compose`: the side-by-side PNGs of the meshes.
- `ray_weights`: coarse weights and the two up-sampling densities along one ray into a pit.
- `make`: `make_figures` (load the inputs, render the overview and the crops, write the mesh
  figures and the ray figure) and `write_index` (`index.md`, one entry per figure).
- `real`: scenes without ground truth (real data): the samplers' meshes shaded side by side,
  zoomed on the places where they differ most (`disagreement_regions`).
"""
