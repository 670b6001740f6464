"""The long runs: DP, BDP and PAC-DP at the reference point on the same demos, resumable in chunks."""

from pathlib import Path

from lerobot_pacdp.study import runner
from lerobot_pacdp.study.presets import get_preset


def test_long_plan_has_the_three_methods_on_identical_demos(tmp_path: Path):
    cfg = runner.StudyConfig(preset="cpu", output_dir=tmp_path, long_pair=True)
    preset = runner.resolve_preset(cfg)
    task = preset.tasks[0]
    specs = runner.plan_task(task, preset, 206, long_pair=True)
    assert [s.method for s in specs] == ["DP", "BDP", "PAC-DP"]
    assert {s.train_episodes for s in specs} == {specs[0].train_episodes} and len(specs[0].train_episodes) == 20
    assert all(s.steps == get_preset("cpu").long_pair_steps and s.group == "long" for s in specs)
    assert specs[1].kl_weight == 0.0 and specs[2].kl_weight == task.reference_kl_weight
