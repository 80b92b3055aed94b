"""Issue #27: bad inputs of `neus-l0 eval` and `neus-l0 synth` end in one clear line (exit 2,
no traceback) or a correct result; synth replaces a scene whole or not at all."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

import neus_l0.data.synthetic as synthetic
from neus_l0.cli import main
from neus_l0.data.scene import load_scene
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation import score
from neus_l0.evaluation.cull import dilate_mask

SMALL = ("--width", "32", "--height", "24", "--no-progress")


def _one_line_error(capsys, argv: list[str], *needles: str) -> str:
    """Run the CLI; assert exit 2 and one line on stderr naming `needles`, no traceback."""
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith(f"neus-l0 {argv[0]}: error: "), err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def _eval(tiny_scene, tmp_path, *flags: str) -> list[str]:
    return ["eval", str(tiny_scene / "gt_mesh.ply"), "--scene", str(tiny_scene),
            "--json", str(tmp_path / "r.json"), *flags]


# ------------------------------------------------------------------------------------------
# eval


@pytest.mark.parametrize("workers", ["0", "-2"])
def test_eval_workers_zero_or_negative(tiny_scene, tmp_path, capsys, workers):
    _one_line_error(capsys, _eval(tiny_scene, tmp_path, "--workers", workers),
                    f"--workers {workers}", "-1 (all cores)")
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("density", ["inf", "0", "-0.5", "nan"])
def test_eval_density_not_positive_finite(tiny_scene, tmp_path, capsys, density):
    _one_line_error(capsys, _eval(tiny_scene, tmp_path, "--density", density),
                    "--density", "positive finite")
    assert not (tmp_path / "r.json").exists()


def test_eval_density_too_fine_is_refused_before_sampling(tiny_scene, tmp_path, capsys,
                                                          monkeypatch):
    import neus_l0.mesh.memory as memory

    budget = 4 * 2**30
    monkeypatch.setattr(memory, "available_memory", lambda: budget)

    def never(*_a, **_k):
        raise AssertionError("sampled despite the refusal")

    monkeypatch.setattr(score, "sample_mesh", never)
    err = _one_line_error(capsys, _eval(tiny_scene, tmp_path, "--density", "0.001"),
                          "--density 0.001", "points", "4 GiB is available",
                          "smallest density that fits is about")
    smallest = float(err.rsplit("about ", 1)[1])
    # the density named fits the same budget, and a slightly finer one does not
    gt = trimesh.load(tiny_scene / "gt_mesh.ply", process=False)
    v, f = np.asarray(gt.vertices), np.asarray(gt.faces)
    score.check_sampling(v, f, smallest, budget)
    with pytest.raises(NeusL0Error):
        score.check_sampling(v, f, 0.9 * smallest, budget)


@pytest.mark.parametrize("flag, value", [
    ("--depth-tol", "-100"), ("--depth-tol", "nan"), ("--max-dist", "inf"),
    ("--max-dist", "0"), ("--vmax", "0"), ("--vmax", "inf"), ("--margin-low", "-1"),
    ("--margin-high", "inf"), ("--cull-dilate", "-1"), ("--seed", "-1"),
])
def test_eval_numeric_flags_out_of_range(tiny_scene, tmp_path, capsys, flag, value):
    _one_line_error(capsys, _eval(tiny_scene, tmp_path, flag, value), f"{flag} {value}")
    assert not (tmp_path / "r.json").exists()


def test_eval_unknown_cmap_refused_before_any_work(tiny_scene, tmp_path, capsys, monkeypatch):
    def never(*_a, **_k):
        raise AssertionError("read the ground truth despite the bad --cmap")

    monkeypatch.setattr(score, "load_ground_truth", never)
    _one_line_error(capsys, _eval(tiny_scene, tmp_path, "--cmap", "nosuchcmap",
                                  "--error-maps", str(tmp_path / "maps")),
                    "--cmap nosuchcmap", "not a matplotlib colormap")
    assert not (tmp_path / "maps").exists()


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_eval_json_is_strict_json(tiny_scene, tmp_path, capsys):
    """A mesh far outside the evaluation box scores no point: accuracy is null, not NaN."""
    far = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    far.apply_translation([1e5, 0, 0])
    path = tmp_path / "far.ply"
    far.export(path)
    rc = main(["eval", str(path), "--scene", str(tiny_scene), "--density", "2"])
    out = capsys.readouterr().out
    assert rc == 0
    written = (tmp_path / "far.ply.eval.json").read_text()
    report = _strict(written)
    assert _strict(out.strip().splitlines()[-1]) == report
    assert report["accuracy"] is None and report["overall"] is None
    assert report["counts"]["pred_kept"] == 0
    assert score.finite_json({"a": [math.inf, np.float32(math.nan), 1.5], "b": np.int64(3)}) \
        == {"a": [None, None, 1.5], "b": 3}


def test_eval_long_scoring_shows_progress_bars(tiny_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(score, "PROGRESS_POINTS", 1)
    assert main(_eval(tiny_scene, tmp_path, "--density", "2")) == 0
    err = capsys.readouterr().err
    assert "eval: sampling about" in err and "eval: sample" in err and "eval: thin" in err
    assert main(_eval(tiny_scene, tmp_path, "--density", "2", "--no-progress")) == 0
    err = capsys.readouterr().err
    assert "eval: sampling about" in err and "pt/s" not in err


def test_eval_huge_cull_dilate_is_the_same_disk_fast():
    """--cull-dilate past LARGE_DILATE uses a distance transform: the same disk."""
    import cv2

    from neus_l0.evaluation.cull import LARGE_DILATE

    m = np.zeros((201, 221), bool)
    m[100, 110] = m[10, 5] = True
    r = LARGE_DILATE + 11
    yy, xx = np.mgrid[:2 * r + 1, :2 * r + 1] - r
    disk = (xx**2 + yy**2 <= r**2).astype(np.uint8)
    expected = cv2.dilate(m.astype(np.uint8), disk).astype(bool)
    assert np.array_equal(dilate_mask(m, r), expected)
    assert dilate_mask(m, 10**9).all()  # wider than the image: everything, at once
    assert not dilate_mask(np.zeros((5, 5), bool), 10**9).any()


# ------------------------------------------------------------------------------------------
# synth


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _small_scene(out: Path, views: int) -> Path:
    return synthetic.make_scene("demo", out, views=views, width=32, height=24, gt_voxel=6.0,
                                point_spacing=6.0, progress=False)


@pytest.mark.parametrize("where", ["render", "png"])
def test_synth_interrupted_keeps_the_old_scene(tmp_path, monkeypatch, where):
    out = _small_scene(tmp_path / "scene", views=4)
    before = _snapshot(out)
    calls = {"n": 0}

    def failing(real):
        def wrapped(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 3:
                raise RuntimeError("injected failure")
            return real(*args, **kwargs)
        return wrapped

    if where == "render":  # one view per batch: fails on the third view
        monkeypatch.setattr(synthetic, "RAYS_PER_BATCH", 1)
        monkeypatch.setattr(synthetic, "render_views", failing(synthetic.render_views))
    else:  # fails while writing the second view's image
        monkeypatch.setattr(synthetic, "_write_png", failing(synthetic._write_png))
    with pytest.raises(RuntimeError, match="injected"):
        synthetic.make_scene("demo", out, views=6, width=32, height=24, seed=1,
                             gt_voxel=6.0, point_spacing=6.0, progress=False)
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temporary left
    assert load_scene(out).n_views == 4


def test_synth_fewer_views_leaves_no_stale_images(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["synth", "demo", str(out), "--views", "6", *SMALL]) == 0
    assert main(["synth", "demo", str(out), "--views", "3", *SMALL]) == 0
    for sub in ("image", "mask"):
        assert sorted(p.name for p in (out / sub).iterdir()) == ["000.png", "001.png",
                                                                  "002.png"]
    assert sorted(np.load(out / "cameras_sphere.npz").files) == sorted(
        [f"world_mat_{i}" for i in range(3)] + [f"scale_mat_{i}" for i in range(3)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0
    assert "views        3" in capsys.readouterr().out


def _ply(path: Path, vertices, faces) -> Path:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}",
             "property float x", "property float y", "property float z",
             f"element face {len(faces)}", "property list uchar int vertex_indices",
             "end_header"]
    lines += [" ".join(str(c) for c in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


TETRA = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
TETRA_FACES = [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]


@pytest.mark.parametrize("vertices, faces, why", [
    ([[1, 1, 1]] * 4, TETRA_FACES, "all vertices are the same point"),
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], TETRA_FACES, "zero surface area"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], "lie in one plane"),
    (TETRA, [], "no triangles"),
    ([*TETRA[:3], ["nan", 0, 1]], TETRA_FACES, "NaN or infinite"),
    (TETRA, [[0, 1, 9], *TETRA_FACES[1:]], "do not exist"),
], ids=["one-point", "zero-area", "one-triangle", "no-faces", "nan", "bad-index"])
def test_synth_degenerate_mesh(tmp_path, capsys, vertices, faces, why):
    mesh = _ply(tmp_path / "bad.ply", vertices, faces)
    out = tmp_path / "out"
    _one_line_error(capsys, ["synth", str(mesh), str(out), "--views", "2", *SMALL],
                    str(mesh), why)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.ply"]


def test_synth_solid_mesh_still_works(tmp_path):
    mesh = _ply(tmp_path / "tetra.ply", TETRA, TETRA_FACES)
    out = synthetic.make_scene(str(mesh), tmp_path / "t", views=2, width=32, height=24,
                               point_spacing=8.0, progress=False)
    assert load_scene(out).n_views == 2


@pytest.mark.parametrize("flags, named", [
    (["--views", "0"], "--views 0"), (["--width", "7"], "--width 7"),
    (["--height", "-3"], "--height -3"), (["--spp", "0"], "--spp 0"),
    (["--seed", "-1"], "--seed -1"),
    (["--width", "100000", "--height", "100000"], "of memory"),
])
def test_synth_numeric_flags(tmp_path, capsys, flags, named):
    out = tmp_path / "out"
    _one_line_error(capsys, ["synth", "demo", str(out), "--no-progress", *flags], named)
    assert not out.exists()


def test_synth_never_replaces_a_folder_that_is_not_a_scene(tmp_path, capsys):
    own = tmp_path / "mine"
    own.mkdir()
    (own / "notes.txt").write_text("keep me")
    _one_line_error(capsys, ["synth", "demo", str(own), "--views", "2", *SMALL],
                    str(own), "not a synthetic scene")
    scene = _small_scene(tmp_path / "scene", views=2)
    (scene / "run").mkdir()
    _one_line_error(capsys, ["synth", "demo", str(scene), "--views", "2", *SMALL],
                    "holds run")
    assert (own / "notes.txt").read_text() == "keep me" and (scene / "run").is_dir()
