"""A budget too short to train is refused in one line naming the budget as typed, and the
run folder the command would have made is not left behind."""


def test_a_budget_that_start_up_already_spent(refused, tiny_scene, tmp_path):
    """In-process, the interpreter has run for longer than 1 s: nothing is left to train."""
    line = refused(["train", str(tiny_scene), "--out", str(tmp_path / "r"), "--budget", "1s",
                    "--quiet", "--threads", "1"], "--budget 1s", "too short")
    assert "start-up alone took" in line
    assert not (tmp_path / "r").exists()


def test_a_budget_too_short_after_the_measured_steps(refused, tiny_scene, tmp_path,
                                                     monkeypatch):
    """Start-up counted as nothing, a 2 s budget reaches the plan, which finds no room for
    the fewest iterations (3 s are kept for the end alone); the line names the typed budget
    and the least that would train."""
    monkeypatch.setattr("neus_l0.train.run_config.process_seconds", lambda: 0.0)
    run = tmp_path / "run"
    line = refused(["train", str(tiny_scene), "--out", str(run), "--budget", "2s",
                    "--threads", "1", "--quiet", "train.compile=false"],
                   "--budget 2s", "too short", "give at least")
    assert "train.budget=" not in line
    assert not run.exists()
