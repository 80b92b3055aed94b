"""The run configuration: the dataclass schema with its choice lists, loading with dotted
overrides, range checks, and the keys old runs used.

- `neus_l0.config.schema`: the dataclasses (`Config`, one per component), the choice lists.
- `neus_l0.config.load`: `load_config`, `config_from_dict`, `dump_config`, dotted overrides,
  the built-in configs' folder.
- `neus_l0.config.checks`: range checks, one rule per key.
- `neus_l0.config.legacy`: the keys old configs and checkpoints used.

This package imports nothing of neus_l0 but `neus_l0.errors`.
"""
