"""The fork study and what it reports with: feature errors, paired statistics, the study's
pieces, and its command end to end on a tiny scene."""

from __future__ import annotations

import csv
import json
import math
from math import comb

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.cli import main
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.features import feature_errors, kind_errors, load_features
from neus_l0.evaluation.paired import compare, sign_test_p, t_interval
from neus_l0.evaluation.score import score_mesh
from neus_l0.experiments.fork import ARMS, ForkSpec, collect_rows, train_command, write_view_subset
from neus_l0.experiments.fork_report import paired_rows, summary, to_csv
from neus_l0.experiments.sweep import SweepSpec, snapshot_marks

# ------------------------------------------------------------------------------------------
# Feature errors


def _features():
    return [{"kind": "pit", "name": "p", "center": np.zeros(3), "radius": 1.0, "axis": None},
            {"kind": "pit", "name": "q", "center": np.array([1.5, 0, 0]), "radius": 1.0,
             "axis": None},
            {"kind": "thin", "name": "t", "center": np.array([10.0, 0, 0]), "radius": 0.5,
             "axis": None}]


def test_feature_errors_are_the_means_inside_each_ball():
    pred = np.array([[0, 0, 0], [0.5, 0, 0], [1.2, 0, 0], [10, 0, 0], [20, 0, 0]], float)
    d_pred = np.array([1.0, 3.0, 5.0, 7.0, 100.0])
    gt = np.array([[0, 0, 0.9], [2.4, 0, 0], [10.4, 0, 0]], float)
    d_gt = np.array([2.0, 4.0, math.inf])
    out = {f["name"]: f for f in feature_errors(pred, d_pred, gt, d_gt, _features(), 20.0)}
    # ball p (radius 1 at 0): pred 0, 0.5 -> (1 + 3) / 2; gt (0, 0, 0.9) -> 2
    assert out["p"]["accuracy"] == 2.0 and out["p"]["completeness"] == 2.0
    assert out["p"]["overall"] == 2.0 and (out["p"]["n_pred"], out["p"]["n_gt"]) == (2, 1)
    # ball q (radius 1 at 1.5): pred 0.5, 1.2 -> 4; gt 2.4 -> 4
    assert out["q"]["accuracy"] == 4.0 and out["q"]["completeness"] == 4.0
    # ball t: pred at 10 (7); its one gt point is beyond max_dist -> no completeness
    assert out["t"]["accuracy"] == 7.0 and math.isnan(out["t"]["completeness"])
    assert math.isnan(out["t"]["overall"]) and out["t"]["n_gt"] == 1


def test_kind_errors_count_a_point_in_two_balls_once():
    pred = np.array([[0, 0, 0], [0.75, 0, 0], [1.5, 0, 0]], float)  # 0.75 is in both pits
    d_pred = np.array([1.0, 2.0, 6.0])
    gt = np.array([[10, 0, 0]], float)
    kinds = kind_errors(pred, d_pred, gt, np.array([0.5]), _features(), 20.0)
    assert kinds["pit"]["accuracy"] == 3.0 and kinds["pit"]["n_pred"] == 3
    assert math.isnan(kinds["pit"]["completeness"]) and kinds["pit"]["n_gt"] == 0
    assert kinds["thin"]["completeness"] == 0.5 and kinds["thin"]["n_pred"] == 0
    assert kind_errors(pred, d_pred, gt, np.array([0.5]), [], 20.0) == {}


def test_load_features_refuses_a_malformed_file(tmp_path):
    with pytest.raises(NeusL0Error, match="features.json: missing"):
        load_features(tmp_path)
    (tmp_path / "features.json").write_text(json.dumps(
        {"features": [{"kind": "pit", "name": "x", "center": [0, 0, float("nan")],
                       "radius": 1.0}]}))
    with pytest.raises(NeusL0Error, match="features.json: malformed"):
        load_features(tmp_path)
    (tmp_path / "features.json").write_text('{"features": [{"kind": "pit"}]}')
    with pytest.raises(NeusL0Error, match="malformed"):
        load_features(tmp_path)


