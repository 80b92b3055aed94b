"""`neus_l0.experiments.arms` and `tools/bench_fast_vs_neus.py`: the verdict on hand-made curves,
and one end-to-end run of the tool on a tiny scene."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from neus_l0.experiments import arms
from neus_l0.experiments.runner import RunSpec, read_spec

TOOL = Path(__file__).resolve().parents[2] / "tools" / "bench_fast_vs_neus.py"


def _curve(*points):
    """Curve points from (seconds, overall) pairs, iterations 10, 20, ..."""
    return [{"seconds": s, "iteration": 10 * (i + 1), "accuracy": None, "completeness": None,
             "overall": o, "mesh_s": 0.1} for i, (s, o) in enumerate(points)]


def test_verdict_fast_reaches_neus_and_keeps_improving():
    neus = _curve((120.0, 3.0), (240.0, 2.0), (360.0, 1.6), (481.0, 1.5))
    fast = _curve((30.0, 2.5), (60.0, 1.5), (90.0, 1.2), (121.5, 1.1))
    v = arms.verdict(neus, fast)
    assert v == {"neus_final": 1.5, "neus_seconds": 481.0, "fast_final": 1.1,
                 "fast_seconds": 121.5, "reached_s": 60.0, "reached_iteration": 20,
                 "fast_matches": True, "still_improving": True, "last_two": [1.2, 1.1],
                 "target_met": True}


def test_verdict_fast_never_reaches_or_stalls():
    neus = _curve((100.0, 1.0))
    v = arms.verdict(neus, _curve((10.0, 3.0), (20.0, 2.0), (30.0, 2.5)))
    assert v["reached_s"] is None and v["reached_iteration"] is None
    assert v["fast_matches"] is False and v["still_improving"] is False
    assert v["last_two"] == [2.0, 2.5] and v["target_met"] is False
    # reaches it, but the last point is worse than the one before: not met
    v = arms.verdict(neus, _curve((10.0, 0.9), (20.0, 0.8), (30.0, 0.85)))
    assert (v["reached_s"], v["fast_matches"], v["still_improving"], v["target_met"]) == \
        (10.0, True, False, False)
    # equal to NeuS's final counts as reached; a tie at the end is not improving
    v = arms.verdict(neus, _curve((10.0, 1.0), (20.0, 1.0)))
    assert (v["reached_s"], v["fast_matches"], v["still_improving"]) == (10.0, True, False)


def test_verdict_ignores_unscored_points_and_orders_by_time():
    neus = _curve((50.0, 2.0), (100.0, None))  # the final mesh could not be scored
    fast = list(reversed(_curve((5.0, float("nan")), (10.0, 2.5), (20.0, 1.9))))
    v = arms.verdict(neus, fast)
    assert v["neus_final"] == 2.0 and v["neus_seconds"] == 50.0
    assert v["reached_s"] == 20.0 and v["last_two"] == [2.5, 1.9] and v["target_met"]
    one = arms.verdict(neus, _curve((10.0, 1.0)))
    assert one["fast_matches"] is True and one["still_improving"] is None
    assert one["target_met"] is None and one["last_two"] is None
    assert set(arms.verdict([], fast).values()) == {None}
    assert set(arms.verdict(neus, _curve((1.0, None))).values()) == {None}


def test_summary_table_and_plot_from_hand_made_arms(tmp_path):
    def arm(curve, status="done"):
        row = {"train_seconds": curve[-1]["seconds"], "iterations": curve[-1]["iteration"],
               "its_per_s": 2.0, "peak_mem_mb": 512.0, "accuracy": 1.0,
               "completeness": 2.0, "overall": curve[-1]["overall"], "error": None}
        return {"status": status, "row": row, "curve": curve,
                "timings": {"extract_s": 0.25}, "label": None}

    neus, fast = _curve((10.0, 2.0), (20.0, 1.5)), _curve((5.0, 1.8), (10.0, 1.4))
    scenes = {"demo": {"arms": {
        "fast": arms.arm_summary(arm(fast), "demo", "l0", 10.0),
        "neus": arms.arm_summary(arm(neus), "wmask", "hvs", 20.0)}}}
    scenes["demo"]["verdict"] = arms.verdict(neus, fast)
    table = arms.summary_table(scenes)
    assert "| demo | fast | demo | l0 | 10 | 10 | 20 | 2 | 512 | 0.25 | 1 | 2 | 1.4 | done |" \
        in table
    assert "- demo, neus: 10: 2, 20: 1.5" in table
    assert "first <= it at 10 s (iteration 20)" in table
    assert "still improving (1.8 -> 1.4). Fast arm at or below NeuS's final Chamfer and " \
        "still improving: yes." in table
    png = arms.plot_curves(scenes, tmp_path / "c.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 1000


def test_old_spec_files_load_without_the_new_fields(tmp_path):
    spec = RunSpec(name="a", scene="s", scene_dir="/x", sampler="l0", budget_s=1.0, seed=0,
                   out_dir=str(tmp_path))
    data = {k: v for k, v in spec.__dict__.items() if k not in ("snapshots", "label")}
    (tmp_path / "spec.json").write_text(json.dumps(data))
    old = read_spec(tmp_path / "spec.json")
    assert old.snapshots == [] and old.label is None and old == spec


def _tool():
    spec = importlib.util.spec_from_file_location("bench_fast_vs_neus", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: A tiny network for both arms; budgets end the runs (train.iters is out of reach).
TINY = ["model.sdf.hidden=32", "model.sdf.layers=1", "model.sdf.feature_dim=8",
        "model.sdf.encoding.n_levels=4", "model.sdf.encoding.log2_hashmap_size=10",
        "model.sdf.encoding.finest_resolution=32", "model.color.hidden=16",
        "model.color.layers=1", "render.n_samples=8", "render.n_importance=8",
        "render.up_sample_steps=1", "train.batch_size=32", "train.warm_up=0",
        "train.iters=100000", "train.log_every=20"]


def test_tool_end_to_end(tiny_scene, tmp_path, capsys):
    tool = _tool()
    out = tmp_path / "bench"
    argv = ["--scenes", str(tiny_scene), "--out", str(out), "--neus-conf", "demo",
            "--neus-seconds", "3", "--fast-conf", "demo", "--fast-sampler", "l0",
            "--fast-seconds", "1.5", "--snapshots-per-run", "2", "--threads", "1",
            "--resolution", "24", "--eval-density", "3.0", "--sample-rays", "16",
            "--neus-set", "render.n_importance=16", *TINY]
    assert tool.main(argv) == 0
    printed = capsys.readouterr().out
    assert "| demo | fast |" in printed and "| demo | neus |" in printed
    assert "machine:" in printed and "torch" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["machine"]["torch"] and summary["machine"]["date"]
    for arm, budget in (("fast", 1.5), ("neus", 3.0)):
        run = out / "runs" / f"demo__{arm}"
        ev = json.loads((run / "eval.json").read_text())
        assert ev["label"] == arm and ev["spec"]["snapshots"] == [budget / 2, budget]
        assert ev["spec"]["config"]["sampler"]["name"] == ("l0" if arm == "fast" else "hvs")
        curve = ev["curve"]
        assert len(curve) == 2  # the half-budget snapshot, then the final model
        assert curve[0]["seconds"] >= budget / 2 and curve[0]["iteration"] > 0
        assert curve[0]["iteration"] < curve[1]["iteration"]
        assert curve[-1]["seconds"] == ev["row"]["train_seconds"]
        assert all(p["overall"] > 0 and p["mesh_s"] > 0 for p in curve)
        assert (run / "snapshots" / f"mesh_{curve[0]['iteration']:07d}.ply").is_file()
        assert ev["timings"]["extract_s"] == ev["row"]["mesh_seconds"] > 0
        a = summary["scenes"]["demo"]["arms"][arm]
        assert a["status"] == "done" and a["budget_s"] == budget and a["curve"] == curve
    v = summary["scenes"]["demo"]["verdict"]
    assert v["neus_final"] > 0 and v["fast_final"] > 0 and v["still_improving"] in (True, False)
    assert "Verdict" in (out / "table.md").read_text()
    png = (out / "chamfer_vs_time.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 1000
    # a re-run skips both runs; other settings on the same folder are refused
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/status.json")}
    assert tool.main(argv) == 0
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert tool.main([*argv[:-len(TINY)], "--fast-seconds", "2", *TINY]) == 2
    assert "other settings" in capsys.readouterr().err
    # --arms: only the named arm runs; the other is read as its folder holds it, even when
    # this invocation would have made it otherwise
    (out / "runs" / "demo__neus" / "status.json").unlink()
    again = [*argv[:-len(TINY)], "--fast-seconds", "2", "--arms", "neus", *TINY]
    assert tool.main(again) == 0
    printed = capsys.readouterr().out
    assert "demo__fast: not in --arms" in printed and "| demo | fast |" in printed
    assert (out / "runs" / "demo__neus" / "status.json").is_file()
    assert (out / "runs" / "demo__fast" / "status.json").stat().st_mtime_ns == \
        stamps[out / "runs" / "demo__fast" / "status.json"]


def test_tool_rejects_bad_arguments(tmp_path, capsys):
    tool = _tool()
    base = ["--scenes", "demo", "--out", str(tmp_path / "x")]
    assert tool.main([*base, "--fast-seconds", "0"]) == 2
    assert tool.main([*base, "--snapshots-per-run", "0"]) == 2
    assert tool.main([*base, "sampler=hvs"]) == 2
    assert tool.main([*base, "--neus-conf", "no-such-conf"]) == 2
    assert tool.main([*base, "--arms", "neus,slow"]) == 2
    assert tool.main([*base, "--arms", "budget"]) == 2  # no --budget
    err = capsys.readouterr().err
    assert "--fast-seconds" in err and "--snapshots-per-run" in err and "sampler=hvs" in err
    assert "unknown arm slow" in err and "--arms budget needs --budget" in err
    assert not (tmp_path / "x" / "runs").exists()
    assert tool.snapshot_marks(120.0, 4) == [30.0, 60.0, 90.0, 120.0]
    with pytest.raises(SystemExit):
        tool.main([])
