"""`train.compile: auto` (issue #24 item 1): compile when the run repays it, remember compile
times in the user's cache, keep inductor's cache there, and record the choice in the run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from neus_l0.config.load import dump_config, load_config
from neus_l0.errors import ConfigError
from neus_l0.pipelines.demo import check_same_settings as _check_same_settings
from neus_l0.train import cache_folder as cf
from neus_l0.train import compile_auto as ca
from neus_l0.train.compile import compiled_step
from neus_l0.train.loop import train


@pytest.fixture
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_cache_root_honours_xdg_and_falls_back_to_home(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cf.cache_root() == tmp_path / "xdg" / "neus-l0"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cf.cache_root() == tmp_path / "home" / ".cache" / "neus-l0"


def test_inductor_cache_goes_to_ours_unless_the_user_chose_one(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    assert cf.use_persistent_cache() == tmp_path / "neus-l0" / "inductor"
    import os
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "neus-l0" / "inductor")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine"))
    assert cf.use_persistent_cache() == tmp_path / "mine"


def test_saving_and_choice_follow_the_closed_form(one_thread):
    cfg = load_config("demo", ["train.iters=3000", "train.max_seconds=0"])
    step = ca.EAGER_CPU_S_PER_SAMPLE * 128 * (cfg.render.n_samples + cfg.render.n_importance)
    choice = ca.choose_compile(cfg, "cpu")
    assert choice.eager_step_s == pytest.approx(step)
    assert choice.saving_s == pytest.approx(3000 * step * (1 - ca.COMPILED_FRACTION["cpu"]))
    assert choice.compile_s == ca.COLD_COMPILE_S["cpu"] and not choice.warm
    assert choice.compile is (choice.saving_s > choice.compile_s)
    # a resume late in the run has fewer steps to repay the compile with
    late = ca.choose_compile(cfg, "cpu", start_iteration=2900)
    assert late.saving_s == pytest.approx(100 * step * (1 - ca.COMPILED_FRACTION["cpu"]))
    assert not late.compile


@pytest.mark.parametrize("iters,seconds,expect", [
    (50, 0, False),         # a test-sized run: eager
    (3000, 0, True),        # the demo's length: compile
    (100000, 20, False),    # long, but a 20-s time cap leaves too little to repay 45 s with
    (100000, 200, True),    # the demo's time cap
])
def test_auto_compiles_only_long_runs(one_thread, iters, seconds, expect):
    cfg = load_config("demo", [f"train.iters={iters}", f"train.max_seconds={seconds}"])
    assert ca.choose_compile(cfg, "cpu").compile is expect


def test_a_warm_cache_makes_shorter_runs_worth_compiling(one_thread, tmp_path):
    cfg = load_config("demo", ["train.iters=800", "train.max_seconds=0"])
    assert not ca.choose_compile(cfg, "cpu", record={}).compile  # ~33 s saved < 45 s cold
    path = tmp_path / "record.json"
    # the compiled step's key: what `compiled_step` notes, with the analytic gradient
    key = ca.step_key(ca.as_compiled(cfg), "cpu")
    assert key != ca.step_key(cfg, "cpu")  # demo.yaml names autograd
    ca.note_compile(key, 47.0, path)
    once = ca.choose_compile(cfg, "cpu", record=ca.read_record(path))
    assert once.warm and once.compile_s == ca.WARM_COMPILE_S["cpu"] and once.compile
    ca.note_compile(key, 6.5, path)  # the second compile was a warm one
    twice = ca.choose_compile(cfg, "cpu", record=ca.read_record(path))
    assert twice.compile_s == 6.5
    assert json.loads(path.read_text()) == {key: {"compiles": 2, "seconds": 6.5}}


def test_the_record_is_a_hint_never_a_failure(tmp_path):
    bad = tmp_path / "record.json"
    bad.write_text("{not json")
    assert ca.read_record(bad) == {}
    bad.write_text("[1, 2]")
    assert ca.read_record(bad) == {}
    assert ca.read_record(tmp_path / "missing.json") == {}
    blocked = tmp_path / "file"
    blocked.write_text("")
    ca.note_compile("k", 1.0, blocked / "record.json")  # a folder that cannot exist: no error


def test_the_step_key_ignores_the_schedule_but_not_the_graph():
    base = load_config("demo")
    key = ca.step_key(base, "cpu")
    for same in (["train.iters=7"], ["train.lr=1e-3"], ["train.seed=4"],
                 ["train.max_seconds=9"], ["train.compile=true"], ["train.log_every=3"]):
        assert ca.step_key(load_config("demo", same), "cpu") == key, same
    for other in (["train.batch_size=64"], ["render.n_samples=32"], ["sampler=hvs"],
                  ["model.sdf.hidden=32"]):
        assert ca.step_key(load_config("demo", other), "cpu") != key, other
    assert ca.step_key(base, "cuda") != key
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1 if before != 1 else 2)  # kernels are built per thread count
        assert ca.step_key(base, "cpu") != key
        assert ca.step_key(base, "cuda") == ca.step_key(base, "cuda")
    finally:
        torch.set_num_threads(before)


def test_resolving_auto_takes_the_analytic_gradient_only_when_compiling(one_thread):
    long = load_config("demo", ["train.iters=100000", "train.max_seconds=0",
                                "model.sdf.gradient=autograd"])
    cfg, line = ca.resolve_compile(long, "cpu")
    assert cfg.train.compile is True and cfg.model.sdf.gradient == "analytic"
    assert line.startswith("train.compile=auto: compiling") and "analytic" in line
    # the record's key that auto reads is the one the compiled run writes
    assert ca.step_key(cfg, "cpu") == ca.step_key(ca.as_compiled(long), "cpu")
    short = load_config("demo", ["train.iters=20", "model.sdf.gradient=autograd"])
    cfg, line = ca.resolve_compile(short, "cpu")
    assert cfg.train.compile is False and cfg.model.sdf.gradient == "autograd"
    assert line.startswith("train.compile=auto: eager")
    fixed = load_config("demo", ["train.compile=false", "train.iters=100000"])
    assert ca.resolve_compile(fixed, "cpu") == (fixed, None)


def test_a_resume_keeps_the_choice_its_run_made(one_thread, tmp_path):
    ran = load_config("demo", ["train.compile=true", "model.sdf.gradient=analytic"])
    (tmp_path / "config.yaml").write_text(dump_config(ran))
    # auto would say eager this late, but the run compiled: the resume does too
    cfg, line = ca.resolve_compile(load_config("demo"), "cpu", start_iteration=2990,
                                   run_dir=tmp_path)
    assert cfg.train.compile is True and cfg.model.sdf.gradient == "analytic"
    assert "as the run started" in line
    _check_same_settings(tmp_path, cfg)  # a demo re-run is not refused for it
    # a resume that switched compiling off (recorded in resumes.jsonl) is what counts
    (tmp_path / "resumes.jsonl").write_text(json.dumps(
        {"iteration": 1000, "overrides": ["train.compile=false"],
         "changed": ["train.compile"]}) + "\n")
    cfg, _ = ca.resolve_compile(load_config("demo"), "cpu", start_iteration=2990,
                                run_dir=tmp_path)
    assert cfg.train.compile is False


def test_compiled_step_refuses_an_unresolved_auto():
    with pytest.raises(ConfigError, match="resolve"):
        compiled_step(lambda: None, load_config("demo"), torch.device("cpu"))


def test_a_short_run_says_eager_and_records_the_choice(small, sphere_scene, tmp_path, capsys):
    cfg = load_config("demo", small + ["train.iters=4", "train.log_every=2", "train.val_every=0"])
    assert cfg.train.compile == "auto"
    train(sphere_scene(tmp_path / "scene"), cfg, tmp_path / "run", progress=False)
    assert "train.compile=auto: eager" in capsys.readouterr().err
    saved = yaml.safe_load(Path(tmp_path / "run" / "config.yaml").read_text())
    assert saved["train"]["compile"] is False


def test_the_cli_points_inductor_at_our_cache_before_torch_fixes_it(tmp_path):
    """torch sets TORCHINDUCTOR_CACHE_DIR to its /tmp default when torch._dynamo is imported
    (an optimiser does): the CLI must choose ours first, and a user's choice stands."""
    import os
    import subprocess
    import sys

    code = ("import os, torch; from neus_l0.cli import main; main(['config', 'show']); "
            "torch.optim.Adam([torch.zeros(1, requires_grad=True)]); "
            "print(os.environ['TORCHINDUCTOR_CACHE_DIR'])")
    env = {k: v for k, v in os.environ.items() if k != "TORCHINDUCTOR_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.splitlines()[-1]
    assert out == str(tmp_path / "neus-l0" / "inductor")
    env["TORCHINDUCTOR_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.splitlines()[-1]
    assert out == str(tmp_path / "mine")


def test_a_schema_key_added_at_its_default_keeps_every_step_key(monkeypatch):
    """The record outlives schema changes: a new key at its default (in the run's config
    and in the defaults alike) leaves the key as it was; set to another value it moves it."""
    cfg = load_config("demo")
    key = ca.step_key(cfg, "cpu")
    plain = ca.to_dict

    def with_new_key(value, new=3):
        d = plain(value)
        d["model"]["sdf"]["new_knob"] = new if value is cfg else 3
        return d

    monkeypatch.setattr(ca, "to_dict", with_new_key)
    assert ca.step_key(cfg, "cpu") == key
    monkeypatch.setattr(ca, "to_dict", lambda value: with_new_key(value, new=4))
    assert ca.step_key(cfg, "cpu") != key


def test_machine_speed_is_the_measured_over_the_modelled_step_clipped():
    assert ca.machine_speed(None, 0.03) == 1.0
    assert ca.machine_speed(0.06, 0.03) == pytest.approx(2.0)
    assert ca.machine_speed(0.01, 0.03) == 1.0  # a faster machine keeps the expectation
    assert ca.machine_speed(3.0, 0.03) == ca.MAX_SLOWDOWN


@pytest.mark.parametrize("slower,expect", [(1.0, True), (1.5, True), (3.0, False)])
def test_a_slow_machine_expects_a_slower_compile_and_a_capped_demo_stays_eager(
        one_thread, slower, expect):
    """The demo's 124 s cap saves ~68 s by compiling: worth a 45 s compile, not the 135 s a
    machine whose eager step runs 3x the cost model's should expect (such a VM compiled for
    70-170 s, and the demo's first run trained one iteration)."""
    cfg = load_config("demo", ["train.iters=3500", "train.max_seconds=124"])
    modelled = ca.eager_step_seconds(cfg, "cpu")
    choice = ca.choose_compile(cfg, "cpu", record={}, eager_s=slower * modelled)
    assert choice.measured and choice.compile_s == pytest.approx(ca.COLD_COMPILE_S["cpu"]
                                                                 * slower)
    assert choice.saving_s == pytest.approx(124 * (1 - ca.COMPILED_FRACTION["cpu"]))
    assert choice.compile is expect
    key = ca.step_key(ca.as_compiled(cfg), "cpu")  # a warm cache scales the same way
    warm = ca.choose_compile(cfg, "cpu", record={key: {"compiles": 1, "seconds": 50}},
                             eager_s=slower * modelled)
    assert warm.compile_s == pytest.approx(ca.WARM_COMPILE_S["cpu"] * slower)
    cuda = ca.choose_compile(cfg, "cuda", record={}, eager_s=10.0)
    assert cuda.compile_s == ca.COLD_COMPILE_S["cuda"]  # the GPU's constants are launch-bound


def test_a_fresh_demo_decides_compiling_on_a_timed_step(small, tiny_demo, monkeypatch, tmp_path,
                                                        capsys):
    """The demo leaves `auto` to `train`, which times eager steps first (it used to decide
    on the cost model alone, before `train`, and could not see a slow machine)."""
    from neus_l0.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "demo"
    # long enough to be worth timing (`worth_measuring`), too short to repay a compile
    argv = ["demo", "--out", str(out), "--resolution", "32", "--threads", "1", "--quiet",
            *[o for o in small[:-3] if not o.startswith("model.sdf.encoding")],
            "train.iters=60", "train.max_seconds=30", "train.val_every=0",
            "train.compile=auto"]
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "compile: auto" in cap.out
    assert "train.compile=auto: eager" in cap.err and "ms, measured" in cap.err, cap.err
    assert load_config(out / "run" / "config.yaml").train.compile is False
