"""Configs: built-in files, dotted overrides, clear errors for bad keys and types."""

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import (
    CONFS_DIR,
    config_from_dict,
    dump_config,
    load_config,
    non_default,
    parse_overrides,
    resolve_conf_path,
    to_dict,
)
from neus_l0.config.schema import SAMPLERS, Config, L0Config, SamplerConfig
from neus_l0.errors import ConfigError


def test_wmask_and_womask_match_neus():
    w = load_config("wmask")
    assert (w.train.lr, w.train.warm_up, w.train.iters, w.train.lr_alpha) == (5e-4, 5000, 300000,
                                                                              0.05)
    assert (w.train.batch_size, w.render.n_samples, w.render.n_importance,
            w.render.up_sample_steps) == (512, 64, 64, 4)
    assert (w.train.anneal_end, w.train.igr_weight, w.train.mask_weight) == (0, 0.1, 0.1)
    assert w.render.n_outside == 0 and w.render.perturb and w.sampler.name == "hvs"
    assert (w.model.sdf.hidden, w.model.sdf.layers, w.model.sdf.skip) == (256, 8, [4])
    assert w.model.sdf.encoding.n_freqs == 6 and w.model.color.view_encoding.n_freqs == 4
    assert (w.model.color.hidden, w.model.color.layers) == (256, 4)
    assert w.model.variance.init == 0.3
    wo = load_config("womask")
    assert wo.render.n_outside == 32 and wo.train.anneal_end == 50000
    assert wo.train.mask_weight == 0.0
    assert wo.model.background.encoding.n_freqs == 10
    assert (wo.model.background.layers, wo.model.background.hidden) == (8, 256)


ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("spec", ["wmask", "confs/wmask.yaml", "wmask.yaml", "./confs/wmask.yaml",
                                  "neus_l0/confs/wmask.yaml"])
@pytest.mark.parametrize("where", ["repo", "elsewhere"])
def test_conf_spellings(spec, where, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT if where == "repo" else tmp_path)
    path = resolve_conf_path(spec)
    assert path.name == "wmask.yaml"
    assert path.resolve() == (ROOT / "confs" / "wmask.yaml").resolve()


def test_confs_at_the_repository_root_are_the_only_copy():
    assert CONFS_DIR.resolve() == (ROOT / "confs").resolve()
    assert {p.stem for p in CONFS_DIR.glob("*.yaml")} >= {"demo", "fast", "wmask", "womask"}
    assert not list((ROOT / "neus_l0").rglob("*.yaml"))


def test_absolute_and_relative_paths_are_read_as_they_are(tmp_path, monkeypatch):
    mine = tmp_path / "sub" / "demo.yaml"  # named like a built-in, but another file
    mine.parent.mkdir()
    mine.write_text("train: {iters: 11}\n")
    assert load_config(str(mine)).train.iters == 11
    monkeypatch.chdir(tmp_path)
    assert load_config("sub/demo.yaml").train.iters == 11
    assert load_config("./sub/demo.yaml").train.iters == 11
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(str(tmp_path / "missing.yaml"))
    with pytest.raises(ConfigError, match="no such config file"):
        load_config("other/demo.yaml")  # only confs/ prefixes name built-ins


@pytest.mark.slow
def test_the_wheel_ships_the_configs(tmp_path):
    """A non-editable install finds the built-in configs inside the package."""
    import subprocess
    import sys
    import zipfile

    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", str(ROOT), "-w", str(tmp_path / "dist")],
                   check=True, cwd=tmp_path)
    (wheel,) = (tmp_path / "dist").glob("neus_l0-*.whl")
    with zipfile.ZipFile(wheel) as z:
        z.extractall(tmp_path / "site")
    assert sorted(p.name for p in (tmp_path / "site" / "neus_l0" / "confs").glob("*.yaml")) == \
        sorted(p.name for p in (ROOT / "confs").glob("*.yaml"))
    code = ("import neus_l0.config.load as c; print(c.CONFS_DIR); "
            "print(c.resolve_conf_path('demo')); print(c.load_config('demo').train.iters)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, check=True, text=True,
                         capture_output=True, env={"PYTHONPATH": str(tmp_path / "site"),
                                                   "PATH": "/usr/bin:/bin"}).stdout.split()
    assert out[0] == str(tmp_path / "site" / "neus_l0" / "confs")
    assert out[1] == str(tmp_path / "site" / "neus_l0" / "confs" / "demo.yaml")
    assert out[2] == str(load_config("demo").train.iters)


def test_conf_path(tmp_path):
    p = tmp_path / "mine.yaml"
    p.write_text("sampler: l0-linear\ntrain: {iters: 7}\n")
    cfg = load_config(str(p))
    assert cfg.sampler.name == "l0-linear" and cfg.train.iters == 7
    assert cfg.train.lr == Config().train.lr  # missing keys keep defaults


