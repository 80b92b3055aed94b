"""The run's metrics file: one reader and writer (`neus_l0.run.metrics`)."""

import json

from neus_l0.run import metrics


def test_lines_round_trip_and_bad_lines_are_skipped(tmp_path):
    metrics.append_line(tmp_path, {"iter": 1, "loss": 0.5})
    metrics.append_line(tmp_path, {"snapshot_s": 10.0, "iter": 1, "elapsed": 10.5})
    with open(metrics.metrics_path(tmp_path), "a", encoding="utf-8") as f:
        f.write('{"iter": 2, "loss": 0.4}\n{"iter": 3, "lo\n[1, 2]\n\n')
    assert [m["iter"] for m in metrics.read_lines(tmp_path)] == [1, 1, 2]
    assert [m["iter"] for m in metrics.log_lines(tmp_path)] == [1, 2]
    assert metrics.last_log_line(tmp_path) == {"iter": 2, "loss": 0.4}
    assert metrics.snapshot_lines(tmp_path) == [{"snapshot_s": 10.0, "iter": 1,
                                                 "elapsed": 10.5}]


def test_a_missing_file_reads_as_empty(tmp_path):
    assert list(metrics.read_lines(tmp_path)) == []
    assert metrics.last_log_line(tmp_path) == {}
    metrics.truncate(tmp_path, 5)
    assert not metrics.metrics_path(tmp_path).exists()


def test_truncate_keeps_the_lines_up_to_the_resumed_iteration(tmp_path):
    for it in (1, 2, 3):
        metrics.append_line(tmp_path, {"iter": it, "loss": 1.0 / it})
    with open(metrics.metrics_path(tmp_path), "a", encoding="utf-8") as f:
        f.write("not json\n")
    metrics.truncate(tmp_path, 2)
    lines = metrics.metrics_path(tmp_path).read_text().splitlines()
    assert [json.loads(x)["iter"] for x in lines] == [1, 2]


def test_old_runs_read_with_todays_keys(tmp_path):
    """Runs before the rename logged ``s`` = 1 / s (the logistic's standard deviation)."""
    metrics.metrics_path(tmp_path).write_text('{"iter": 1, "loss": 0.5, "s": 0.02}\n'
                                              '{"iter": 2, "loss": 0.4, "s": 0}\n')
    lines = metrics.log_lines(tmp_path)
    assert lines[0]["inv_s"] == 50.0 and "s" not in lines[0]
    assert lines[1]["inv_s"] != lines[1]["inv_s"]  # NaN: no sharpness from a zero


def test_training_logs_the_sharpness_as_inv_s(tmp_path):
    from neus_l0.train.step import METRIC_NAMES

    assert "inv_s" in METRIC_NAMES and "s" not in METRIC_NAMES
