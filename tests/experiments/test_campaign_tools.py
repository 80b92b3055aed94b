"""`tools/budget_frontier.py` and `tools/pair_features.py` on hand-made bench folders: the
seed-wise merge of several folders, the equal-time comparison, and the paired sign test
over folders that two chains filled side by side; `tools/make_stool.py`'s object; the
sweep tools' pooling and end-to-end paths."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

TOOLS = Path(__file__).resolve().parents[2] / "tools"


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(folder: Path, scene: str, budget: float, seed: int, overall: float,
         wall: float = 0.0, pit: float | None = None, iterations: int = 100) -> Path:
    """A finished run folder as `neus-l0 bench` leaves it (the fields the tools read)."""
    run = folder / "runs" / f"{scene}__l0__{budget:g}s__seed{seed}"
    (run / "checkpoints").mkdir(parents=True)
    by_kind = {"pit": {"overall": pit}} if pit is not None else {}
    each = [{"name": "pit A", "overall": pit}] if pit is not None else []
    (run / "eval.json").write_text(json.dumps({
        "spec": {"scene_dir": f"/scenes/{scene}", "seed": seed, "budget_s": budget},
        "row": {"iterations": iterations},
        "chamfer": {"overall": overall, "features": {"by_kind": by_kind, "each": each}}}))
    (run / "spec.json").write_text("{}")
    ckpt = run / "checkpoints" / "ckpt_0000100.pt"
    ckpt.write_bytes(b"")
    start = (run / "spec.json").stat().st_mtime
    os.utime(ckpt, (start + wall, start + wall))
    return run


def test_frontier_merges_folders_seed_by_seed(tmp_path):
    bf = _tool("budget_frontier")
    old, a, b = tmp_path / "old", tmp_path / "a", tmp_path / "b"
    for seed, value in enumerate((1.0, 2.0, 3.0)):
        _run(old, "demo", 240, seed, value)
    _run(a, "demo", 240, 0, 0.5)          # a re-run of seed 0 replaces it
    _run(b, "demo", 240, 2, 0.7)          # another chain re-ran seed 2
    _run(b, "demo", 1200, 1, 0.4)         # a budget only the new chain ran
    plan: dict = {}
    for folder in (old, a, b):
        bf.merge(plan, bf.arms(folder))
    assert [r["overall"] for r in plan[("demo", 240.0)]] == [0.5, 2.0, 0.7]
    assert [r["seed"] for r in plan[("demo", 240.0)]] == [0, 1, 2]
    assert [r["overall"] for r in plan[("demo", 1200.0)]] == [0.4]


def test_frontier_compares_with_the_best_demo_arm_that_fits_the_time(tmp_path):
    bf = _tool("budget_frontier")
    plan_dir, demo_dir = tmp_path / "plan", tmp_path / "demo"
    for seed in range(3):
        _run(plan_dir, "demo", 120, seed, 1.0 + 0.1 * seed, wall=118)
        _run(demo_dir, "demo", 60, seed, 1.5, wall=70)       # fits 120 s: compared
        _run(demo_dir, "demo", 40, seed, 1.9, wall=50)       # fits, scores worse
        _run(demo_dir, "demo", 600, seed, 0.9, wall=130)     # over 120 s + 5 %: not compared
    text = bf.table(bf.arms(plan_dir), bf.arms(demo_dir))
    row = next(line for line in text.splitlines() if "| 120 s |" in line)
    assert "max_seconds 60:" in row and row.endswith("| 3 of 3 |")
    assert "1.100 [1.00-1.20]" in row


def test_pairs_join_folders_per_side_and_refuse_a_run_given_twice(tmp_path):
    pf = _tool("pair_features")
    offa, offb, ona, onb = (tmp_path / n for n in ("offa", "offb", "ona", "onb"))
    # off 1.0 / on 0.8 on seeds 0-1 (chain a), off 1.0 / on 1.2 on seed 2 (chain b)
    for seed in (0, 1):
        _run(offa, "demo", 240, seed, 1.0, pit=2.0)
        _run(ona, "demo", 240, seed, 0.8, pit=1.0)
    _run(offb, "demo", 240, 2, 1.0, pit=2.0)
    _run(onb, "demo", 240, 2, 1.2, pit=1.0)
    rows = {(r["scene"], r["feature"]): r
            for r in pf.paired_rows([offa, offb], [ona, onb], "overall")}
    total = rows[("demo", "total")]
    assert total["pairs"] == 3 and total["wins"] == "2/3"
    assert total["on/off"] == pytest.approx((0.8 + 0.8 + 1.2) / 3)
    assert total["p"] == pytest.approx(1.0)  # 2 of 3: P(X <= 1) * 2 = 1
    pit = rows[("demo", "all pits")]
    assert pit["wins"] == "3/3" and pit["on/off"] == pytest.approx(0.5)
    assert pit["p"] == pytest.approx(0.25)
    # only one side's folder: the unmatched runs are left out, not paired with anything
    assert rows[("every scene", "total")]["pairs"] == 3
    assert pf.paired_rows([offa], [ona, onb], "overall")[0]["pairs"] == 2
    with pytest.raises(SystemExit, match="in both"):
        pf.paired_rows([offa, offa], [ona], "overall")


def test_pairs_read_a_re_meshed_report_by_name(tmp_path):
    """``--eval NAME``: each run's `neus-l0 eval --json` report (no spec; the scene from the
    run's name) instead of the bench's eval.json."""
    pf = _tool("pair_features")
    off, on = tmp_path / "off", tmp_path / "on"
    for seed, (a, b) in enumerate(((1.0, 0.5), (2.0, 1.0))):
        for folder, value in ((off, a), (on, b)):
            run = _run(folder, "pits", 300, seed, 9.0, pit=9.0)
            (run / "eval_cu.json").write_text(json.dumps({
                "overall": value, "accuracy": value, "completeness": value,
                "features": {"by_kind": {"pit": {"overall": value * 2}}, "each": []}}))
    rows = {(r["scene"], r["feature"]): r
            for r in pf.paired_rows([off], [on], "overall", "eval_cu.json")}
    assert rows[("pits", "total")]["on/off"] == pytest.approx(0.5)
    assert rows[("pits", "all pits")]["wins"] == "2/2"
    assert rows[("pits", "total")]["pairs"] == 2
    # the bench's own reports are still the default
    assert pf.paired_rows([off], [on], "overall")[0]["on/off"] == pytest.approx(1.0)


def test_the_exact_model_is_the_scenes_surface(tiny_scene):
    """The ground-truth points (world units, projected onto the true surface) lie on the
    stand-in's zero level set once taken to the normalised frame."""
    import numpy as np
    import torch

    from neus_l0.evaluation.io import load_points

    floor = _tool("extraction_floor")
    model, scale_mat, name = floor.exact_model(tiny_scene)
    assert name == "demo"
    gt = load_points(tiny_scene / "gt_points.ply")
    normalised = (gt - scale_mat[:3, 3]) / scale_mat[0, 0]
    values = model.sdf.sdf(torch.as_tensor(normalised, dtype=torch.float64))
    assert values.shape == (len(gt), 1)
    assert float(values.abs().max()) * scale_mat[0, 0] < 0.05  # world units
    inside = model.sdf.sdf(torch.zeros(1, 3, dtype=torch.float64))  # the sphere's centre
    assert np.isfinite(float(inside))


