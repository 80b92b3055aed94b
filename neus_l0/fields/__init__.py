"""NeuS's networks: SDF, colour, single variance, NeRF++ background, and input encodings.

- `neus_l0.fields.model`: `NeuSModel` (a plain container of the networks), `build_model`,
  `make_model` (a run's networks from its seed).
- `neus_l0.fields.sdf`: the SDF network and its spatial gradient `sdf_and_gradient`.
- `neus_l0.fields.color`, `variance`, `background`: the other networks.
- `neus_l0.fields.encodings`: positional encodings, each with a closed-form Jacobian.
- `neus_l0.fields.linear`: weight-norm weights cached outside autograd.
"""
