"""`neus-l0 eval`'s bad inputs (issue #27): numbers out of range and an unknown colour map
refused before any work, strict JSON, a huge cull dilation, a one-point mesh, progress.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import trimesh

from neus_l0.cli import main
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation import score
from neus_l0.evaluation.cull import dilate_mask


def _eval(tiny_scene, tmp_path, *flags: str) -> list[str]:
    return ["eval", str(tiny_scene / "gt_mesh.ply"), "--scene", str(tiny_scene),
            "--json", str(tmp_path / "r.json"), *flags]


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize("workers", ["0", "-2"])
def test_eval_workers_zero_or_negative(tiny_scene, tmp_path, workers, refused):
    refused(_eval(tiny_scene, tmp_path, "--workers", workers),
            f"--workers {workers}", "-1 (all cores)", alone=True)
    assert not (tmp_path / "r.json").exists()


def test_eval_unknown_cmap_refused_before_any_work(tiny_scene, tmp_path, monkeypatch, refused):
    def never(*_a, **_k):
        raise AssertionError("read the ground truth despite the bad --cmap")

    monkeypatch.setattr(score, "load_ground_truth", never)
    refused(_eval(tiny_scene, tmp_path, "--cmap", "nosuchcmap",
                  "--error-maps", str(tmp_path / "maps")),
            "--cmap nosuchcmap", "not a matplotlib colormap", alone=True)
    assert not (tmp_path / "maps").exists()


@pytest.mark.parametrize("density", ["inf", "0", "-0.5", "nan"])
def test_eval_density_not_positive_finite(tiny_scene, tmp_path, density, refused):
    refused(_eval(tiny_scene, tmp_path, "--density", density),
            "--density", "positive finite", alone=True)
    assert not (tmp_path / "r.json").exists()


def test_eval_density_too_fine_is_refused_before_sampling(tiny_scene, tmp_path, monkeypatch,
                                                          refused):
    import neus_l0.device as memory

    budget = 4 * 2**30
    monkeypatch.setattr(memory, "available_memory", lambda: budget)

    def never(*_a, **_k):
        raise AssertionError("sampled despite the refusal")

    monkeypatch.setattr(score, "sample_mesh", never)
    err = refused(_eval(tiny_scene, tmp_path, "--density", "0.001"),
                  "--density 0.001", "points", "4 GiB is available",
                  "smallest density that fits is about", alone=True)
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
def test_eval_numeric_flags_out_of_range(tiny_scene, tmp_path, flag, value, refused):
    refused(_eval(tiny_scene, tmp_path, flag, value), f"{flag} {value}", alone=True)
    assert not (tmp_path / "r.json").exists()


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


def test_eval_huge_cull_dilate_is_the_same_disk_fast():
    """--cull-dilate past LARGE_DILATE uses a distance transform: the same disk."""
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


def test_an_all_equal_vertex_obj_scores_as_the_point_it_is(scene96, tmp_path, capsys,
                                                           one_point_obj):
    """(Was a ZeroDivisionError.) eval: its degenerate triangles give their vertices, so the
    mesh scores as one point on the surface: accuracy 0, completeness the mean distance of the
    ground-truth points to it (those within max_dist)."""
    from neus_l0.evaluation.chamfer import truncated_mean
    from neus_l0.evaluation.io import load_points

    gt = trimesh.load(scene96 / "gt_mesh.ply", process=False)
    p = np.asarray(gt.vertices)[0]
    obj = one_point_obj(tmp_path / "point.obj", p)
    assert main(["eval", str(obj), "--scene", str(scene96), "--json",
                 str(tmp_path / "r.json")]) == 0
    assert "Traceback" not in capsys.readouterr().err
    report = _strict((tmp_path / "r.json").read_text())
    assert report["counts"]["mesh_vertices"] == 4 and report["counts"]["pred_kept"] == 1
    assert report["accuracy"] == pytest.approx(0.0, abs=1e-9)
    points = load_points(scene96 / "gt_points.ply")
    expected = truncated_mean(np.linalg.norm(points - p, axis=1),
                              report["settings"]["max_dist"])
    assert report["completeness"] == pytest.approx(expected, rel=1e-9)


def test_eval_long_scoring_shows_progress_bars(tiny_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(score, "PROGRESS_POINTS", 1)
    assert main(_eval(tiny_scene, tmp_path, "--density", "2")) == 0
    err = capsys.readouterr().err
    assert "eval: sampling about" in err and "eval: sample" in err and "eval: thin" in err
    assert main(_eval(tiny_scene, tmp_path, "--density", "2", "--no-progress")) == 0
    err = capsys.readouterr().err
    assert "eval: sampling about" in err and "pt/s" not in err