def test_the_floor_falls_with_the_resolution_and_bad_folders_get_one_line(tiny_scene,
                                                                          tmp_path, capsys):
    floor = _tool("extraction_floor")
    out = tmp_path / "floor"
    assert floor.main([str(tiny_scene), "--resolutions", "24,64", "--density", "2.0",
                       "--out", str(out)]) == 0
    rows = json.loads((out / "floor.json").read_text())["rows"]
    assert [r["resolution"] for r in rows] == [24, 64]
    assert rows[1]["overall"] < rows[0]["overall"]
    assert rows[0]["cell"] == pytest.approx(rows[1]["cell"] * 63 / 23)
    assert rows[0]["features"] and "| 64 |" in (out / "floor.md").read_text()
    assert (out / "exact_64.ply").is_file()
    capsys.readouterr()
    assert floor.main([str(tmp_path / "nowhere")]) == 2
    assert "not a scene made by `neus-l0 synth`" in capsys.readouterr().err
    assert floor.main([str(tiny_scene), "--resolutions", "4"]) == 2


def test_rescoring_meshes_each_run_as_the_bench_does_and_resumes(tiny_scene, tiny_trained,
                                                                   tmp_path, capsys):
    """`tools/rescore_bench.py`: a run's new eval.json holds the Chamfer of its checkpoint
    meshed at the new resolution (the same numbers as meshing and scoring it by hand), keeps
    the run's training numbers, records where it came from, and a second call skips it."""
    import shutil

    from neus_l0.evaluation.score import ScoreSpec, score_mesh
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run

    rescore = _tool("rescore_bench")
    sweep, out = tmp_path / "sweep", tmp_path / "new"
    run = Path(shutil.copytree(tiny_trained, sweep / "runs" / "demo__l0__60s__seed0"))
    (run / "eval.json").write_text(json.dumps({
        "spec": {"scene_dir": str(tiny_scene), "eval_density": 2.0, "resolution": 16},
        "row": {"iterations": 4, "overall": 9.0, "psnr_heldout": 12.5},
        "chamfer": {"overall": 9.0, "accuracy": 8.0, "completeness": 10.0}}))
    (sweep / "runs" / "unfinished").mkdir()          # no eval.json: skipped, not an error
    assert rescore.main([str(sweep), "--out", str(out), "--resolution", "32"]) == 0
    rec = json.loads((out / "runs" / run.name / "eval.json").read_text())
    by_hand = export_mesh(mesh_from_run(run, 32, "cpu").mesh, tmp_path / "by_hand.ply")
    want = score_mesh(by_hand, ScoreSpec(scene=tiny_scene, density=2.0), log=lambda m: None)
    for key in ("overall", "accuracy", "completeness"):
        assert rec["chamfer"][key] == pytest.approx(want[key])
        assert rec["row"][key] == pytest.approx(want[key])
    assert rec["row"]["iterations"] == 4 and rec["row"]["psnr_heldout"] == 12.5
    assert rec["spec"]["resolution"] == 32
    assert rec["rescored"]["old"]["overall"] == 9.0 and rec["rescored"]["old_resolution"] == 16
    assert (out / "runs" / run.name / "mesh.ply").is_file()
    assert "unfinished: skipped" in capsys.readouterr().err
    before = (out / "runs" / run.name / "eval.json").stat().st_mtime_ns
    assert rescore.main([str(sweep), "--out", str(out), "--resolution", "32"]) == 0
    assert (out / "runs" / run.name / "eval.json").stat().st_mtime_ns == before
    assert rescore.main([str(sweep), "--out", str(sweep)]) == 2
    assert rescore.main([str(sweep), "--out", str(sweep / "runs")]) == 2
    # --out pointed at another sweep: a run folder holding a checkpoint is not written over
    other = tmp_path / "other"
    (other / "runs" / run.name / "checkpoints").mkdir(parents=True)
    (other / "runs" / run.name / "mesh.ply").write_bytes(b"theirs")
    capsys.readouterr()
    assert rescore.main([str(sweep), "--out", str(other)]) == 1
    assert "holds files this tool did not write" in capsys.readouterr().err
    assert (other / "runs" / run.name / "mesh.ply").read_bytes() == b"theirs"
    assert rescore.main([str(tmp_path / "nowhere"), "--out", str(out)]) == 2
    assert "no runs/ folder" in capsys.readouterr().err


