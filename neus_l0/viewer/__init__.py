"""The web viewer of a run (`neus-l0 view RUN`, `neus-l0 train --viewer`): a viser page with
the run's mesh, training cameras, curves and validation images, served on the loopback."""
