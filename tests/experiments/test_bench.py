"""`neus-l0 bench`: the sweep's results and resumption, failures, held-out views, the
fine-sample distance probe, plots, and the Ray backend."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.cli import main
from neus_l0.config.load import load_config
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.data.scene import Scene
from neus_l0.data.split import split_views, subset_scene
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.sample_distance import (
    SurfaceDistance,
    fine_points_world,
    object_rays,
)
from neus_l0.experiments.results import COLUMNS, DETERMINISTIC, NUMERIC
from neus_l0.experiments.sample_hook import SampleDistanceHook
from neus_l0.experiments.sweep import SweepSpec, check_spec, default_conf, run_sweep
from neus_l0.formats.neus import load_scene

#: A tiny network and schedule; `train.iters` ends every run long before its budget, so the
#: rows are deterministic (same iterations) and comparable between backends.
TINY = ["model.sdf.hidden=32", "model.sdf.layers=2", "model.sdf.skip=[]",
        "model.sdf.feature_dim=16", "model.sdf.encoding.n_freqs=2", "model.color.hidden=32",
        "model.color.layers=1", "render.n_samples=16", "render.n_importance=16",
        "render.up_sample_steps=2", "train.batch_size=64", "train.warm_up=0",
        "train.iters=8", "train.log_every=4"]
SWEEP = dict(conf="demo", overrides=TINY, holdout=4, device="cpu", threads=1, resolution=24,
             eval_density=3.0, sample_rays=32)


def sweep_spec(out, scenes, samplers, budgets, seeds, **kw) -> SweepSpec:
    return SweepSpec(out, scenes, samplers, budgets, seeds, **{**SWEEP, **kw})
BUDGET = 30.0


@pytest.fixture(scope="module")
def sweep(tiny_scene, tmp_path_factory):
    """A sweep of three runs on the tiny scene: a crashing sampler first, then hvs and l0."""
    out = tmp_path_factory.mktemp("bench") / "sweep"
    outcome = run_sweep(sweep_spec(out, [str(tiny_scene)], ["nope", "hvs", "l0"], [BUDGET], [0]),
                        progress=False)
    return out, outcome


def _csv_rows(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == COLUMNS
        return list(reader)


def test_sweep_writes_results_with_finite_numbers(sweep):
    out, outcome = sweep
    rows = {r["sampler"]: r for r in _csv_rows(out)}
    assert set(rows) == {"nope", "hvs", "l0"}
    for sampler in ("hvs", "l0"):
        r = rows[sampler]
        assert r["status"] == "done" and r["error"] == ""
        for c in NUMERIC:
            if c not in ("pits", "thin") or r[c] != "":
                assert math.isfinite(float(r[c])), (sampler, c, r[c])
        assert int(r["iterations"]) == 8
        assert float(r["overall"]) > 0 and float(r["peak_mem_mb"]) > 10
        run_dir = out / r["run_dir"]
        assert run_dir.name == f"demo__{sampler}__30s__seed0"
        for name in ("config.yaml", "metrics.jsonl", "mesh.ply", "eval.json", "status.json"):
            assert (run_dir / name).is_file(), name
        assert list((run_dir / "checkpoints").glob("ckpt_*.pt"))
        assert (out / r["mesh"]).is_file()
        logged = [json.loads(line) for line in (run_dir / "metrics.jsonl").open()]
        assert [m["iter"] for m in logged] == [4, 8]
        views = json.loads((run_dir / "run.json").read_text())["views"]
        assert views == {"holdout": 4, "n_views": 8, "train": [1, 2, 3, 5, 6, 7],
                         "heldout": [0, 4]}  # the full scene's indices
        spec = json.loads((run_dir / "spec.json").read_text())
        assert spec["config"]["train"]["iters"] == 8  # resolved once, when the sweep began
        assert all(m["sample_dist"] > 0 for m in logged)
        by_kind = json.loads((run_dir / "eval.json").read_text())["chamfer"]["features"]["by_kind"]
        for column, kind in (("pits", "pit"), ("thin", "thin")):  # the demo has both
            want = by_kind[kind]["overall"]
            assert (r[column] == "") if want is None else float(r[column]) == pytest.approx(want)
    assert json.loads((out / "results.json").read_text()) == outcome.rows
    assert (out / "scenes" / "demo").exists()


def test_runs_record_their_last_step_and_the_psnr_stride(sweep, tiny_scene):
    from neus_l0.experiments.progress import read_step
    from neus_l0.experiments.runner import psnr_stride

    out, _ = sweep
    scene = load_scene(tiny_scene)
    for sampler in ("hvs", "l0"):
        run_dir = out / "runs" / f"demo__{sampler}__30s__seed0"
        step = read_step(run_dir / "progress.json")
        assert step["step"].startswith("held-out PSNR") and step["unit"] == "view"
        assert step["n"] == step["total"] == len(split_views(scene.n_views, 4)[1])
        report = json.loads((run_dir / "eval.json").read_text())
        demo = load_config("demo")
        assert report["psnr_stride"] == psnr_stride(scene.height, scene.width,
                                                    demo.train.val_downscale, 10000)


def test_crashing_run_is_recorded_and_the_sweep_goes_on(sweep):
    out, outcome = sweep
    assert outcome.ran == ["demo__nope__30s__seed0", "demo__hvs__30s__seed0",
                           "demo__l0__30s__seed0"]
    failed = next(r for r in outcome.rows if r["sampler"] == "nope")
    assert failed["status"] == "failed"
    assert "ConfigError" in failed["error"] and "nope" in failed["error"]
    assert "\n" not in failed["error"]
    status = json.loads((out / failed["run_dir"] / "status.json").read_text())
    assert status["status"] == "failed"


def test_rerun_skips_finished_runs(sweep):
    out, _ = sweep
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/status.json")}
    again = run_sweep(sweep_spec(out, [str(Path(out / "scenes" / "demo").resolve())],
                                 ["hvs", "l0"], [BUDGET], [0]), progress=False)
    assert again.ran == []
    assert sorted(again.skipped) == ["demo__hvs__30s__seed0", "demo__l0__30s__seed0"]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert len(again.rows) == 3  # the failed run stays on record


def test_other_settings_on_the_same_folder_are_refused(sweep):
    out, _ = sweep
    with pytest.raises(NeusL0Error, match="other settings"):
        run_sweep(sweep_spec(out, [str(out / "scenes" / "demo")], ["hvs"], [BUDGET], [0],
                             holdout=2), progress=False)


def test_the_mesh_steps_are_settings_of_the_sweep_and_of_each_run(sweep, tmp_path):
    """`bench --close-underside`, `--drop-outside-masks`, `--inset`, `--fill-missed` and
    `--photo-carve` reach every run's spec, are recorded in sweep.json, and a folder meshed one
    way refuses the other."""
    out, _ = sweep
    spec = sweep_spec(tmp_path / "s", ["demo"], ["l0"], [BUDGET], [0], close_underside=True,
                      drop_outside_masks=True, inset=0.5, fill_missed=True,
                      photo_carve=True)
    assert spec.settings({})["close_underside"] is True
    assert spec.settings({})["photo_carve"] is True
    assert spec.settings({})["fill_missed"] is True
    assert spec.settings({})["drop_outside_masks"] is True
    assert spec.settings({})["inset"] == 0.5
    plain = sweep_spec(tmp_path / "s", ["demo"], ["l0"], [BUDGET], [0]).settings({})
    assert "close_underside" not in plain and "inset" not in plain
    assert "fill_missed" not in plain and "photo_carve" not in plain
    run = spec.run_spec("demo", tmp_path, "l0", BUDGET, 0, {})
    assert run.close_underside is True and run.drop_outside_masks is True
    assert run.mesh_steps.inset == 0.5 and run.mesh_steps.needs_masks
    assert run.fill_missed is True and run.mesh_steps.fill_missed
    assert run.photo_carve is True and run.mesh_steps.photo_carve
    for steps in ({"close_underside": True}, {"inset": 0.5}, {"fill_missed": True},
                  {"photo_carve": True}):
        with pytest.raises(NeusL0Error, match="other settings"):
            run_sweep(sweep_spec(out, [str(out / "scenes" / "demo")], ["hvs"], [BUDGET], [0],
                                 **steps), progress=False)
    with pytest.raises(NeusL0Error, match="--inset"):
        check_spec(sweep_spec(tmp_path / "s", ["demo"], ["l0"], [BUDGET], [0], inset=-1.0))


def test_plots_are_written(sweep):
    out, _ = sweep
    assert main(["bench", "--plot-only", str(out)]) == 0
    for name in ("chamfer_vs_time.png", "psnr_vs_time.png", "chamfer_vs_iterations.png",
                 "sample_distance.png"):
        data = (out / "plots" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    for name in ("pits_vs_time.png", "thin_vs_time.png"):  # the demo has both kinds
        assert (out / "plots" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = (out / "plots" / "table.md").read_text()
    assert "| demo | hvs | 30 | 1 |" in table and "| demo | l0 | 30 | 1 |" in table
    assert "| pits | thin parts |" in table
    assert "demo__nope__30s__seed0" in table  # listed under the failed runs


def test_cli_rejects_bad_arguments(tmp_path, capsys):
    assert main(["bench", "--scenes", "demo", "--seconds", "1", "--out", str(tmp_path),
                 "--samplers", "hvs,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err
    assert main(["bench", "--scenes", "demo", "--seconds", "1", "--out", str(tmp_path),
                 "sampler=hvs"]) == 2
    assert main(["bench", "--seconds", "1"]) == 2
    assert main(["bench", "--scenes", "demo", "--seconds", "1", "--out", str(tmp_path),
                 "--threads", "-1"]) == 2
    assert main(["bench", "--scenes", "demo", "--seconds", "1", "--out", str(tmp_path),
                 "--psnr-pixels", "0"]) == 2
    assert "--psnr-pixels 0" in capsys.readouterr().err


def test_ray_backend_gives_the_rows_of_the_local_one(sweep, tiny_scene, tmp_path):
    ray = pytest.importorskip("ray")
    out, local = sweep
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = run_sweep(sweep_spec(tmp_path / "ray", [str(tiny_scene)], ["l0"], [BUDGET],
                                      [0], backend="ray"), progress=False)
    finally:
        ray.shutdown()
    (row,) = remote.rows
    (expected,) = [r for r in local.rows if r["sampler"] == "l0"]
    assert row["run_dir"] == expected["run_dir"]
    for c in DETERMINISTIC:
        assert row[c] == pytest.approx(expected[c], rel=1e-6), c
    assert (tmp_path / "ray" / "results.csv").is_file()


# --- held-out views ---------------------------------------------------------------------


def test_psnr_stride_bounds_the_pixels():
    from neus_l0.experiments.runner import psnr_stride

    # 400x300 at stride 3 is 134x100 = 13400 pixels; stride 4 gives 100x75 = 7500
    assert psnr_stride(300, 400, 2, 10000) == 4
    assert psnr_stride(300, 400, 2, 13400) == 3
    assert psnr_stride(300, 400, 2, 10**9) == 2  # never finer than the validation downscale
    assert psnr_stride(1, 1, 0, 1) == 1
    with pytest.raises(ValueError):
        psnr_stride(10, 10, 1, 0)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 2000), st.integers(1, 2000), st.integers(0, 8), st.integers(1, 10**6))
def test_psnr_stride_is_the_smallest_within_budget(h, w, base, pixels):
    from neus_l0.experiments.runner import psnr_stride

    s = psnr_stride(h, w, base, pixels)
    assert s >= max(base, 1)
    assert math.ceil(h / s) * math.ceil(w / s) <= pixels
    if s > max(base, 1):
        assert math.ceil(h / (s - 1)) * math.ceil(w / (s - 1)) > pixels


def test_default_config_by_device():
    assert default_conf("cpu") == "demo" and default_conf("cuda") == "fast"
    cuda = SweepSpec("d", [], [], [], device="cuda:0")
    assert (cuda.conf, cuda.resolution, cuda.eval_density) == ("fast", 256, 0.2)
    cpu = SweepSpec("d", [], [], [], conf="wmask", eval_density=1.0)
    assert (cpu.conf, cpu.resolution, cpu.eval_density) == ("wmask", 128, 1.0)


def test_step_reporter_throttles_and_the_display_follows(tmp_path):
    import io

    from tqdm import tqdm

    from neus_l0.experiments.progress import StepDisplay, StepReporter, read_step

    path = tmp_path / "progress.json"
    assert read_step(path) is None
    report = StepReporter(path, min_interval=3600.0)
    report("held-out PSNR", 0, 3, "view")
    report("held-out PSNR", 1, 3, "view")  # same step within the interval: not written
    assert read_step(path)["n"] == 0
    report("held-out PSNR", 3, 3, "view")  # the step's end is always written
    assert read_step(path)["n"] == 3
    report("mesh", note="no count")  # a new step is always written
    assert read_step(path) == {"step": "mesh", "n": 0, "total": None, "unit": "it",
                               "note": "no count"}
    sink = io.StringIO()
    bar = tqdm(file=sink, mininterval=0)
    display = StepDisplay(bar)
    display.start("run")
    StepReporter(path)("train", 12.5, 30.0, "s", note="it 400")
    display.poll(path)
    assert (bar.desc, bar.n, bar.total, bar.unit) == ("train", 12.5, 30.0, "s")
    assert "it 400" in sink.getvalue()
    StepReporter(path)("mesh")
    display.poll(path)
    assert (bar.desc, bar.n, bar.total) == ("mesh", 0, None)
    assert sink.getvalue().rsplit("\r", 1)[-1].startswith("mesh: 00:0")  # elapsed, no count
    bar.close()


def test_wait_watches_the_run_and_kills_it_at_the_timeout():
    import subprocess
    import sys

    from neus_l0.experiments.runner import _wait

    calls = []
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(1.2)"])
    assert _wait(proc, None, lambda: calls.append(1), every=0.1) == 0
    assert len(calls) >= 3
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    assert _wait(proc, 0.5, None, every=0.1) is None
    assert proc.returncode is not None  # killed and reaped


def test_split_views_holds_out_every_kth():
    train, held = split_views(10, 4)
    assert held == [0, 4, 8] and train == [1, 2, 3, 5, 6, 7, 9]
    assert split_views(5, 0) == ([0, 1, 2, 3, 4], [])
    with pytest.raises(NeusL0Error):
        split_views(3, 1)


def test_subset_scene_excludes_the_heldout_views(tiny_scene):
    scene = load_scene(tiny_scene)
    train, held = split_views(scene.n_views, 3)
    sub = subset_scene(scene, train)
    assert sub.n_views == len(train) == scene.n_views - len(held)
    assert sub.image_names == [scene.image_names[i] for i in train]
    assert not set(sub.image_names) & {scene.image_names[i] for i in held}
    for j, i in enumerate(train):
        assert torch.equal(sub.images[j], scene.images[i])
        assert torch.equal(sub.masks[j], scene.masks[i])
        assert torch.equal(sub.c2w[j], scene.c2w[i])
        assert torch.equal(sub.intrinsics[j], scene.intrinsics[i])
    for i in held:  # no held-out image survives in the training subset
        assert not any(torch.equal(sub.images[j], scene.images[i]) for j in range(sub.n_views))
    with pytest.raises(NeusL0Error):
        subset_scene(scene, [scene.n_views])


# --- the fine-sample distance probe -----------------------------------------------------


def test_surface_distance_to_a_plane_is_exact():
    verts = np.array([[-50.0, -50, 3], [50, -50, 3], [50, 50, 3], [-50, 50, 3]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    surf = SurfaceDistance(verts, faces)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-40, 40, (200, 2))
    h = rng.uniform(-5, 5, 200)
    pts = np.column_stack([xy, 3.0 + h])
    np.testing.assert_allclose(surf(pts), np.abs(h), atol=1e-12)
    on = np.column_stack([xy, np.full(200, 3.0)])
    assert np.abs(surf(on)).max() < 1e-12
    # the nearest-point fallback agrees where the points are the surface itself
    assert np.abs(SurfaceDistance(points=on)(on)).max() == 0.0


def _sphere_scene(radius=0.5, n_views=4, H=12, W=16):
    """In-memory scene of a sphere of `radius` (normalised frame) at the origin, with masks."""
    K = torch.tensor([[W * 1.2, 0, (W - 1) / 2], [0, W * 1.2, (H - 1) / 2], [0, 0, 1.0]])
    c2ws, masks = [], []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = 2.5 * np.array([np.cos(a), np.sin(a), 0.4])
        f = -eye / np.linalg.norm(eye)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = r, np.cross(f, r), f, eye
        c2w = torch.tensor(c2w, dtype=torch.float32)
        o, d = pixel_rays(K, c2w, pixel_grid(H, W).reshape(-1, 2))
        b = (o * d).sum(-1)
        hit = b * b - ((o * o).sum(-1) - radius**2) > 0
        masks.append(hit.float().reshape(H, W))
        c2ws.append(c2w)
    scale = np.diag([40.0, 40.0, 40.0, 1.0])
    scale[:3, 3] = [10.0, -20.0, 5.0]
    return Scene(root=Path("sphere"), images=torch.zeros(n_views, H, W, 3),
                 masks=torch.stack(masks), has_masks=True,
                 intrinsics=K.expand(n_views, 3, 3).clone(), c2w=torch.stack(c2ws),
                 scale_mat=scale, image_names=[f"{i:03d}.png" for i in range(n_views)])


class _AnalyticSphere:
    """Exact world distance to the sphere |x - c| = R (stands in for `SurfaceDistance`)."""

    def __init__(self, center, radius):
        self.center, self.radius = np.asarray(center), radius

    def __call__(self, points):
        return np.abs(np.linalg.norm(points - self.center, axis=-1) - self.radius)


def _sphere_hits(o, d, radius):
    """Entry and exit distances of unit rays through the sphere at the origin: (B, 2)."""
    b = (o * d).sum(-1, keepdim=True)
    disc = (b * b - ((o * o).sum(-1, keepdim=True) - radius**2)).clamp_min(0).sqrt()
    return torch.cat([-b - disc, -b + disc], dim=-1)


def test_object_rays_hit_the_object():
    scene = _sphere_scene()
    o, d = object_rays(scene, 40, seed=3)
    assert len(o) == 40
    b = (o * d).sum(-1)
    assert bool((b * b - ((o * o).sum(-1) - 0.25) > 0).all())
    o2, _ = object_rays(scene, 40, seed=3)
    assert torch.equal(o, o2)  # the same rays for every run


def test_sample_distance_hook_is_zero_for_samples_on_the_surface(monkeypatch):
    scene = _sphere_scene(radius=0.5)
    cfg = load_config("demo", ["render.n_importance=8"])
    surface = _AnalyticSphere(scene.scale_mat[:3, 3], 0.5 * scene.scale_mat[0, 0])
    offset = {"value": 0.0}

    def fake_render(model, origins, dirs, render_cfg, sampler, **kwargs):
        hits = _sphere_hits(origins.double(), dirs.double(), 0.5)  # (B, 2)
        z = hits.repeat(1, render_cfg.n_importance // 2) + offset["value"]
        return SimpleNamespace(t_fine=z)  # (B, n_importance): every sample on the sphere

    monkeypatch.setattr("neus_l0.render.volume.render_rays", fake_render)
    hook = SampleDistanceHook(surface, n_rays=64)
    # float32 rays (|d| = 1 to ~1e-7) limit the exactness to ~1e-6 of the 20-unit radius
    assert hook(10, None, scene, cfg)["sample_dist"] == pytest.approx(0.0, abs=1e-4)
    # every sample moved by -0.1 (normalised) along its ray: the hook reports the mean world
    # distance of those points, each at most 0.1 * 40 world units from the sphere
    offset["value"] = -0.1
    o, d = hook.rays(scene)
    z = _sphere_hits(o.double(), d.double(), 0.5).repeat(1, 4) - 0.1
    dist = surface(fine_points_world(o.double(), d.double(), z, scene.scale_mat))
    assert 0.5 < dist.mean() <= 4.0 + 1e-9
    assert hook(10, None, scene, cfg) == {}  # not due again before iteration 15
    assert hook(10, None, scene, cfg, force=True)["sample_dist"] == pytest.approx(
        dist.mean(), rel=1e-4)


def test_sample_distance_is_measured_at_geometric_iterations():
    hook = SampleDistanceHook(surface=None, growth=1.5)
    measured = [it for it in range(50, 5001, 50) if hook.due(it)]
    assert measured == [50, 100, 150, 250, 400, 600, 900, 1350, 2050, 3100, 4650]
    every = SampleDistanceHook(surface=None, growth=1.0)
    assert all(every.due(it) for it in range(50, 501, 50))
    with pytest.raises(ValueError):
        SampleDistanceHook(surface=None, growth=0.5)


def test_fine_points_world_uses_the_scale_mat():
    o = torch.tensor([[0.0, 0.0, -2.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    z = torch.tensor([[1.5, 2.0, 2.5]])
    S = np.diag([10.0, 10.0, 10.0, 1.0])
    S[:3, 3] = [1.0, 2.0, 3.0]
    pts = fine_points_world(o, d, z, S)
    np.testing.assert_allclose(pts, [[1, 2, -2], [1, 2, 3], [1, 2, 8]], atol=1e-6)


def test_paired_differences_exact():
    from neus_l0.experiments.plots import paired_differences

    def row(sampler, seed, overall, its, budget=60.0, scene="s"):
        return {"scene": scene, "sampler": sampler, "budget_s": budget, "seed": seed,
                "status": "done", "overall": overall, "iterations": its}

    rows = [row("hvs", s, 5.0, 100) for s in range(6)]
    rows += [row("l0", s, 4.0 + 0.1 * s, 200) for s in range(6)]  # lower in all 6 pairs
    rows += [row("l0", 9, 1.0, 100)]                               # no hvs partner: unpaired
    rows += [{**row("hvs", 7, 5.0, 100), "status": "failed"}, row("l0", 7, 9.0, 100)]
    text = paired_differences(rows)
    # differences -1.0, -0.9, ..., -0.5: mean -0.75; sign test 2 * (1/2)^6 = 0.03125
    assert "| l0 | 6 | 6 | -0.750 | -1.000 .. -0.500 | 2.00 | 0.0312 |" in text
    assert paired_differences([row("l0", 0, 1.0, 10)]) == ""


def test_iteration_matched_effect_recovers_an_exact_offset():
    from neus_l0.experiments.plots import iteration_matched_effect

    rows = []
    for scene, a, b in (("s1", 20.0, -1.5), ("s2", 12.0, -0.8)):
        for sampler, g in (("hvs", 0.0), ("l0", -0.25)):
            for its in (300, 700, 1500, 4000):
                rows.append({"scene": scene, "sampler": sampler, "budget_s": float(its),
                             "seed": 0, "status": "done", "iterations": its,
                             "overall": a + b * np.log(its) + g})
    text = iteration_matched_effect(rows)
    # 16 runs, 5 parameters: the noise-free offset is recovered exactly, with zero error
    assert "| l0 | 16 | 2 | -0.250 | 0.000 | 11 |" in text
    assert iteration_matched_effect(rows[:4]) == ""  # one sampler only: nothing to fit


def test_a_score_without_features_has_no_pit_or_thin_column():
    from neus_l0.evaluation.features import kind_overall

    assert kind_overall(None, "pit") is None
    assert kind_overall({"overall": 1.0}, "pit") is None
    assert kind_overall({"features": {"by_kind": {"thin": {"overall": 2.5}}}}, "pit") is None
    assert kind_overall({"features": {"by_kind": {"thin": {"overall": 2.5}}}}, "thin") == 2.5
