"""Malformed config files (issue #33 item 17): a broken ``--conf`` YAML, a ``!!python`` tag
and a garbage ``RUN/config.yaml`` each end in one line naming the file, the line and the
problem, without the parser's context lines."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("text, named", [
    ("train:\n  iters: [1, 2\n  lr: 3\n", ("line 3", "expected ','")),
    ("train: !!python/object/apply:os.system ['touch PWNED']\n", ("line 1", "no Python tags")),
    ("a: b: c\n", ("line 1, column 5", "mapping values")),
])
def test_malformed_conf_is_one_line(tmp_path, text, named, refused):
    conf = tmp_path / "bad.yaml"
    conf.write_text(text, encoding="utf-8")
    refused(["config", "show", "--conf", str(conf)], str(conf), *named)
    assert not (tmp_path / "PWNED").exists()


def test_garbage_run_config_is_one_line(tmp_path, tiny_scene, refused):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.yaml").write_bytes(bytes(range(256)) * 4)
    (run / "run.json").write_text("{}\n")  # a run folder of this tool, its config garbage
    refused(["train", str(tiny_scene), "--out", str(run), "--resume",
                       "--threads", "1"], str(run / "config.yaml"), "not UTF-8")
