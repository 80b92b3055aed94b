"""The config's range rules (`neus_l0.config.checks`): one rule per key, every float finite,
numbers that cannot work refused before any work starts, naming the key."""

import dataclasses
import typing

import pytest

from neus_l0.config.checks import RULES
from neus_l0.config.load import CONFS_DIR, load_config
from neus_l0.config.schema import Config
from neus_l0.errors import ConfigError


@pytest.mark.parametrize("override", [
    "render.chunk=0", "render.chunk=-4", "train.save_every=-7", "train.max_seconds=-1",
    "train.lr=.nan", "train.lr=0", "train.lr=-1e-3", "train.lr=.inf", "train.igr_weight=-1",
    "train.lr_alpha=-1", "train.lr_alpha=2", "sampler.l0.pad=.inf", "train.warm_up=-1",
    "train.val_downscale=0", "train.keep_checkpoints=-1", "train.mask_weight=-0.1",
    "train.eikonal_fraction=0", "data.downscale=0", "render.n_samples=1",
    "render.hull.resolution=4", "render.hull.margin_px=-1", "model.variance.init=.nan",
    "model.sdf.skip=[-1]", "model.sdf.encoding.log2_hashmap_size=40", "train.seed=-1",
    "render.occupancy.update_every=0", "sampler.base_inv_s=0",
])
def test_a_number_that_cannot_work_is_refused_naming_its_key(override):
    key = override.split("=")[0]
    with pytest.raises(ConfigError) as exc:
        load_config("demo", [override])
    msg = str(exc.value)
    assert f"{key}:" in msg and len(msg.splitlines()) == 1, msg


def test_every_shipped_config_passes_every_rule():
    for path in sorted(CONFS_DIR.glob("*.yaml")):
        load_config(path.stem)


def _fields(cls, out):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            _fields(hints[f.name], out)
        else:
            out.add((cls, f.name, hints[f.name]))
    return out


def test_every_rule_names_a_real_numeric_field_and_every_int_count_has_a_rule():
    fields = _fields(Config, set())
    names = {(c, n) for c, n, _ in fields}
    assert set(RULES) <= names, set(RULES) - names
    numeric = {(c, n) for c, n, t in fields if t in (int, float, int | None)}
    # numbers that may be any finite value: the seed is a count too; these are free
    free = {("SDFConfig", "bias"), ("VarianceConfig", "init"),
            ("EncodingConfig", "per_level_scale")}  # per_level_scale: a joint rule
    missing = {(c.__name__, n) for c, n in numeric - set(RULES)} - free
    assert not missing, sorted(missing)


def test_boundaries_are_accepted():
    cfg = load_config("demo", ["train.lr_alpha=0", "train.lr_alpha=1", "train.save_every=0",
                               "train.max_seconds=0", "render.chunk=1", "train.warm_up=0"])
    assert cfg.train.lr_alpha == 1 and cfg.render.chunk == 1