def test_accuracy_parts_split_the_distance_and_find_what_hangs_below(tiny_scene, tmp_path):
    """`tools/accuracy_parts.py`: the parts' shares of the summed distance add up to 1 and
    their point shares too; the exact surface scores ~0 everywhere; a slab glued under the
    object (where the scene's cameras, 20-70 degrees above, barely look) is all `under`,
    and it carries the accuracy's excess."""
    import numpy as np
    import trimesh

    from neus_l0.mesh.extract import export_mesh, extract_mesh

    parts = _tool("accuracy_parts")
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0.6, 0.0, 0.8], [0, 0, 1.0]])
    points = np.array([[0, 0, 5.0], [0, 0, 5.0], [0, 0, 5.0], [0, 0, -3.0]])
    assert list(parts.face_parts(normals, points, lowest=0.0)) == ["top", "axis", "other",
                                                                   "under"]
    rng = np.random.default_rng(0)
    dist = rng.uniform(0, 3, 400)
    names = rng.choice(["top", "axis", "other", "under"], 400)
    table = parts.part_table(dist, names)
    assert sum(r["accuracy share"] for r in table) == pytest.approx(1.0)
    assert sum(r["points"] for r in table) == pytest.approx(1.0)
    for r in table:
        assert r["mean"] == pytest.approx(dist[names == r["part"]].mean())
    capped = np.concatenate([dist, [20.0, 20.0]])  # points truncated at the score's cap
    bands = parts.band_table(capped)
    assert sum(b["points"] for b in bands) == pytest.approx(1.0)
    assert sum(b["accuracy share"] for b in bands) == pytest.approx(1.0)
    assert bands[-1]["accuracy share"] == pytest.approx(40.0 / capped.sum())

    floor = _tool("extraction_floor")
    model, scale_mat, _ = floor.exact_model(tiny_scene)
    exact = extract_mesh(model, scale_mat, resolution=64)
    clean = parts.analyse(export_mesh(exact, tmp_path / "exact.ply"), tiny_scene, 8, 20000)
    assert clean["accuracy"] < 1.5 and clean["parts"][3]["points"] < 0.01
    lo, hi = exact.bounds
    slab = trimesh.creation.box(extents=(hi[0] - lo[0], hi[1] - lo[1], 20.0))
    slab.apply_translation(((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] - 10.0))
    hanging = trimesh.util.concatenate([exact, slab])
    rep = parts.analyse(export_mesh(hanging, tmp_path / "hanging.ply"), tiny_scene, 8, 20000)
    under = rep["parts"][3]
    assert under["part"] == "under" and under["points"] > 0.01
    assert under["accuracy share"] > 0.5 and rep["accuracy"] > clean["accuracy"] + 0.5
    assert rep["accuracy without under"] == pytest.approx(clean["accuracy"], abs=0.5)
    assert 0.0 <= rep["under"]["seen against the background in a training view"] <= 1.0
    assert "| under |" in parts.markdown(rep)
    assert parts.main([str(tmp_path / "none.ply"), str(tiny_scene)]) == 2


def test_hash_share_is_one_for_a_lone_label_and_falls_as_the_closed_form():
    """`diagnose_pits.hash_share_table`: a label alone in its cells owns all their traffic
    at every level of a collision-free table; points of another label at the very same spot
    take a share n_b / (n_a + n_b) of it; free samples there, weighted, as w m / (n + w m)."""
    import numpy as np

    diag = _tool("diagnose_pits")
    eye = np.eye(4)
    far_a = np.array([0.31, 0.29, 0.27])   # normalised frame = world (scale_mat = I)
    far_b = np.array([-0.52, -0.48, -0.33])
    pts = np.concatenate([np.tile(far_a, (10, 1)), np.tile(far_b, (1000, 1))])
    labels = np.array([3] * 10 + [1] * 1000)
    rows = diag.hash_share_table(pts, labels, eye, "demo", [22])
    floor = next(r for r in rows if r["label"] == "pit floor")
    levels = [v for k, v in floor.items() if k.startswith("L") and "cells" in k]
    assert len(levels) == 6 and all(v == pytest.approx(1.0) for v in levels)

    shared = np.concatenate([pts, np.tile(far_a, (30, 1))])
    rows = diag.hash_share_table(shared, np.concatenate([labels, [4] * 30]), eye, "demo", [22])
    floor = next(r for r in rows if r["label"] == "pit floor")
    rods = next(r for r in rows if r["label"] == "rods")
    assert floor["L5 (64 cells)"] == pytest.approx(10 / 40)
    assert rods["L0 (16 cells)"] == pytest.approx(30 / 40)

    rows = diag.hash_share_table(pts, labels, eye, "demo", [22], np.tile(far_a, (5, 1)),
                                 weights=(2.0, 3.0))
    floor = next(r for r in rows if r["label"] == "pit floor")
    assert floor["L3 (36 cells)"] == pytest.approx(20 / (20 + 15))