def test_score_mesh_reports_the_features_of_a_synthetic_scene(tiny_scene):
    exact = score_mesh(tiny_scene / "gt_mesh.ply", scene=tiny_scene, density=2.0,
                       log=lambda _: None)
    kinds = exact["features"]["by_kind"]
    assert set(kinds) == {"pit", "thin"}
    assert [f["name"] for f in exact["features"]["each"]] == [
        f["name"] for f in load_features(tiny_scene)]
    # the true surface: accuracy exact (point-to-mesh), completeness within the sampling
    for k in kinds.values():
        assert k["accuracy"] < 1e-6 and k["completeness"] < 2.0 and k["n_pred"] > 0


# ------------------------------------------------------------------------------------------
# Paired statistics


def test_sign_test_closed_forms():
    assert sign_test_p(9, 9) == pytest.approx(2 / 512)
    assert sign_test_p(0, 9) == pytest.approx(2 / 512)
    assert sign_test_p(7, 9) == pytest.approx(2 * (1 + 9 + 36) / 512)
    assert sign_test_p(2, 4) == 1.0 and sign_test_p(0, 0) == 1.0
    with pytest.raises(ValueError):
        sign_test_p(5, 4)


@given(st.integers(1, 60).flatmap(lambda n: st.tuples(st.just(n), st.integers(0, n))))
@settings(max_examples=200, deadline=None)
def test_sign_test_is_symmetric_and_a_probability(case):
    n, k = case
    p = sign_test_p(k, n)
    assert 0 < p <= 1 and p == sign_test_p(n - k, n)
    # the tail it sums, computed another way
    tail = sum(comb(n, i) for i in range(n + 1) if min(i, n - i) <= min(k, n - k)) / 2**n
    assert p == pytest.approx(min(1.0, tail if k * 2 != n else 1.0), rel=1e-12)


def test_t_interval_matches_scipy_and_covers_the_mean_at_its_rate():
    from scipy import stats

    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, 7)
    mean, lo, hi = t_interval(x)
    ref = stats.t.interval(0.95, 6, loc=x.mean(), scale=stats.sem(x))
    assert (lo, hi) == pytest.approx(ref, rel=1e-12) and mean == pytest.approx(x.mean())
    covered = sum(lo <= 3.0 <= hi for lo, hi in
                  (t_interval(rng.normal(3.0, 2.0, 5))[1:] for _ in range(4000)))
    assert abs(covered / 4000 - 0.95) < 0.015
    assert t_interval([2.0])[0] == 2.0 and math.isinf(t_interval([2.0])[1])
    assert all(math.isnan(v) for v in t_interval([]))


def test_compare_pairs_values_and_leaves_out_missing_ones():
    c = compare([2.0, 4.0, 5.0, None, 1.0], [1.0, 3.0, 5.0, 1.0, float("nan")])
    assert (c["n"], c["better"], c["ties"]) == (3, 2, 1)
    assert c["diff"] == pytest.approx(-2 / 3)
    assert c["rel"] == pytest.approx(100 * (-0.5 - 0.25 + 0) / 3)
    assert c["p"] == sign_test_p(2, 2) == 0.5
    up = compare([10.0, 11.0], [12.0, 13.0], lower_is_better=False)
    assert up["better"] == 2 and up["diff"] == pytest.approx(2.0)
    with pytest.raises(ValueError):
        compare([1.0], [1.0, 2.0])


# ------------------------------------------------------------------------------------------
# The study's pieces


