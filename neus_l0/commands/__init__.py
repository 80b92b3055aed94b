"""One module per `neus-l0` subcommand: `add_parser(subparsers, name)` and `run(args)`."""