def test_source_visibility_sees_each_pixel_from_its_own_view_and_counts_shares(tiny_scene):
    """A view is its own perfect source (every hit projects back onto its pixel at its
    depth); a view from across the object does not see the far side; the shares sum to 1."""
    import numpy as np

    from neus_l0.evaluation.synthetic import first_hits

    tool = _tool("source_visibility")
    pts, depth, projections = first_hits(tiny_scene)
    v = 0
    hit = np.isfinite(pts[v, ..., 0])
    own = tool.seen_by(pts[v][hit], np.array([v]), depth, projections, tol=0.5)
    assert hit.sum() > 100 and (own == 1).all()
    from neus_l0.data.cameras import decompose_projection

    at = np.stack([decompose_projection(P)[1][:3, 3] for P in projections])
    centre = at.mean(0)
    facing = (at - centre) @ (at[v] - centre)
    far = int(np.argmin(facing))  # the camera most opposite view 0
    across = tool.seen_by(pts[v][hit], np.array([far]), depth, projections, tol=0.5)
    assert across.mean() < 0.5
    rows = tool.visibility_table(tiny_scene, None, 3, 1.5)
    assert rows and all(abs(sum(r["share_seen_by"]) - 1) < 1e-9 for r in rows if r["pixels"])
    assert {r["feature"] for r in rows} == {f["name"] for f in json.loads(
        (tiny_scene / "features.json").read_text())["features"]}
    with pytest.raises(SystemExit, match="no feature named"):
        tool.visibility_table(tiny_scene, ["no such"], 3, 1.5)
    # per-point sources: the same as `seen_by` when every point has the same ones
    same = np.broadcast_to(np.array([far, v]), (int(hit.sum()), 2))
    assert (tool.seen_by_each(pts[v][hit], same, depth, projections, 0.5)
            == tool.seen_by(pts[v][hit], np.array([far, v]), depth, projections, 0.5)).all()
    # sources by the normal only add: no feature is seen by none more often with them
    more = tool.visibility_table(tiny_scene, None, 3, 1.5, normal_sources=2)
    for r, m in zip(rows, more, strict=True):
        assert len(m["share_seen_by"]) == 6 and abs(sum(m["share_seen_by"]) - 1) < 1e-9
        assert m["share_seen_by"][0] <= r["share_seen_by"][0] + 1e-12