def test_view_subset_renumbers_images_masks_and_cameras(tiny_scene, tmp_path):
    out = write_view_subset(tiny_scene, [1, 3, 6], tmp_path / "sub")
    assert sorted(p.name for p in (out / "image").iterdir()) == ["000.png", "001.png",
                                                                 "002.png"]
    src, sub = np.load(tiny_scene / "cameras_sphere.npz"), np.load(out / "cameras_sphere.npz")
    for new, old in enumerate([1, 3, 6]):
        assert (sub[f"world_mat_{new}"] == src[f"world_mat_{old}"]).all()
        assert (out / "mask" / f"{new:03d}.png").read_bytes() == \
            (tiny_scene / "mask" / f"{old:03d}.png").read_bytes()
    assert len(sub.files) == 6
    stamp = (out / "views.json").stat().st_mtime_ns
    write_view_subset(tiny_scene, [1, 3, 6], tmp_path / "sub")  # done: kept
    assert (out / "views.json").stat().st_mtime_ns == stamp


def test_view_subset_names_a_missing_camera(tiny_scene, tmp_path):
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    cams = dict(np.load(scene / "cameras_sphere.npz"))
    del cams["world_mat_3"]
    np.savez(scene / "cameras_sphere.npz", **cams)
    with pytest.raises(NeusL0Error, match=r"cameras_sphere.npz: no world_mat_3 for image 003"):
        write_view_subset(scene, [1, 3], tmp_path / "sub")
    assert not (tmp_path / "sub").exists() and not (tmp_path / "sub.tmp").exists()


def test_the_commands_fork_one_hvs_run(tmp_path):
    spec = ForkSpec(tmp_path, ["demo"], base_iters=300, arm_iters=100, threads=2,
                    overrides=["train.lr=1e-3"])
    base = train_command(spec, tmp_path / "d", tmp_path / "base", None, 4)
    assert base[2:4] == ["neus_l0", "train"] and "--stop-at" in base
    assert base[base.index("--stop-at") + 1] == "300" and base[-1] == "train.iters=400"
    assert "sampler=hvs" in base and "train.seed=4" in base and "train.lr=1e-3" in base
    assert base.index("train.lr=1e-3") < base.index("sampler=hvs")
    arm = train_command(spec, tmp_path / "d", tmp_path / "a", "l0 interp", 4)
    assert arm[-4:] == ["--resume", "--change-config", "sampler=l0",
                        "sampler.l0.masses=interpolant"]
    assert arm[arm.index("--threads") + 1] == "2"


@pytest.mark.parametrize("change, match", [
    (dict(arms=["hvs", "l1"]), "unknown l1"), (dict(arms=["l0"]), "include hvs"),
    (dict(arm_iters=0), "--arm-iters 0"), (dict(holdout=1), "--holdout 1"),
    (dict(seeds=[]), "at least one"), (dict(resolution=0), "--resolution 0"),
    (dict(eval_density=float("nan")), "--eval-density nan")])
def test_fork_spec_refuses_what_cannot_run(tmp_path, change, match):
    with pytest.raises(NeusL0Error, match=match):
        ForkSpec(tmp_path, ["demo"], **change).check()


def _row(scene, seed, arm, overall, psnr=20.0):
    return {"scene": scene, "seed": seed, "arm": arm, "sampler": arm, "masses": "sections",
            "iteration": 10, "train_s": 1.0, "overall": overall, "accuracy": overall,
            "completeness": overall, "pit": None, "thin": None, "sample_dist": 1.0,
            "psnr": psnr}


def test_report_pairs_every_arm_with_hvs_over_scenes_and_seeds(tmp_path):
    rows = [_row(s, k, "hvs", 2.0 + k) for s in ("a", "b") for k in range(3)]
    rows += [_row(s, k, "l0", 1.9 + k, psnr=21.0) for s in ("a", "b") for k in range(3)]
    rows += [_row("a", 0, "base", 3.0)]
    c = paired_rows(rows, "overall")["l0"]
    assert (c["n"], c["better"], c["p"]) == (6, 6, sign_test_p(6, 6))
    assert c["diff"] == pytest.approx(-0.1)
    assert paired_rows(rows, "psnr")["l0"]["better"] == 6  # higher PSNR is better
    text = summary(rows, ForkSpec(tmp_path, ["a", "b"]))
    assert "| Chamfer (lower is better) | l0 | 6 | 6 |" in text and "| a | base | 1 |" in text
    lines = list(csv.DictReader(to_csv(rows).splitlines()))
    assert len(lines) == 13 and lines[0]["pit"] == ""


