"""`neus-l0 bench --plan`: each run's budget is `train.budget`, with the ladder's capacity."""

from neus_l0.config.load import load_config, to_dict
from neus_l0.experiments.runner import RunSpec


def _spec(budget, planned, config=None):
    return RunSpec(name="x", scene="demo", scene_dir="/tmp/s", sampler="l0", budget_s=budget,
                   seed=1, out_dir="/tmp/o", conf="demo", planned=planned, config=config)


def test_planned_runs_get_a_budget_and_the_ladder():
    base = to_dict(load_config("demo", ["train.val_every=0"]))
    for config in (None, base):
        cut = _spec(1200, False, config).load_config()
        planned = _spec(1200, True, config).load_config()
        assert cut.train.max_seconds == 1200 and cut.train.budget == 0
        assert planned.train.budget == 1200 and planned.train.batch_size == 256
        assert planned.train.seed == 1 and planned.sampler.name == "l0"
    assert _spec(60, True, base).load_config().train.batch_size == 128


def test_two_scenes_of_one_name_are_refused_before_any_scene_is_built(tmp_path):
    """``--scenes demo,demo`` (or two folders of one name) fails before synthesising."""
    import pytest

    from neus_l0.errors import NeusL0Error
    from neus_l0.experiments.sweep import SweepSpec, check_spec

    spec = SweepSpec(out_dir=tmp_path / "out", scenes=["demo", "demo"], samplers=["l0"],
                     budgets=[10.0])
    with pytest.raises(NeusL0Error, match="share a name"):
        check_spec(spec)
    assert not (tmp_path / "out").exists()