def test_photo_cost_profile_scores_a_view_against_itself_as_perfect_at_any_offset(tiny_scene,
                                                                                 monkeypatch):
    """A view as its own source: every plane through a point on a pixel's ray carries the
    patch back onto itself, so the cost is 0 at every offset; with the real sources, each
    feature's shares of the lowest offset sum to 1 and a view sees its own hits."""
    import dataclasses

    import numpy as np
    import torch

    from neus_l0.data.patches import ncc
    from neus_l0.evaluation.synthetic import first_hits
    from neus_l0.formats.neus import load_scene
    from neus_l0.train.photometric import PhotoContext, sample_gray

    # the tool imports its sibling as a script does (its own folder first on the path)
    monkeypatch.setitem(sys.modules, "source_visibility", _tool("source_visibility"))
    tool = _tool("photo_cost_profile")
    scene = load_scene(tiny_scene)
    ctx = PhotoContext.from_scene(scene, 3, 3, 1, 2)
    own = dataclasses.replace(ctx, sources=torch.arange(scene.n_views)[:, None])
    pts, depth, projections = first_hits(tiny_scene)
    ys, xs = np.nonzero(np.isfinite(pts[0, ..., 0]))
    keep = (xs > 2) & (xs < scene.width - 3) & (ys > 2) & (ys < scene.height - 3)
    xy = torch.tensor(np.stack([xs[keep], ys[keep]], -1), dtype=torch.float32)
    scale, centre = float(scene.scale_mat[0, 0]), np.asarray(scene.scale_mat[:3, 3])
    cam = scene.c2w[0, :3, 3].double().numpy()
    pix = xy[:, None, :] + ctx.offsets[None]
    ref, _ = sample_gray(ctx.gray, ctx.height, ctx.width, torch.zeros(1, dtype=torch.long), pix)
    itself = (1.0 - ncc(ref, ref[:, None, :])) * 0.5  # 0 but for ncc's eps on flat patches
    for d in (-0.05, 0.0, 0.1):  # normalised units along each ray
        xw = (pts[0][ys[keep], xs[keep]] - centre) / scale
        ray = (xw - cam) / np.linalg.norm(xw - cam, axis=-1, keepdims=True)
        x = torch.tensor(xw + d * ray, dtype=torch.float32)
        normal = torch.tensor(cam - xw, dtype=torch.float32)  # facing the camera
        cost, valid = tool.source_costs(own, 0, xy, x, normal / normal.norm(dim=-1,
                                                                             keepdim=True))
        assert valid.float().mean() > 0.9
        assert torch.allclose(cost[valid[:, 0]], itself[valid[:, 0]], atol=1e-4)
    rows = tool.profile(tiny_scene, None, [-2.0, 0.0, 2.0], 3, 2, 1.0, 50, 1.5)
    assert rows
    for r in rows:
        assert len(r["mean_cost"]) == 3 and 0 <= r["counted"] <= r["pixels"]
        assert r["counted"] == 0 or abs(sum(r["lowest_at"]) - 1) < 1e-9
        for q in (r["seen_quantiles"], r["hidden_quantiles"]):
            assert q == sorted(q)
        assert r["seen_sources"] + r["hidden_sources"] == 3 * r["pixels"]  # 3 sources each
    with pytest.raises(SystemExit, match="no feature named"):
        tool.profile(tiny_scene, ["no such"], [0.0], 3, 2, 1.0, 50, 1.5)
    done = subprocess.run([sys.executable, str(TOOLS / "photo_cost_profile.py"), str(tiny_scene),
                           "--offsets=-1,0,1", "--pixels", "20"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "| d=-1 | d=0 | d=1 |" in done.stdout
    bad = subprocess.run([sys.executable, str(TOOLS / "photo_cost_profile.py"), str(tiny_scene),
                          "--offsets=1,2"], capture_output=True, text=True)
    assert bad.returncode != 0 and "must include 0" in bad.stderr


def test_floor_height_keeps_the_vertices_over_the_floor_and_measures_their_rise():
    import numpy as np

    tool = _tool("floor_height")
    g = np.random.default_rng(0)
    xy = g.uniform(-20, 20, size=(500, 2))
    raised = np.column_stack([xy, np.full(500, 12.5)])  # a floor 2.5 above the true one at 10
    far = np.array([[0.0, 0.0, 60.0], [30.0, 0.0, 12.5]])  # too high / beside the floor
    h = tool.floor_heights(np.vstack([raised, far]), np.array([0.0, 0.0, 10.0]), 7.0, 25.0)
    inside = (np.hypot(xy[:, 0], xy[:, 1]) < 7.0).sum()
    assert h.size == inside > 0 and np.allclose(h, 2.5)


def test_surface_offset_reads_a_shell_of_the_scenes_surface_as_its_offset(tiny_scene, tmp_path,
                                                                          capsys):
    """The true mesh moved 0.4 along its vertex normals: median +0.4, all outside; moved in:
    -0.4, none outside; the true mesh about 0."""
    import numpy as np
    import trimesh

    tool = _tool("surface_offset")
    from neus_l0.synthetic.scene import WORLD_OFFSET
    from neus_l0.synthetic.shapes import Translated, builtin_shape

    gt = trimesh.load(tiny_scene / "gt_mesh.ply", process=False)
    normals = np.asarray(gt.vertex_normals)
    probe = tool.signed_distances(np.asarray(gt.vertices) + 0.2 * normals,
                                  Translated(builtin_shape("demo").sdf, WORLD_OFFSET))
    normals = normals * (1.0 if np.median(probe) > 0 else -1.0)  # outward, whatever the winding
    paths = []
    for k in (0.0, 0.4, -0.4):
        m = trimesh.Trimesh(gt.vertices + k * normals, gt.faces, process=False)
        paths.append(tmp_path / f"m{k:+.1f}.ply")
        m.export(paths[-1])
    assert tool.main([str(tiny_scene), *map(str, paths), "--samples", "20000"]) == 0
    rows = [r.split("|") for r in capsys.readouterr().out.splitlines()[2:]]
    med = [float(r[4]) for r in rows]
    out = [float(r[5]) for r in rows]
    assert abs(med[0]) < 0.05 and med[1] == pytest.approx(0.4, abs=0.05)
    assert med[2] == pytest.approx(-0.4, abs=0.05)
    assert out[1] > 0.95 and out[2] < 0.05
    d = tool.signed_distances(np.zeros((0, 3)), lambda x: x[:, 0])
    assert d.shape == (0,)


def test_the_scenes_world_sdf_is_zero_on_its_true_mesh_and_bad_folders_are_named(tiny_scene,
                                                                                 tmp_path):
    import numpy as np
    import torch
    import trimesh

    from neus_l0.errors import NeusL0Error
    from neus_l0.synthetic.scene import scene_world_sdf

    sdf, name = scene_world_sdf(tiny_scene)
    assert name == "demo"
    gt = np.asarray(trimesh.load(tiny_scene / "gt_mesh.ply", process=False).vertices)
    assert np.abs(sdf(torch.as_tensor(gt, dtype=torch.float64)).numpy()).max() < 1e-3
    with pytest.raises(NeusL0Error, match="scene.json"):
        scene_world_sdf(tmp_path)  # no scene.json
    (tmp_path / "scene.json").write_text('{"source": "bunny.obj"}')
    with pytest.raises(NeusL0Error, match="not a built-in analytic shape"):
        scene_world_sdf(tmp_path)


def test_missed_rays_picks_the_rods_side_pixels_and_reports_each_run(tiny_scene, tiny_trained,
                                                                    capsys):
    """Pixels whose first hit lies on a vertical rod's side, in the mask, are the rod's (not its
    ends, not misses, not off the mask); a run gets one row with that many pixels."""
    import numpy as np

    tool = _tool("missed_rays")
    hits = np.full((1, 2, 4, 3), np.nan)
    hits[0, 0] = [[1.0, 0.0, 5.0], [1.4, 0.0, 5.0], [0.0, 1.0, 0.5], [3.0, 0.0, 5.0]]
    hits[0, 1] = [[0.0, -1.2, 9.0], [0.0, 0.5, 9.8], [0.0, 0.0, 5.0], [0.0, 0.0, 5.0]]
    masks = np.ones((1, 2, 4))
    masks[0, 1, 3] = 0.0
    got = tool.rod_pixels(hits, masks, (0.0, 0.0), 1.0, (0.0, 10.0))
    assert got.tolist() == [[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 2]]
    # the tiny scene's body as one wide "rod" around its vertical axis
    from neus_l0.synthetic.scene import WORLD_OFFSET

    axis = f"{WORLD_OFFSET[0]},{WORLD_OFFSET[1]}"
    assert tool.main([str(tiny_scene), str(tiny_trained), "--axis", axis, "--radius", "80",
                      "--z=-100,200", "--threads", "1"]) == 0
    out = capsys.readouterr().out.splitlines()
    n = int(out[0].split()[0])
    row = out[3].split("|")
    assert n > 0 and int(row[3]) == n and 0.0 <= float(row[4]) <= 1.0
    with pytest.raises(SystemExit, match="--axis"):
        tool.main([str(tiny_scene), str(tiny_trained), "--axis", "1", "--radius", "1",
                   "--z", "0,1"])


def test_fit_exact_sdf_lowers_the_error_and_probes_a_rod_as_its_radius(tiny_scene, capsys):
    """A few steps of the fit lower the L1; across a true cylinder of radius 1.5 (as the
    network and as the exact SDF) the probe reads -1.5 at every height."""
    import numpy as np
    import torch

    tool = _tool("fit_exact_sdf")

    def cylinder(x):  # (N, 3) world -> (N,), axis at (2, 3), radius 1.5
        return torch.hypot(x[:, 0] - 2.0, x[:, 1] - 3.0) - 1.5

    class Net(torch.nn.Module):
        def forward(self, x, count=True):
            return cylinder(x * 10.0 + 1.0)[:, None] / 10.0

    rows = tool.rod_minima(Net(), cylinder, np.full(3, 1.0), 10.0, (2.0, 3.0), [0.0, 5.0])
    assert [r for pair in rows for r in pair] == pytest.approx([-1.5] * 4, abs=1e-3)

    class Ball(torch.nn.Module):  # radius 0.5 at the origin, normalised
        def forward(self, x, count=True):
            return (x.norm(dim=-1) - 0.5)[:, None]

    mesh = tool.fitted_mesh(Ball(), np.array([10.0, 20.0, 30.0]), 4.0, 64)
    r = np.linalg.norm(np.asarray(mesh.vertices) - [10.0, 20.0, 30.0], axis=-1)
    assert r == pytest.approx(np.full(len(r), 2.0), abs=0.02)  # 0.5 x 4 world units
    from neus_l0.config.load import load_config
    from neus_l0.fields.model import make_model

    net = make_model(load_config("demo")).sdf
    target = lambda x: x.norm(dim=-1) - 0.4  # noqa: E731  (a ball, normalised)
    pts = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1) * 0.4
    first = tool.fit(net, target, pts, 1, unit=0.01, log=lambda _: None)
    last = tool.fit(net, target, pts, 40, unit=0.01, seed=1, log=lambda _: None)
    assert last < first
    with pytest.raises(SystemExit, match="--axis"):
        tool.main([str(tiny_scene), "--axis", "1", "--z", "0,1"])


def test_the_stool_and_its_features_agree_in_synths_frame(tmp_path):
    """`tools/make_stool.py`: the mesh, turned z-up as synth turns it (scale 1: 250 across)
    and centred at `WORLD_OFFSET`, has each feature's rod where the feature says: the rod's
    two end rings (32 vertices each) at the named radius from its axis, half its length from
    its centre."""
    import numpy as np
    import trimesh

    from neus_l0.synthetic.scene import WORLD_OFFSET

    assert _tool("make_stool").main([str(tmp_path)]) == 0
    mesh = trimesh.load(tmp_path / "stool.ply")
    mesh.apply_transform([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])  # synth's
    assert np.ptp(mesh.vertices, axis=0).max() == pytest.approx(250.0)
    mesh.apply_translation(np.asarray(WORLD_OFFSET) - mesh.bounds.mean(axis=0))
    feats = json.loads((tmp_path / "features.json").read_text())["features"]
    assert len(feats) == 8 and all(f["kind"] == "thin" for f in feats)
    v = np.asarray(mesh.vertices)
    for f in feats:
        c, a, r = np.asarray(f["center"]), np.asarray(f["axis"]), float(f["name"].split()[1][1:])
        along = (v - c) @ a
        off_axis = np.linalg.norm(v - c - along[:, None] * a, axis=1)
        ring = (np.abs(off_axis - r) < 1e-3) & (np.abs(np.abs(along) - f["radius"]) < 1e-3)
        assert ring.sum() >= 64, f["name"]



def test_sweep_depth_reads_a_true_mesh_as_right(tiny_scene, tmp_path, capsys):
    """`tools/sweep_depth.py` on the scene's own ground-truth mesh: the mesh's depth errors are
    a fraction of a unit (the depth map is unbiased); the table has a row per feature asked
    and the open surface; a bad patch is one line. (At 64x48 a 5x5 patch spans a fifth of the
    object: the sweep's own answer is not judged here; `tests/mesh/test_photo_carve.py` does.)"""
    tool = _tool("sweep_depth")
    feats = json.loads((tiny_scene / "features.json").read_text())["features"]
    name = feats[0]["name"]
    out = tmp_path / "t.json"
    assert tool.main([str(tiny_scene), str(tiny_scene / "gt_mesh.ply"), "--features", name,
                      "--open", "200", "--max-pixels", "200", "--behind", "2",
                      "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["feature"] for r in rows] == [name, "open surface"]
    open_row = rows[1]
    assert open_row["pixels"] > 100 and open_row["mesh_median_abs"] < 0.5
    assert abs(open_row["mesh_median"]) < 0.2
    assert "| open surface |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--patch 4"):
        tool.main([str(tiny_scene), str(tiny_scene / "gt_mesh.ply"), "--patch", "4"])
    with pytest.raises(SystemExit, match="no feature"):
        tool.main([str(tiny_scene), str(tiny_scene / "gt_mesh.ply"), "--features", "nope"])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_carve_consensus_counts_each_ray_in_the_first_ball_that_holds_it(seed):
    tool = _tool("carve_consensus")
    g = np.random.default_rng(seed)
    feats = [{"center": g.uniform(-5, 5, 3).tolist(), "radius": float(g.uniform(1, 6))}
             for _ in range(int(g.integers(0, 5)))]
    points = g.uniform(-8, 8, (50, 3))
    points[0] = np.nan
    got = tool.first_ball(points, feats)
    for i, p in enumerate(points):
        inside = [f for f, b in enumerate(feats)
                  if np.linalg.norm(p - np.asarray(b["center"])) <= b["radius"]]
        assert got[i] == (inside[0] if inside else len(feats))


def test_carve_consensus_runs_on_a_scene_and_writes_its_table(tiny_scene, tmp_path, capsys):
    """End to end on the tiny scene's own ground-truth mesh (at 64x48 the sweep's answers are
    not judged: `tests/mesh/test_photo_carve.py` does that)."""
    tool = _tool("carve_consensus")
    out = tmp_path / "c.json"
    assert tool.main([str(tiny_scene), str(tiny_scene / "gt_mesh.ply"), "--every", "4",
                      "--out", str(out)]) == 0
    assert "pass 1:" in capsys.readouterr().out
    rows = json.loads(out.read_text())["rows"]
    assert all(set(r) == {"feature", "agree", "rays", "overshoot", "mesh_in_front",
                          "sweep_minus_truth"}
               for r in rows)
    mesh = str(tiny_scene / "gt_mesh.ply")
    for argv, named in (([str(tmp_path / "none"), mesh], "features.json"),
                        ([str(tiny_scene), str(tmp_path / "no.ply")], "no.ply: no such mesh"),
                        ([str(tiny_scene), mesh, "--cell", "0"], "--cell 0")):
        with pytest.raises(SystemExit, match=named):
            tool.main(argv)
    # a scene with a mask missing is named before any sweep
    broken = tmp_path / "broken"
    shutil.copytree(tiny_scene, broken)
    next(iter(sorted((broken / "mask").iterdir()))).unlink()
    with pytest.raises(SystemExit, match="mask: views"):
        tool.main([str(broken), mesh])



def _before_after(*args: str) -> str:
    """`tools/pits_before_after.py ARGS`'s output (run as a script: it imports
    pair_features from its own folder)."""
    done = subprocess.run([sys.executable, str(TOOLS / "pits_before_after.py"), *args],
                          capture_output=True, text=True, check=True)
    return done.stdout


def test_before_after_runs_the_issues_setting_against_the_demos(tmp_path):
    from neus_l0.config.load import load_config

    (tmp_path / "scenes" / "cup-49").mkdir(parents=True)  # already synthesised: not again
    lines = _before_after("--out", str(tmp_path), "--scenes", "cup,well", "--seeds", "0,1",
                          "--seconds", "120", "--dry-run").splitlines()
    cmds = [line.split() for line in lines]
    assert cmds[0][3:6] == ["synth", "well", str(tmp_path / "scenes" / "well-49")]
    benches = cmds[1:]
    outs = [c[c.index("--out") + 1] for c in benches]
    assert [Path(o).name for o in outs] == ["ISSUE_cup_0", "NOW_cup_0", "ISSUE_cup_1",
                                            "NOW_cup_1", "ISSUE_well_0", "NOW_well_0",
                                            "ISSUE_well_1", "NOW_well_1"]
    issue, now = benches[:2]
    cfg = load_config("demo").train
    for cmd in (issue, now):
        assert cmd[cmd.index("--scenes") + 1] == str(tmp_path / "scenes" / "cup-49")
        assert cmd[cmd.index("--seconds") + 1] == "120"
        assert cmd[cmd.index("--threads") + 1] == "1"  # one core a run, side by side
    assert issue[-2:] == ["train.photo.weight=0", "train.hit_color_floor=0"]
    assert "--close-underside" not in issue and "--fill-missed" in now
    assert f"train.photo.weight={cfg.photo.weight}" in now and cfg.photo.weight > 0
    assert f"train.hit_color_floor={cfg.hit_color_floor}" in now
    gpu = _before_after("--out", str(tmp_path), "--scenes", "cup", "--seeds", "0",
                        "--device", "cuda", "--dry-run").split()
    assert "--threads" not in gpu and gpu[gpu.index("--device") + 1] == "cuda"


def test_before_after_tables_pair_the_arms_run_by_run(tmp_path):
    for seed, (off, on) in enumerate(((1.0, 0.5), (2.0, 0.8), (1.5, 1.8))):
        _run(tmp_path / f"ISSUE_cup_{seed}", "cup", 300, seed, off, pit=3 * off)
        _run(tmp_path / f"NOW_cup_{seed}", "cup", 300, seed, on, pit=3 * on)
    _before_after("--out", str(tmp_path), "--scenes", "cup", "--seeds", "0,1,2",
                  "--table-only")
    text = (tmp_path / "table.md").read_text()
    total = next(line for line in text.splitlines() if "| cup | total |" in line)
    assert total.split(" | ")[2:7] == ["3", "1.500", "1.033", "0.69", "2/3"]
    assert "## completeness" in text and "| ISSUE | NOW | NOW/ISSUE |" in text


def test_before_after_names_what_it_cannot_do(tmp_path):
    def fails(*args: str) -> str:
        done = subprocess.run([sys.executable, str(TOOLS / "pits_before_after.py"), *args],
                              capture_output=True, text=True)
        assert done.returncode != 0
        return done.stderr

    assert "seeds are integers" in fails("--out", str(tmp_path), "--seeds", "0,x", "--dry-run")
    err = fails("--out", str(tmp_path), "--scenes", "no-such-scene", "--seeds", "0")
    assert "could not synthesise 'no-such-scene'" in err
    (tmp_path / "a-file").write_text("")
    assert "is a file, not a folder" in fails("--out", str(tmp_path / "a-file"), "--dry-run")


def test_tube_rows_are_the_means_inside_each_rods_tube():
    """`tube_errors.tube_rows`: each side's mean over the points in the tube, distances at or
    past max_dist left out; features without an axis or not thin are skipped."""
    import numpy as np

    tool = _tool("tube_errors")
    rod = {"kind": "thin", "name": "rod", "center": np.zeros(3), "radius": 10.0,
           "axis": np.array([0.0, 0.0, 1.0])}
    ball = {"kind": "pit", "name": "pit", "center": np.zeros(3), "radius": 50.0, "axis": None}
    pred = np.array([[1.0, 0, 0], [0, 2.0, 5.0], [0, 0, 30.0], [4.0, 0, 0]])
    dist_pred = np.array([0.5, 1.5, 7.0, np.inf])
    gt = np.array([[0, 1.0, -9.0], [10.0, 0, 0]])
    dist_gt = np.array([2.0, 0.1])
    rows = tool.tube_rows(pred, dist_pred, gt, dist_gt, [ball, rod], tube=5.0, max_dist=20.0)
    assert [r["feature"] for r in rows] == ["rod"]
    r = rows[0]
    assert r["accuracy"] == pytest.approx(1.0) and r["completeness"] == pytest.approx(2.0)
    assert r["overall"] == pytest.approx(1.5) and (r["n_pred"], r["n_gt"]) == (3, 1)


def test_tube_errors_of_the_true_mesh_are_small_and_grow_when_it_moves(tiny_scene, tmp_path):
    """The demo scene's horn (radius 17, so a tube of 22): its own ground-truth mesh scores
    about the ground-truth points' spacing in the tube; moved 4 units along x, both sides
    grow by a unit or more and stay under the shift."""
    import trimesh

    tool = _tool("tube_errors")
    exact = trimesh.load(tiny_scene / "gt_mesh.ply", process=False)
    rows = tool.mesh_tubes(tiny_scene / "gt_mesh.ply", tiny_scene, 22.0, 200000)
    horn = next(r for r in rows if r["feature"].startswith("horn"))
    assert horn["n_pred"] > 100 and horn["n_gt"] > 50
    # point-to-point against ground-truth points 2 units apart: about 1, not 0
    assert horn["accuracy"] < 1.2 and horn["completeness"] < 0.6
    exact.apply_translation([4.0, 0.0, 0.0])
    exact.export(tmp_path / "moved.ply")
    moved = next(r for r in tool.mesh_tubes(tmp_path / "moved.ply", tiny_scene, 22.0,
                                            200000) if r["feature"].startswith("horn"))
    assert horn["accuracy"] + 1.0 < moved["accuracy"] < 4.0
    assert horn["completeness"] + 1.0 < moved["completeness"] < 4.0
    assert tool.main([str(tiny_scene), str(tmp_path / "none.ply")]) == 2
    assert tool.main([str(tiny_scene), str(tmp_path / "moved.ply"), "--points", "2000",
                      "--json", str(tmp_path / "t.json")]) == 0
    assert "horn r17" in (tmp_path / "t.json").read_text()


def test_map_concentration_and_effective_share_have_their_closed_forms():
    """`map_draws`: equal errors have Gini 0 and their top 10 % holds 10 %; one tile holding
    all has Gini 1 - 1/K; a uniform draw keeps the whole batch, and a mixed one keeps
    ``P^2 / sum(1 / p)`` of it, as a plain loop over the pixels gives."""
    md = _tool("map_draws")
    flat = md.concentration(np.full(200, 3.0))
    assert flat["gini"] == pytest.approx(0.0, abs=1e-12) and flat["top10"] == pytest.approx(0.1)
    one = np.zeros(200)
    one[17] = 5.0
    c = md.concentration(one)
    assert c["gini"] == pytest.approx(1 - 1 / 200) and c["top1"] == c["top10"] == 1.0
    assert md.concentration(np.zeros(5)) == {"top1": 0.0, "top10": 0.0, "gini": 0.0}
    assert md.effective_share(np.full(50, 1 / 50)) == pytest.approx(1.0)
    rng = np.random.default_rng(0)
    q = rng.random(50)
    p = 0.3 / 50 + 0.7 * q / q.sum()
    mean_w2 = sum(pi * (1 / (50 * pi)) ** 2 for pi in p)
    assert md.effective_share(p) == pytest.approx(1 / mean_w2, rel=1e-12)
    assert md.effective_share(p) < 1.0
    rows = md.feature_rows(np.full(40, 1 / 40), np.arange(40.0), np.repeat([0, 1], 20),
                           ("a", "b"))
    assert [r["draw_vs_uniform"] for r in rows] == pytest.approx([1.0, 1.0])
    assert [r["error_vs_mean"] for r in rows] == pytest.approx([9.5 / 19.5, 29.5 / 19.5])


def test_map_draws_reads_a_trained_runs_map_per_feature(tiny_scene, small_overrides,
                                                        tmp_path, capsys):
    """A run with the error map: its rows cover the pool, the draw against uniform averages
    to 1 over the pool's pixels, and a run without a map gets one line."""
    from neus_l0.cli import main

    md = _tool("map_draws")
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                 "--threads", "1", *small_overrides, "train.iters=6", "train.save_every=3",
                 "train.log_every=2", "train.error_map.fraction=0.5"]) == 0
    rep = md.report(run, [0.5, 0.8])
    rows = rep["features"]
    pixels = sum(r["pixels"] for r in rows)
    assert pixels > 100 and rows[0]["feature"] in ("nothing", "open surface")
    assert sum(r["draw_vs_uniform"] * r["pixels"] for r in rows) / pixels == \
        pytest.approx(1.0, abs=0.05)
    assert [a["largest_weight"] for a in rep["at_fractions"]] == pytest.approx([2.0, 5.0])
    plain = tmp_path / "plain"
    assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(plain), "--quiet",
                 "--threads", "1", *small_overrides, "train.iters=2"]) == 0
    with pytest.raises(md.NeusL0Error, match="no error map"):
        md.report(plain, [0.5])
    with pytest.raises(md.NeusL0Error, match="run.json"):
        md.report(tmp_path, [0.5])  # not a run folder


def test_underside_heights_ships_the_librarys_plane(tiny_scene, small_overrides, tmp_path):
    """The ``shipped`` height is the one `underside_plane` cuts at; 2 views a vertex never
    counts more vertices than 1; the truth's lowest point is read; a folder that is not a run
    is named."""
    from neus_l0.cli import main
    from neus_l0.mesh.from_run import mesh_from_run, training_views
    from neus_l0.mesh.underside import underside_plane

    uh = _tool("underside_heights")
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                 "--threads", "1", *small_overrides, "train.iters=4"]) == 0
    row = uh.report(run, 48)
    mesh = mesh_from_run(run, 48).mesh
    plane = underside_plane(mesh, *training_views(run))
    assert plane is not None  # the sphere-like early SDF sags below what the views see
    assert row["shipped"] == pytest.approx(plane[1])
    assert np.allclose(row["up"], plane[0])
    assert row["shipped"] >= row["lowest_vertex"] - row["edge"]
    assert row["truth"] is not None and np.isfinite(row["per_view_q10"])
    assert row["per_view_q10"] <= row["per_view_q25"]
    with pytest.raises(uh.NeusL0Error, match="run.json"):
        uh.report(tmp_path, 48)  # not a run folder