def test_bench_snapshot_marks_and_settings():
    assert snapshot_marks(90, 3) == [30.0, 60.0] and snapshot_marks(90, 1) == []
    assert snapshot_marks(90, 0) == []
    plain = SweepSpec("d", [], [], [], conf="demo")
    assert "snapshots" not in plain.settings({})  # folders from before still match
    assert SweepSpec("d", [], [], [], conf="demo", snapshots=4).settings({})["snapshots"] == 4
    run = SweepSpec("d", [], [], [], conf="demo", snapshots=3).run_spec(
        "demo", "scene", "l0", 90.0, 0, {})
    assert run.snapshots == [30.0, 60.0]  # each run of the sweep checkpoints at its marks


def test_bench_refuses_negative_snapshots(tmp_path, capsys):
    assert main(["bench", "--scenes", "demo", "--seconds", "5", "--out", str(tmp_path / "b"),
                 "--snapshots", "-1"]) == 2
    assert "--snapshots" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# End to end


def test_fork_study_end_to_end(tiny_scene, tmp_path, small_overrides, capsys):
    """Base, two arms, scores and summary on the tiny scene (about a minute)."""
    out = tmp_path / "fork"
    args = ["study", "fork", "--out", str(out), "--scenes", str(tiny_scene), "--seeds", "0",
            "--arms", "hvs,l0", "--base-iters", "6", "--arm-iters", "4", "--resolution", "48",
            "--eval-density", "2.0", *small_overrides,
            "train.compile=false", "train.log_every=2"]
    assert main(args) == 0
    rows = collect_rows(out)
    assert [(r["arm"], r["iteration"], r["sampler"]) for r in rows] == [
        ("base", 6, "hvs"), ("hvs", 10, "hvs"), ("l0", 10, "l0")]
    for r in rows:
        assert r["overall"] > 0 and r["psnr"] > 0 and r["sample_dist"] > 0
        assert r["thin"] is not None  # a blob this early: it may not reach the pit's ball
    run = out / "runs" / "demo__seed0"
    resumes = [json.loads(x) for x in (run / "l0" / "resumes.jsonl").read_text().splitlines()]
    assert resumes[0]["iteration"] == 6 and resumes[0]["changed"] == ["sampler.name"]
    assert "| Chamfer (lower is better) | l0 | 1 |" in (out / "summary.md").read_text()
    # a re-run finds everything done
    stamps = {p: p.stat().st_mtime_ns for p in run.glob("*/score.json")}
    assert main(args) == 0
    assert {p: p.stat().st_mtime_ns for p in run.glob("*/score.json")} == stamps
    # other scoring settings: scored again, not trained again
    ckpts = {p: p.stat().st_mtime_ns for p in run.glob("*/checkpoints/*.pt")}
    assert main([*args, "--resolution", "40"]) == 0
    assert all(json.loads(p.read_text())["scoring"]["resolution"] == 40
               for p in run.glob("*/score.json"))
    assert {p: p.stat().st_mtime_ns for p in run.glob("*/checkpoints/*.pt")} == ckpts
    assert set(ARMS) >= {"hvs", "l0"}


# ------------------------------------------------------------------------------------------
# The budget frontier


def test_time_to_reach_interpolates_between_snapshots():
    from neus_l0.experiments.frontier import time_to_reach

    curve = [(30.0, 100, 4.0), (60.0, 200, 2.0), (90.0, 300, 1.5)]
    assert time_to_reach(curve, 3.0) == pytest.approx(45.0)
    assert time_to_reach(curve, 2.0) == 60.0 and time_to_reach(curve, 5.0) == 30.0
    assert time_to_reach(curve, 1.75) == pytest.approx(75.0)
    assert math.isinf(time_to_reach(curve, 1.0))
    assert time_to_reach([(10.0, 1, None), (20.0, 2, 1.0)], 1.0) == 20.0


