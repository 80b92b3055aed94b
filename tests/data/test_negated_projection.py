"""A negated ``world_mat`` (issue #33 item 10) is the same camera projectively: the scene
loads with positive focal lengths and the same poses as the original."""

from __future__ import annotations

import json
import shutil

import numpy as np

from neus_l0.cli import main
from neus_l0.data.cameras import decompose_projection, look_at, projection_matrix
from neus_l0.formats.neus import load_scene


def test_decompose_takes_the_sign_of_p():
    K = np.array([[113.0, 0.0, 40.0], [0.0, 113.0, 30.0], [0.0, 0.0, 1.0]])
    w2c = look_at(np.array([3.0, 1.0, 2.0]), np.zeros(3))
    for scale in (1.0, -1.0, -7.5):
        k, c2w = decompose_projection(scale * projection_matrix(K, w2c))
        np.testing.assert_allclose(k, K, atol=1e-9)
        np.testing.assert_allclose(c2w, np.linalg.inv(w2c), atol=1e-9)


def test_negated_world_mat_inspects_as_the_original(capsys, tmp_path, tiny_scene):
    neg = tmp_path / "neg"
    shutil.copytree(tiny_scene, neg)
    cams = dict(np.load(neg / "cameras_sphere.npz"))
    for key in [k for k in cams if k.startswith("world_mat_") and "inv" not in k]:
        cams[key] = -cams[key]
    np.savez(neg / "cameras_sphere.npz", **cams)
    assert main(["inspect", str(neg), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    a, b = load_scene(tiny_scene), load_scene(neg)
    assert info["focal"]["min"] > 0 and not info["warnings"]
    np.testing.assert_allclose(b.intrinsics, a.intrinsics, rtol=1e-5)
    np.testing.assert_allclose(b.c2w, a.c2w, atol=1e-5)