def test_overrides():
    cfg = load_config("wmask", ["sampler=hvs", "train.iters=2000", "model.sdf.hidden=64",
                                "train.lr=1e-4", "model.sdf.skip=[2]", "render.perturb=false"])
    assert cfg.sampler.name == "hvs" and cfg.train.iters == 2000 and cfg.model.sdf.hidden == 64
    assert cfg.train.lr == pytest.approx(1e-4) and cfg.model.sdf.skip == [2]
    assert cfg.render.perturb is False
    assert parse_overrides(["a.b=1", "a.c=x"]) == {"a": {"b": 1, "c": "x"}}


@pytest.mark.parametrize("override, words", [
    (["model.sdf.hiden=3"], ["model.sdf.hiden", "unknown"]),
    (["nope=1"], ["nope", "unknown"]),
    (["train.iters=abc"], ["train.iters", "integer"]),
    (["train.lr=true"], ["train.lr", "number"]),
    (["render.perturb=3"], ["render.perturb", "true or false"]),
    (["sampler=foo"], ["sampler", "foo"]),
    (["model.sdf=3"], ["model.sdf", "mapping"]),
    (["train.iters"], ["train.iters", "key=value"]),
    (["render.n_importance=30"], ["n_importance", "multiple"]),
    (["render.point_weights=mid"], ["point_weights"]),
])
def test_bad_overrides_name_the_key(override, words):
    with pytest.raises(ConfigError) as exc:
        load_config("wmask", override)
    for w in words:
        assert w in str(exc.value)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="no such config"):
        load_config("does-not-exist")
    p = tmp_path / "bad.yaml"
    p.write_text("train: {iters: [1, 2}\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_config(str(p))
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(str(p))
    p.write_text("train: {batch: 3}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml.*train.batch"):
        load_config(str(p))


def test_round_trip_and_yaml(tmp_path):
    cfg = load_config("demo", ["train.iters=5"])
    assert config_from_dict(to_dict(cfg)) == cfg
    p = tmp_path / "c.yaml"
    p.write_text(dump_config(cfg))
    assert load_config(str(p)) == cfg


def test_every_builtin_config_loads():
    confs = sorted(Path(resolve_conf_path("wmask")).parent.glob("*.yaml"))
    assert {c.stem for c in confs} >= {"wmask", "womask", "demo"}
    for c in confs:
        assert load_config(c.stem).sampler.name in SAMPLERS


def test_one_registry_of_sampler_names():
    from neus_l0.config.schema import SAMPLERS as S
    from neus_l0.sampling.upsample import REGISTRY

    assert SAMPLERS is S and tuple(S) == tuple(REGISTRY)
    assert {"hvs", "l0", "l0-inverse", "l0-linear", "neus-exact"} <= set(S)


def test_sampler_block_and_its_shorthand(tmp_path):
    cfg = load_config("wmask", ["sampler=l0-linear"])
    assert isinstance(cfg.sampler, SamplerConfig) and cfg.sampler.name == "l0-linear"
    assert cfg.sampler.name == "l0-linear"
    assert cfg.sampler.l0_kind() == "linear" and cfg.sampler.l0.pad == SamplerConfig().l0.pad
    cfg = load_config("demo", ["sampler.pad=0.05", "sampler.pad_mode=relative",
                               "sampler.masses=interpolant"])
    assert cfg.sampler.name == "l0" and (cfg.sampler.l0.pad, cfg.sampler.l0.pad_mode) == (0.05,
                                                                                    "relative")
    cfg = load_config("wmask", ["sampler.pad_mode=none"])  # the file's name is kept
    assert (cfg.sampler.name, cfg.sampler.l0.pad_mode) == ("hvs", "none")
    # a bare name over a block changes the name only, in either order
    for items in (["sampler.pad=0.2", "sampler=l0-linear"], ["sampler=l0-linear",
                                                             "sampler.pad=0.2"]):
        s = load_config("wmask", [*items, "sampler.masses=interpolant"]).sampler
        assert (s.name, s.l0.pad) == ("l0-linear", 0.2), items
    p = tmp_path / "block.yaml"
    p.write_text("sampler: {name: l0, pad_mode: relative, pad: 0.05, masses: interpolant}\n")
    s = load_config(str(p), ["sampler=hvs"]).sampler
    assert (s.name, s.l0.pad_mode, s.l0.pad) == ("hvs", "relative", 0.05)
    assert Config(sampler="hvs").sampler == SamplerConfig(name="hvs")
    assert SamplerConfig(name="l0") != SamplerConfig(name="l0", l0=L0Config(pad=0.5))
    p = tmp_path / "s.yaml"
    p.write_text("sampler: {name: l0, kind: inverse, blur: false}\n")
    s = load_config(str(p)).sampler
    assert (s.l0_kind(), s.l0.blur) == ("inverse", False)


def test_old_render_keys_map_to_the_sampler_block(tmp_path):
    p = tmp_path / "old.yaml"
    p.write_text("sampler: l0\nrender: {point_weights: endpoint, weights_as_density: false, "
                 "l0_pad: 0.01, compile_sampler: false, n_samples: 16}\n")
    with pytest.warns(FutureWarning, match="render.compile_sampler"):
        cfg = load_config(str(p))
    s = cfg.sampler
    assert (s.name, s.l0.placement, s.l0.as_density, s.l0.pad) == ("l0", "endpoint", False, 0.01)
    assert (s.l0.blur, s.l0.pad_mode) == (True, "absolute")  # what the old code ran
    assert (SamplerConfig().l0.blur, SamplerConfig().l0.pad) == (False, 0.0)  # the new default
    assert cfg.render.n_samples == 16
    # the new key wins where both are given; old command-line keys still work
    with pytest.warns(FutureWarning):
        cfg = load_config(str(p), ["sampler.pad=0.02", "render.weights_as_density=true"])
    assert cfg.sampler.l0.pad == 0.02 and cfg.sampler.l0.as_density is True
    assert cfg.sampler.l0.placement == "endpoint"
    assert config_from_dict(to_dict(cfg)) == cfg
    assert s.l0.masses == "interpolant"  # what the old code drew from


def test_a_block_dumped_before_masses_keeps_the_interpolant():
    """Runs saved before `sampler.masses` existed resume with the draw they were trained with."""
    old = to_dict(load_config("demo"))
    flat = {**{k: v for k, v in old["sampler"].items() if k != "l0"}, **old["sampler"]["l0"]}
    del flat["masses"]  # the flat block of the time, before `masses` and the `l0` block
    old["sampler"] = flat
    assert config_from_dict(old).sampler.l0.masses == "interpolant"
    assert load_config("demo").sampler.l0.masses == "sections"
    # a hand-written block that sets base_inv_s is not a dump: the default draw
    hand = {**old, "sampler": {"name": "l0", "base_inv_s": 128.0}}
    assert config_from_dict(hand).sampler.l0.masses == "sections"
    assert load_config("fast", ["sampler=l0"]).sampler.l0.masses == "sections"


@pytest.mark.parametrize("override, words", [
    (["sampler.kind=cubic"], ["sampler.l0.kind", "cubic"]),
    (["sampler=hvs", "sampler.kind=exp"], ["sampler.l0.kind", "hvs"]),
    (["sampler=l0-inverse", "sampler.kind=linear"], ["contradicts"]),
    (["sampler.pad_mode=fraction"], ["sampler.l0.pad_mode", "relative"]),
    (["sampler.pad=-1"], ["sampler.l0.pad"]),
    (["sampler.pad=0.05"], ["sampler.l0.pad", "sampler.l0.masses=interpolant"]),
    (["sampler.blur=true"], ["sampler.l0.blur", "sampler.l0.masses=interpolant"]),
    (["sampler.masses=pdf"], ["sampler.l0.masses", "sections"]),
    (["sampler.base_inv_s=0"], ["base_inv_s"]),
    (["sampler.name=nope"], ["sampler.name", "nope", "neus-exact"]),
])
def test_bad_sampler_settings_name_the_key(override, words):
    with pytest.raises(ConfigError) as exc:
        load_config("demo", override)
    for w in words:
        assert w in str(exc.value)


@pytest.mark.parametrize("override,key", [
    ("render.hull.resolution=-1", "render.hull.resolution"),
    ("render.hull.margin_px=-2", "render.hull.margin_px"),
    ("model.sdf.gradient=symbolic", "model.sdf.gradient"),
])
def test_bad_hull_and_gradient_settings_name_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config("demo", [override])


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from("abcd"), st.integers(0, 2), max_size=4),
       st.dictionaries(st.sampled_from("abcd"), st.integers(0, 2), max_size=4),
       st.dictionaries(st.sampled_from("abcd"), st.integers(0, 2), max_size=4))
def test_non_default_keeps_exactly_the_entries_that_differ(top, inner, inner_default):
    values = {**{f"x{k}": v for k, v in top.items()}, "sub": inner}
    defaults = {"xa": 0, "xb": 1, "sub": inner_default}
    got = non_default(values, defaults)
    want = {k: v for k, v in values.items() if k != "sub" and defaults.get(k, None) != v}
    sub = {k: v for k, v in inner.items() if inner_default.get(k, None) != v}
    if sub:
        want["sub"] = sub
    assert got == want
