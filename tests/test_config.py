"""Configs: nested groups with one default each, task presets laid underneath, old keys through the shim."""

from __future__ import annotations

import pytest

from mrchaos.learn.config import (
    ConfigError,
    config_from_dict,
    config_to_dict,
    load_config,
)

OLD_SODA = """
name: soda
env:
  num_worlds: 256
  piece_set: soda6
  view_extent: 0.44
  grid_half_range: 0.18
  grid_ntheta: 1
  twin_slots: exclusive
  view_mode: binary
  reward_shaping: false
  nthread: 1
task:
  cache: 1.0
  chaos_mode: mix
  workspace: 0.15
  cache_path: runs/chaos_cache_soda_8192.npz
  cache_size: 8192
"""


def test_an_old_flat_yaml_loads_like_the_nested_preset_config(tmp_path):
    old = tmp_path / "old.yaml"
    old.write_text(OLD_SODA)
    a = load_config(old)
    b = load_config("conf/soda.yaml", ["env.physics.nthread=1"])
    assert a.env == b.env and a.task == b.task
    assert a.task.preset == "soda" and a.env.view.extent == 0.44 and a.env.reward.twin_slots == "exclusive"


def test_a_preset_fills_what_the_config_leaves_out_and_the_config_wins():
    cfg = config_from_dict({"task": {"preset": "cutlery"}, "env": {"grid": {"ntheta": 16}}})
    assert cfg.env.piece_set == "cutlery" and cfg.env.view.extent == 0.40 and cfg.task.chaos.workspace == 0.14
    assert cfg.env.grid.ntheta == 16 and cfg.env.grid.half_range == 0.16
    plain = config_from_dict({})
    assert plain.env.piece_set == "tangram7" and plain.env.view.extent == 0.26


def test_old_keys_work_as_overrides_and_clash_with_new_ones(tmp_path):
    cfg = load_config(None, ["env.view_extent=0.3", "task.cache_size=99", "task.chaos=0.5", "optim.lr=5e-5"])
    assert cfg.optim.lr == 5e-5
    assert cfg.env.view.extent == 0.3 and cfg.task.cache.size == 99 and cfg.task.mix.chaos == 0.5
    with pytest.raises(ConfigError, match="both 'env.view_extent'"):
        config_from_dict({"env": {"view_extent": 0.3, "view": {"extent": 0.4}}})
    with pytest.raises(ConfigError, match="unknown task 'forks'"):
        load_config(None, ["task.preset=forks"])
    with pytest.raises(ConfigError, match="unknown key 'env.view.width'"):
        load_config(None, ["env.view.width=3"])


def test_the_resolved_config_round_trips_through_yaml(tmp_path):
    import yaml

    cfg = load_config("conf/full.yaml", ["env.robot.mount=[0.1, -0.4, 0.0]"])
    path = tmp_path / "resolved.yaml"
    path.write_text(yaml.safe_dump(config_to_dict(cfg)))
    again = load_config(path)
    assert again == cfg and again.env.robot.mount == (0.1, -0.4, 0.0)
