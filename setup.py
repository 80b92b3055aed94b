"""Build-time mapping of the configs: the repository's top-level ``confs/`` (the one source
of the YAMLs) is shipped inside the package as ``neus_l0/confs/``, where an installed
`neus_l0.config` finds them. Everything else about the project is in pyproject.toml."""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["neus_l0", "neus_l0.*"]), "neus_l0.confs"],
    package_dir={"neus_l0.confs": "confs"},
    package_data={"neus_l0.confs": ["*.yaml"]},
)
