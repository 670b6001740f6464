"""The long runs: DP, BDP and PAC-DP at the reference point on the same demos, resumable in chunks."""

from pathlib import Path

from lerobot_pacdp.study import runner
from lerobot_pacdp.study.plan import plan_task, train_config
from lerobot_pacdp.study.presets import get_preset


def test_long_plan_has_the_three_methods_on_identical_demos(tmp_path: Path):
    cfg = runner.StudyConfig(preset="cpu", output_dir=tmp_path, long_pair=True)
    preset = runner.resolve_preset(cfg)
    task = preset.tasks[0]
    specs = plan_task(task, preset, 206, long_pair=True)
    assert [s.method for s in specs] == ["DP", "BDP", "PAC-DP"]
    assert {s.train_episodes for s in specs} == {specs[0].train_episodes} and len(specs[0].train_episodes) == 20
    assert all(s.steps == get_preset("cpu").long_pair_steps and s.group == "long" for s in specs)
    assert specs[1].kl_weight == 0.0 and specs[2].kl_weight == task.reference_kl_weight


def test_long_runs_use_the_long_pair_batch_size_and_leave_the_main_study_alone(tmp_path: Path):
    cpu = get_preset("cpu")
    long_task = runner.resolve_preset(runner.StudyConfig(preset="cpu", output_dir=tmp_path, long_pair=True)).tasks[0]
    main_task = runner.resolve_preset(runner.StudyConfig(preset="cpu", output_dir=tmp_path)).tasks[0]
    spec = plan_task(long_task, cpu, 206, long_pair=True)[0]
    request = train_config(spec, long_task, tmp_path / "data", cpu.seed_offset, tmp_path)
    assert request["batch_size"] == cpu.long_pair_batch_size == 16
    assert request["steps"] == cpu.long_pair_steps and request["save_freq"] == cpu.long_pair_save_freq
    assert main_task.train_config["batch_size"] == 64