def _bench_folder(root, n, runs):
    """A bench folder in the layout `read_bench` reads: sweep.json, results.json, eval.json."""
    (root / "runs").mkdir(parents=True)
    (root / "sweep.json").write_text(json.dumps(
        {"config": {"render": {"n_samples": n, "n_importance": n}}}))
    rows = []
    for scene, seed, sampler, curve in runs:
        name = f"{scene}__{sampler}__90s__seed{seed}"
        (root / "runs" / name).mkdir()
        (root / "runs" / name / "eval.json").write_text(json.dumps({"curve": [
            {"seconds": t, "iteration": i, "overall": c} for t, i, c in curve]}))
        rows.append({"scene": scene, "seed": seed, "sampler": sampler, "status": "done",
                     "budget_s": 90.0, "iterations": curve[-1][1], "overall": curve[-1][2],
                     "run_dir": f"runs/{name}"})
    (root / "results.json").write_text(json.dumps(rows))
    return root


def test_frontier_pairs_each_budget_with_hvs_at_the_largest(tmp_path, capsys):
    from neus_l0.experiments.frontier import frontier_rows, read_bench, reference_arm

    big = _bench_folder(tmp_path / "b32", 32, [
        (s, k, "hvs", [(30, 100, 3.0), (60, 200, 2.0), (90, 300, 1.8)])
        for s in ("a", "b") for k in (0, 1)])
    small = _bench_folder(tmp_path / "b8", 8, [
        (s, k, smp, [(30, 200, 2.5), (60, 400, 1.7 if smp == "l0" else 1.9),
                     (90, 600, 1.6 if smp == "l0" else 1.85)])
        for s in ("a", "b") for k in (0, 1) for smp in ("hvs", "l0")])
    runs = read_bench(big) + read_bench(small)
    assert reference_arm(runs) == ("hvs", "32+32")
    rows = {(r["scene"], r["seed"], r["sampler"], r["samples"]): r for r in frontier_rows(runs)}
    l0 = rows[("a", 0, "l0", "8+8")]
    assert l0["reference"] == 1.8 and l0["overall"] == 1.6
    assert l0["reach_s"] == pytest.approx(30 + 30 * 0.7 / 0.8)
    assert math.isinf(rows[("a", 0, "hvs", "8+8")]["reach_s"])
    assert main(["study", "frontier", "--bench", f"{big},{small}",
                 "--out", str(tmp_path / "f")]) == 0
    text = (tmp_path / "f" / "summary.md").read_text()
    assert "| l0 | 8+8 | 4 | 90 s | 600 | 90 s | 1.600 | -11.1 (-11.1 .. -11.1) | 4 |" in text
    assert "| hvs | 8+8 | 4 |" in text and "0 of 4" in text
    assert "| -13.5, 4 of 4, p = 0.12 | 4 of 4 |" in text  # l0 against hvs at 8+8
    assert (tmp_path / "f" / "frontier.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["study", "frontier", "--bench", str(tmp_path / "none"),
                 "--out", str(tmp_path / "g")]) == 2
    assert "not a bench folder" in capsys.readouterr().err


def test_fork_study_refuses_a_scene_without_ground_truth(tiny_scene, tmp_path, capsys):
    import shutil

    scene = tmp_path / "real"
    for part in ("image", "mask"):
        shutil.copytree(tiny_scene / part, scene / part)
    shutil.copy2(tiny_scene / "cameras_sphere.npz", scene)
    assert main(["study", "fork", "--out", str(tmp_path / "f"), "--scenes",
                 f"{tiny_scene},{scene}", "--seeds", "0"]) == 2
    assert "no gt_mesh.ply" in capsys.readouterr().err
    assert not (tmp_path / "f" / "runs").exists()  # the good first scene did not train
