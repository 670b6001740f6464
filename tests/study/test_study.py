"""The reproduction study: planning, identical / disjoint episode sets, resumable execution, tables."""

import dataclasses
import json
import math
import shutil
import sys
from pathlib import Path

import pytest

from lerobot_pacdp.metrics.sweep import RolloutOutcome
from lerobot_pacdp.study import evaluation, executors, runner, tables
from lerobot_pacdp.study.executors import LocalExecutor
from lerobot_pacdp.study.plan import RunSpec, plan_task, split_episodes, train_config
from lerobot_pacdp.study.presets import Preset, StudyError, TaskPreset, get_preset, with_overrides
from lerobot_pacdp.study.state import (
    DATASET_FILE,
    DONE_FILE,
    LOG_FILE,
    REQUEST_FILE,
    run_state,
    write_json_atomic,
)
from lerobot_pacdp.train_runs import final_checkpoint, step_dirs

from fake_trainer import write_checkpoint

FAKE_TRAINER = [sys.executable, str(Path(__file__).with_name("fake_trainer.py"))]


def _tiny_preset(steps: int = 6, save_freq: int = 2, demos=(2, 3), seeds=(0, 1), heldout: int = 2) -> Preset:
    base = get_preset("cpu")
    task = dataclasses.replace(base.tasks[0], demos=demos, steps=steps, save_freq=save_freq, heldout=heldout)
    return dataclasses.replace(base, tasks=(task,), seeds=seeds, jobs=1)


def _write_requests(specs: list[RunSpec], preset: Preset, out: Path) -> None:
    for spec in specs:
        config = train_config(spec, preset.tasks[0], out / "data", preset.seed_offset, out)
        write_json_atomic(spec.run_dir(out) / REQUEST_FILE, config)


def _local(preset: Preset, out: Path, trainer=FAKE_TRAINER, max_chunk_steps=None) -> LocalExecutor:
    return LocalExecutor(out, trainer, preset.jobs, max_chunk_steps)


def test_cpu_plan_shape_and_methods():
    preset = get_preset("cpu")
    specs = plan_task(preset.tasks[0], preset, num_episodes=206)
    assert len(specs) == 3 * 2 * 2  # methods x demos {20, 40} x seeds
    assert {(s.method, s.kl_weight, s.prior_rho) for s in specs} == {
        ("DP", None, None), ("BDP", 0.0, -4.5), ("PAC-DP", 1e-4, -4.5)
    }
    assert len({s.name for s in specs}) == len(specs)


def test_paper_plan_uses_the_task_table_and_grid():
    preset = get_preset("paper")
    from lerobot_pacdp.robomimic.tasks import TASKS

    square = preset.task("square")
    assert square.steps == TASKS["square"].train_steps and square.reference_kl_weight == TASKS["square"].kl_weight
    assert preset.task("transport").demos == (140,)
    specs = plan_task(square, preset, num_episodes=200)
    per_cell = 1 + 4 + 2 * 4  # DP, BDP per rho, PAC-DP per (lambda in {1e-5, 1e-6}) x rho
    assert len(specs) == len(square.demos) * len(preset.seeds) * per_cell
    pusht = plan_task(preset.task("pusht"), preset, num_episodes=206)
    assert {s.kl_weight for s in pusht if s.method == "PAC-DP"} == {1e-4, 1e-5, 1e-6}  # reference lambda added


def test_training_episodes_identical_across_methods_heldout_disjoint_and_fixed_per_seed():
    preset = with_overrides(get_preset("cpu"), prior_rhos=[-4.0, -4.5], kl_weights=[1e-5])
    specs = plan_task(preset.tasks[0], preset, num_episodes=206)
    for seed in preset.seeds:
        runs = [s for s in specs if s.seed == seed]
        assert len({s.heldout_episodes for s in runs}) == 1  # one held-out set per seed
        heldout = set(runs[0].heldout_episodes)
        for demos in (20, 40):
            sets = {s.train_episodes for s in runs if s.demos == demos}
            assert len(sets) == 1  # every method and grid point trains on the same demos
            (train,) = sets
            assert len(train) == demos and not heldout & set(train)
        small = next(s for s in runs if s.demos == 20).train_episodes
        assert set(small) <= set(next(s for s in runs if s.demos == 40).train_episodes)
    assert specs[0].heldout_episodes != next(s for s in specs if s.seed == 1).heldout_episodes
    assert split_episodes(206, 0, 20, [20]) == split_episodes(206, 0, 20, [20])  # deterministic


def test_bad_inputs_fail_clearly():
    with pytest.raises(StudyError, match="leave 6 for training"):
        split_episodes(26, 0, 20, [20])
    with pytest.raises(StudyError, match="unknown preset"):
        get_preset("gpu")
    with pytest.raises(StudyError, match="no task"):
        with_overrides(get_preset("cpu"), tasks=["lift"])
    with pytest.raises(StudyError, match="kl_weights must be > 0"):
        with_overrides(get_preset("cpu"), kl_weights=[0.0])
    with pytest.raises(StudyError, match="distinct"):
        with_overrides(get_preset("cpu"), seeds=[0, 0])
    with pytest.raises(StudyError, match="success_every must be >= 0"):
        with_overrides(get_preset("cpu_v2"), success_every=-1)


def test_success_every_override_replaces_the_presets_and_none_keeps_it():
    preset = get_preset("cpu_v2")
    assert with_overrides(preset, success_every=5000).success_every == 5000
    assert with_overrides(preset, success_every=0).success_every == 0
    assert with_overrides(preset).success_every == preset.success_every == 1000


def test_dp_is_pacdps_twin_and_lerobot_dp_has_the_same_diffusion_settings(tmp_path):
    import draccus
    from lerobot.configs.policies import PreTrainedConfig

    preset = get_preset("cpu")
    specs = plan_task(preset.tasks[0], preset, num_episodes=206, lerobot_diffusion=True)
    dp = next(s for s in specs if s.method == "DP")
    lerobot_dp = next(s for s in specs if s.method == "LeRobot-DP" and s.demos == dp.demos and s.seed == dp.seed)
    pac = next(s for s in specs if s.method == "PAC-DP" and s.demos == dp.demos and s.seed == dp.seed)
    assert (dp.name.endswith("_dp"), lerobot_dp.name.endswith("_lerobot_dp")) == (True, True)
    configs = [train_config(s, preset.tasks[0], tmp_path, preset.seed_offset, tmp_path) for s in (dp, lerobot_dp, pac)]
    assert all(c["dataset"] == configs[2]["dataset"] and c["seed"] == configs[2]["seed"] for c in configs)
    assert configs[0]["dataset"]["eval_split"] == 0.0 and configs[0]["eval_steps"] == 0
    dp_policy, lerobot_policy, pac_policy = (draccus.decode(PreTrainedConfig, c["policy"]) for c in configs)
    assert (dp_policy.type, dp_policy.bayesian, dp_policy.use_ema) == ("pacdp", False, True)
    assert lerobot_policy.type == "diffusion" and pac_policy.type == "pacdp" and pac_policy.bayesian
    for field in ("down_dims", "diffusion_step_embed_dim", "horizon", "n_obs_steps", "n_action_steps",
                  "num_inference_steps", "noise_scheduler_type", "beta_schedule", "normalization_mapping",
                  "do_mask_loss_for_padding", "optimizer_lr", "scheduler_warmup_steps", "kernel_size"):  # fmt: skip
        assert getattr(dp_policy, field) == getattr(lerobot_policy, field) == getattr(pac_policy, field), field
    assert pac_policy.kl_weight == 1e-4 and pac_policy.prior_rho == -4.5
    assert not any(s.method == "LeRobot-DP" for s in plan_task(preset.tasks[0], preset, num_episodes=206))


def test_executor_skips_finished_runs_and_resumes_interrupted_ones(tmp_path, monkeypatch):
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    preset = _tiny_preset(demos=(2,), seeds=(0,))
    specs = plan_task(preset.tasks[0], preset, num_episodes=8)
    _write_requests(specs, preset, tmp_path)
    calls = tmp_path / "calls.txt"
    monkeypatch.setenv("FAKE_TRAINER_CALLS", str(calls))
    monkeypatch.setenv("FAKE_TRAINER_FAIL_AT", "4")  # every run dies after its step-4 checkpoint
    outcome = _local(preset, tmp_path).run(specs)
    assert len(outcome.failed) == 3 and not outcome.done
    assert all(run_state(s, tmp_path) == ("resume", 4) for s in specs)

    monkeypatch.delenv("FAKE_TRAINER_FAIL_AT")
    outcome = _local(preset, tmp_path).run(specs)
    assert len(outcome.done) == 3
    lines = calls.read_text().splitlines()
    assert len(lines) == 6 and all("resume=True from=4" in line for line in lines[3:])
    for spec in specs:
        done = json.loads((spec.run_dir(tmp_path) / DONE_FILE).read_text())
        assert done["steps"] == 6 and done["final_checkpoint"].endswith("000006")

    outcome = _local(preset, tmp_path).run(specs)  # nothing left to do
    assert len(outcome.done) == 3 and len(calls.read_text().splitlines()) == 6


def test_the_progress_of_a_resumed_run_counts_from_the_step_it_resumed_at(tmp_path):
    """lerobot-train's bar counts its own call's steps (tqdm total = steps - resume step), and a resumed run's
    log holds every call's bars: the heartbeat reads the last call's only."""
    log = tmp_path / "train.log"
    first = f"{executors.CALL_HEADER}2026-12-04 18:48:00 new at step 0: lerobot-train --steps=40000\n"
    log.write_text(first + "Training:  80%|########  | 31857/40000 [1:02:00<15:00,  9.00step/s]")
    assert executors.progress_step(log, 0) == 31857
    with open(log, "a") as f:
        f.write(f"{executors.CALL_HEADER}2026-12-04 21:04:58 resume at step 30000: lerobot-train --resume=true\n")
    assert executors.progress_step(log, 30000) is None  # this call has shown no bar yet (the caller's fallback)
    with open(log, "a") as f:
        f.write("Training:  26%|##6       | 2605/10000 [04:50<13:44,  8.97step/s]")
    assert executors.progress_step(log, 30000) == 32605
    assert executors.progress_step(tmp_path / "missing.log", 0) is None


def test_the_time_left_is_the_last_slot_to_free_up_not_the_work_shared_over_idle_slots():
    assert executors.time_left([1600.0], [], jobs=2) == 1600.0  # one run left: the other core cannot help it
    assert executors.time_left([], [], jobs=2) == 0.0
    # slots end at 300 and 500; the waiting 1000 s run starts at 300 (ends 1300), the 200 s one at 500 (ends 700)
    assert executors.time_left([500.0, 300.0], [1000.0, 200.0], jobs=2) == 1300.0
    # one running run, a free slot: the waiting runs go 0 -> 400, then 400 -> 700 beside the 900 s run
    assert executors.time_left([900.0], [400.0, 300.0], jobs=2) == 900.0
    assert executors.time_left([100.0], [400.0, 300.0], jobs=1) == 800.0  # one slot: everything in turn


def test_run_without_checkpoint_restarts_and_final_checkpoint_counts_as_done(tmp_path, monkeypatch):
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    preset = _tiny_preset(demos=(2,), seeds=(0,))
    specs = plan_task(preset.tasks[0], preset, num_episodes=8)[:2]
    _write_requests(specs, preset, tmp_path)
    (specs[0].train_dir(tmp_path) / "checkpoints").mkdir(parents=True)  # died before its first checkpoint
    final = specs[1].train_dir(tmp_path) / "checkpoints" / "000006"  # finished, but no done marker yet
    write_checkpoint(final, json.loads((specs[1].run_dir(tmp_path) / REQUEST_FILE).read_text()), 6)
    assert run_state(specs[0], tmp_path) == ("new", 0) and run_state(specs[1], tmp_path).status == "done"
    outcome = _local(preset, tmp_path).run(specs)
    assert len(outcome.done) == 2
    assert (specs[1].run_dir(tmp_path) / DONE_FILE).is_file()
    assert not (specs[1].run_dir(tmp_path) / LOG_FILE).exists()  # never launched


def test_a_final_checkpoint_killed_mid_write_is_not_done_and_the_run_resumes_before_it(tmp_path, monkeypatch):
    """The study reads checkpoints as pacdp-recover-run does: every file LeRobot writes must be complete."""
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    preset = _tiny_preset(demos=(2,), seeds=(0,))
    spec = plan_task(preset.tasks[0], preset, num_episodes=8)[0]
    _write_requests([spec], preset, tmp_path)
    config = json.loads((spec.run_dir(tmp_path) / REQUEST_FILE).read_text())
    checkpoints = spec.train_dir(tmp_path) / "checkpoints"
    write_checkpoint(checkpoints / "000004", config, 4)
    (checkpoints / "last").symlink_to("000004")
    write_checkpoint(checkpoints / "000006", config, 6)
    (checkpoints / "000006" / "training_state" / "optimizer_state.safetensors").write_bytes(b"\x10")  # cut off
    assert run_state(spec, tmp_path) == ("resume", 4)
    calls = tmp_path / "calls.txt"
    monkeypatch.setenv("FAKE_TRAINER_CALLS", str(calls))
    assert _local(preset, tmp_path).run([spec]).done == (spec,)
    assert calls.read_text() == f"pacdp {spec.name} resume=True from=4\n"


def _one_fake_run(tmp_path: Path, monkeypatch, **trainer_env: str) -> tuple[Preset, RunSpec]:
    """A 6-step run (checkpoint every 2) with its request written, for the stand-in trainer with `trainer_env`."""
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    for name, value in trainer_env.items():
        monkeypatch.setenv(name, value)
    preset = _tiny_preset(steps=6, save_freq=2, demos=(2,), seeds=(0,))
    spec = plan_task(preset.tasks[0], preset, num_episodes=8)[0]
    _write_requests([spec], preset, tmp_path)
    return preset, spec


def test_chunked_runs_pause_at_a_checkpoint_and_continue(tmp_path, monkeypatch):
    preset, spec = _one_fake_run(tmp_path, monkeypatch, FAKE_TRAINER_SLEEP="1.0")
    outcome = _local(preset, tmp_path, max_chunk_steps=3).run([spec])
    assert outcome.paused == (spec,) and run_state(spec, tmp_path) == ("resume", 4)  # 3 steps -> checkpoint 4
    outcome = _local(preset, tmp_path, max_chunk_steps=3).run([spec])
    assert outcome.done == (spec,)


def test_tables_from_known_rows():
    def run(method, demos, seed, kl, rho, npe, sr):
        return {"task": "pusht", "demos": demos, "seed": seed, "method": method, "kl_weight": kl, "prior_rho": rho,
                "npe": npe, "nll_bound": None, "success_rate": sr}  # fmt: skip

    per_run = [
        run("DP", 20, 0, None, None, 0.30, 0.4), run("DP", 20, 1, None, None, 0.32, 0.6),
        run("BDP", 20, 0, 0.0, -4.5, 0.28, 0.5), run("BDP", 20, 1, 0.0, -4.5, 0.30, 0.5),
        run("BDP", 20, 0, 0.0, -4.0, 0.26, 0.3), run("BDP", 20, 1, 0.0, -4.0, 0.26, 0.3),
        run("PAC-DP", 20, 0, 1e-4, -4.5, 0.10, 0.7), run("PAC-DP", 20, 1, 1e-4, -4.5, 0.14, 0.9),
        run("PAC-DP", 20, 0, 1e-5, -4.5, 0.20, 0.8), run("PAC-DP", 20, 1, 1e-5, -4.5, 0.20, 0.6),
    ]  # fmt: skip
    stats = tables.seed_statistics(per_run)
    assert stats[("pusht", 20, "DP", None, None)]["npe"] == pytest.approx((0.31, math.sqrt(2e-4), 2))
    cells = tables.build_tables(stats, {"pusht": (1e-4, -4.5)})
    get = {(c["table"], c["column"], c["metric"]): c for c in cells}
    assert get[("I", "PAC-DP", "npe")]["mean"] == pytest.approx(0.12)
    assert get[("I", "BDP", "npe")]["mean"] == pytest.approx(0.29)  # the reference rho, not the best one
    assert get[("II", "BDP", "npe")]["mean"] == pytest.approx(0.26)  # best rho (lowest NPE)
    assert get[("II", "PAC-DP", "success_rate")]["mean"] == pytest.approx(0.8)  # best SR: lambda 1e-4 (0.8 vs 0.7)
    assert get[("II", "PAC-DP", "success_rate")]["kl_weight"] == 1e-4
    avg = get[("III", "PAC-DP avg", "npe")]
    assert avg["mean"] == pytest.approx(0.16) and avg["std"] == pytest.approx(math.sqrt(2 * 0.04**2)) and avg["n"] == 2
    assert get[("III", "BDP avg", "success_rate")]["mean"] == pytest.approx(0.4)
    assert get[("III", "PAC-DP best", "npe")]["mean"] == pytest.approx(0.12)
    assert ("I", "DP", "nll_bound") not in get  # no values, no cell
    markdown = tables.render_markdown(cells, last_k=3)
    assert "| pusht | 20 | 0.310 ± 0.014 |" in markdown and "(0.0001, -4.5)" in markdown


def test_a_table_cell_of_one_seed_shows_its_value_without_a_spread():
    per_run = [{"task": "pusht", "demos": 20, "seed": 0, "method": "DP", "kl_weight": None, "prior_rho": None,
                "npe": 0.25, "nll_bound": None, "success_rate": 0.08}]  # fmt: skip
    cells = tables.build_tables(tables.seed_statistics(per_run), {"pusht": (1e-5, -4.5)})
    markdown = tables.render_markdown(cells, last_k=1)
    assert "| pusht | 20 | 0.250 |" in markdown and "0.250 ± 0.000" not in markdown


def test_per_run_values_use_the_last_k_checkpoints():
    rows = [{"run": "r", "label": "x", "step": s, "npe": v, "nll_bound": None, "success_rate": None, "task": "pusht",
             "demos": 20, "seed": 0, "method": "DP", "kl_weight": None, "prior_rho": None, "name": "r", "group": "main"}
            for s, v in ((1, 9.0), (2, 1.0), (3, 2.0))]  # fmt: skip
    (value,) = tables.per_run_values(rows, last_k=2)
    assert value["npe"] == pytest.approx(1.5) and value["last_step"] == 3 and value["success_rate"] is None


def test_dry_run_prints_the_plan(tmp_path, capsys, pusht_zarr):
    argv = ["--preset=cpu", f"--output_dir={tmp_path}", f"--pusht_zarr={pusht_zarr}", "--dry_run=true", "--seeds=[3]",
            "--demos=[5]"]  # fmt: skip
    assert runner.main(argv) == 0
    out = capsys.readouterr().out
    assert "seed 3: held-out demos (20)" in out and "5 training demos (same for every method)" in out
    assert out.count(" new") == 3 and not (tmp_path / "runs").exists()



def test_methods_keeps_only_the_named_methods_runs(tmp_path, capsys, pusht_zarr):
    argv = ["--preset=cpu", f"--output_dir={tmp_path}", f"--pusht_zarr={pusht_zarr}", "--dry_run=true", "--seeds=[3]",
            "--demos=[5]", "--methods=[PAC-DP]"]  # fmt: skip
    assert runner.main(argv) == 0
    out = capsys.readouterr().out
    assert out.count(" new") == 1 and "PAC-DP" in out and "BDP" not in out


def test_an_unknown_method_is_one_line_and_exit_2_with_nothing_written(tmp_path, capsys, pusht_zarr):
    argv = ["--preset=cpu", f"--output_dir={tmp_path}", f"--pusht_zarr={pusht_zarr}", "--methods=[PACDP]"]
    assert runner.main(argv) == 2
    err = capsys.readouterr().err
    assert err == "pacdp-study: error: --methods: unknown PACDP; choose from DP, BDP, PAC-DP, LeRobot-DP.\n"
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_tiny_study_end_to_end_through_lerobot_train(tmp_path, monkeypatch):
    """Two methods x one seed through the real lerobot-train (a few steps), then metrics, the two final
    checkpoints' rollouts side by side (spawned workers) and the tables."""
    from pacdp_testing import make_tiny_dataset

    monkeypatch.setattr(executors, "POLL_S", 0.2)
    make_tiny_dataset(tmp_path / "data", [30] * 6)
    base = get_preset("cpu")
    config = json.loads(json.dumps(base.tasks[0].train_config))
    config["dataset"]["repo_id"] = "local/tiny"
    config["policy"].update(down_dims=[16, 32], diffusion_step_embed_dim=16, horizon=8, n_action_steps=4,
                            drop_n_last_frames=3)  # fmt: skip
    config.update(batch_size=4, log_freq=1)
    task = TaskPreset("pusht", config, demos=(3,), heldout=2, steps=4, save_freq=2, reference_kl_weight=1e-4,
                      dataset_root=str(tmp_path / "data"))  # fmt: skip
    preset = dataclasses.replace(base, tasks=(task,), seeds=(0,), prior_rhos=(-4.5,), jobs=2, last_k=2,
                                 nll_steps=4, success_episodes=2, success_last_k=1, perf_rows=())  # fmt: skip
    specs = [s for s in plan_task(task, preset, num_episodes=6) if s.method != "BDP"]
    _write_requests(specs, preset, tmp_path)
    for spec in specs:  # point the runs at the tiny dataset
        request = spec.run_dir(tmp_path) / REQUEST_FILE
        cfg = json.loads(request.read_text())
        cfg["dataset"]["root"] = str(tmp_path / "data")
        write_json_atomic(request, cfg)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    outcome = _local(preset, tmp_path, trainer=executors.default_trainer()).run(specs)
    assert len(outcome.done) == 2, outcome
    for spec in specs:
        saved = json.loads((spec.train_dir(tmp_path) / "checkpoints" / "000004" / "pretrained_model" / "train_config.json").read_text())
        assert saved["dataset"]["episodes"] == list(spec.train_episodes)
    tables.report(preset, specs, evaluation.evaluate_runs(preset, specs, tmp_path), tmp_path)
    per_run = (tmp_path / "results" / "runs.csv").read_text()
    assert "DP" in per_run and "PAC-DP" in per_run
    markdown = (tmp_path / "results" / "tables.md").read_text()
    assert "Table I" in markdown and "Performance" in markdown
    assert (tmp_path / "results" / "figures" / "main_pusht_d003" / "npe.png").is_file()
    summary = json.loads((tmp_path / "results" / "summary.json").read_text())
    assert [(r["method"], r["step"], r["n_episodes"]) for r in summary] == [("DP", 4, 2), ("PAC-DP", 4, 2)]
    assert all(r["heldout_npe"] > 0 and r["success_rate"] in (0.0, 0.5, 1.0) for r in summary)
    cache = json.loads((evaluation.metrics_dir(tmp_path, "main", "pusht", 0) / "success.json").read_text())
    assert sorted(Path(c).parts[-2] for c in cache["rates"]) == ["000004", "000004"]  # both final checkpoints


def test_performance_table_runs_each_rows_benchmark_and_reads_its_ratios(tmp_path, monkeypatch):
    from lerobot_pacdp import speed_benchmark

    requests = []

    def fake_benchmark(request):
        requests.append(request)
        ratios = {"train_step": 1.5 + request.batch_size / 100, "mean_mode_latency": 1.0, "sample_mode_latency": 1.25,
                  "peak_memory": 2.0}  # fmt: skip
        result = {"config": {"down_dims": [8, 16]}, "device": "test cpu", "ratios_pacdp_over_dp": ratios}
        request.result_file().write_text(json.dumps(result))

    monkeypatch.setattr(speed_benchmark, "run_benchmark", fake_benchmark)
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    preset = get_preset("cpu")
    lines = tables.performance_table(preset, tmp_path, measure=True).splitlines()
    assert [(r.preset, r.batch_size, r.device, r.output_dir) for r in requests] == [
        (row.speed_preset, row.batch_size, "cpu", tmp_path) for row in preset.perf_rows
    ]
    assert (requests[1].train_steps, requests[1].latency_calls) == (10, 5)  # the paper U-Net row on CPU is short
    assert (requests[0].train_steps, requests[0].latency_calls) == (None, None)  # the benchmark preset's
    assert lines[-1] == "| paper (8/16) | 8 | test cpu | 1.58 | 1.00 | 1.25 | 2.00 |"
    unmeasured = tables.performance_table(dataclasses.replace(preset, perf_rows=preset.perf_rows[:1]), tmp_path, False)
    assert "| cpu (8/16) | 64 | test cpu | 2.14 |" in unmeasured
    missing = tables.performance_table(preset, tmp_path / "elsewhere", measure=False)
    assert "| paper | 8 | cpu | not measured (`pacdp-study --perf=true`) | | | |" in missing


def test_dynamics_find_the_best_checkpoint_and_the_rise_after_it():
    def row(run, method, step, npe, kl):
        return {"task": "lift", "run": f"/x/{run}", "name": run, "method": method, "demos": 20, "seed": 0, "step": step, "npe": npe,
                "nll_bound": -2.0 - npe, "kl": kl}  # fmt: skip

    rows = [row("dp", "DP", 1000, 0.05, None), row("dp", "DP", 3000, 0.06, None), row("dp", "DP", 2000, 0.04, None),
            row("pac", "PAC-DP", 1000, 0.05, 10.0), row("pac", "PAC-DP", 2000, 0.045, 12.0)]  # fmt: skip
    dp, pac = tables.dynamics_rows(rows)
    assert (dp["best_step"], dp["best_npe"], dp["last_step"], dp["last_npe"]) == (2000, 0.04, 3000, 0.06)
    assert dp["npe_rise"] == pytest.approx(0.5) and dp["last_kl"] is None and dp["last_nll_bound"] == pytest.approx(-2.06)
    assert pac["best_step"] == pac["last_step"] == 2000 and pac["npe_rise"] == 0.0 and pac["last_kl"] == 12.0
    markdown = tables.render_dynamics([dp, pac])
    assert "| lift | dp | DP | 0.0400 | 2000 | 3000 | 0.0600 | +50.0% | -2.06 | -- |" in markdown
    assert "| lift | pac | PAC-DP | 0.0450 | 2000 | 2000 | 0.0450 | +0.0% | -2.045 | 12 |" in markdown


def test_unfinished_runs_are_reported_only_when_asked(tmp_path, monkeypatch):
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    monkeypatch.setenv("FAKE_TRAINER_FAIL_AT", "4")  # stopped after its step-4 checkpoint of 6
    preset = dataclasses.replace(_tiny_preset(demos=(2,), seeds=(0,)), success_episodes=0)
    specs = plan_task(preset.tasks[0], preset, num_episodes=8)[:1]
    _write_requests(specs, preset, tmp_path)
    _local(preset, tmp_path).run(specs)
    swept = []

    def fake_sweep(cfg):
        swept.append(cfg)
        return [{"label": specs[0].name, "run": str(cfg.runs[0]), "step": 4, "npe": 0.1}], {}

    monkeypatch.setattr(evaluation, "run_sweep", fake_sweep)
    assert evaluation.evaluate_runs(preset, specs, tmp_path) == [] and swept == []
    (row,) = evaluation.evaluate_runs(preset, specs, tmp_path, unfinished=True)
    assert row["step"] == 4 and row["method"] == specs[0].method
    (sweep,) = swept  # typed lists, not comma-joined strings
    assert sweep.runs == [specs[0].train_dir(tmp_path)] and sweep.labels == [specs[0].name]
    assert sweep.episodes == list(specs[0].heldout_episodes)


def _finished_runs_of_2_and_3_demos(tmp_path, monkeypatch, kills: list[str]):
    """Six finished runs (2 and 3 demos, seed 0) and a stand-in for run_sweep that, like it, writes metrics.json
    with the settings and the swept runs' rows only, then raises KeyboardInterrupt while `kills` has an entry.
    Returns the preset, the 2- and 3-demo runs, and the labels metrics.json holds."""
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    preset = dataclasses.replace(_tiny_preset(demos=(2, 3), seeds=(0,)), success_episodes=0)
    specs = plan_task(preset.tasks[0], preset, num_episodes=8)
    _write_requests(specs, preset, tmp_path)
    _local(preset, tmp_path).run(specs)

    def fake_sweep(cfg):
        rows = [{"label": label, "run": str(run), "checkpoint": f"{run}/6", "step": 6, "npe": 0.1}
                for run, label in zip(cfg.runs, cfg.labels, strict=True)]  # fmt: skip
        write_json_atomic(cfg.output_dir / "metrics.json", {"settings": {"nll_steps": cfg.nll_steps}, "rows": rows})
        if kills:
            raise KeyboardInterrupt(kills.pop())
        return rows, {}

    monkeypatch.setattr(evaluation, "run_sweep", fake_sweep)
    metrics_file = evaluation.metrics_dir(tmp_path, specs[0].group, specs[0].task, 0) / "metrics.json"

    def stored_labels() -> list[str]:
        return sorted(row["label"] for row in json.loads(metrics_file.read_text())["rows"])

    two, three = [s for s in specs if s.demos == 2], [s for s in specs if s.demos == 3]
    return preset, two, three, stored_labels


def test_a_later_call_over_other_demos_keeps_the_earlier_runs_metrics_rows_of_the_same_settings(tmp_path, monkeypatch):
    preset, two, three, stored_labels = _finished_runs_of_2_and_3_demos(tmp_path, monkeypatch, kills=[])
    assert len(two) == len(three) == 3
    evaluation.evaluate_runs(preset, two, tmp_path)
    assert [row["demos"] for row in evaluation.evaluate_runs(preset, three, tmp_path)] == [3, 3, 3]
    assert stored_labels() == sorted(s.name for s in two + three)
    evaluation.evaluate_runs(dataclasses.replace(preset, nll_steps=None), two, tmp_path)  # other settings
    assert stored_labels() == sorted(s.name for s in two)


def test_a_metrics_pass_killed_mid_sweep_leaves_the_other_runs_rows_to_the_next_pass(tmp_path, monkeypatch):
    kills = []
    preset, two, three, stored_labels = _finished_runs_of_2_and_3_demos(tmp_path, monkeypatch, kills)
    evaluation.evaluate_runs(preset, two, tmp_path)
    kills.append("Ctrl-C while sweeping the 3-demo runs")
    with pytest.raises(KeyboardInterrupt):
        evaluation.evaluate_runs(preset, three, tmp_path)
    assert stored_labels() == sorted(s.name for s in three)  # what the killed sweep left in metrics.json
    evaluation.evaluate_runs(preset, three, tmp_path)
    assert stored_labels() == sorted(s.name for s in two + three)  # the 2-demo runs' rows are back
    directory = evaluation.metrics_dir(tmp_path, two[0].group, two[0].task, 0)
    assert sorted(p.name for p in directory.iterdir()) == ["metrics.json"]  # no backup left behind


def _record_rollouts(monkeypatch) -> list[str]:
    """Rollouts replaced by a success rate of 0.5 and a score of 0.8 each; returns the checkpoints rolled out."""
    rolled_out = []

    def fake_rollouts(checkpoints, env_dict, preset):
        rolled_out.extend(checkpoints)
        return ((c, RolloutOutcome(success_rate=0.5, avg_max_reward=0.8)) for c in checkpoints)

    monkeypatch.setattr(evaluation, "_rollouts", fake_rollouts)
    return rolled_out


def test_a_seed_with_one_run_on_disk_keeps_the_stored_rows_and_success_rates_of_its_runs_trained_elsewhere(
    tmp_path, monkeypatch
):
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    preset = dataclasses.replace(_tiny_preset(demos=(2,), seeds=(0,)), success_episodes=2, success_last_k=1)
    here, *elsewhere = plan_task(preset.tasks[0], preset, num_episodes=8)
    _write_requests([here], preset, tmp_path)
    _local(preset, tmp_path).run([here])
    directory = evaluation.metrics_dir(tmp_path, here.group, here.task, 0)
    published = [{"label": s.name, "run": f"/other/{s.name}", "checkpoint": f"/other/{s.name}/006", "step": 6,
                  "npe": 0.2} for s in elsewhere]  # fmt: skip
    settings = {"nll_steps": preset.nll_steps}
    write_json_atomic(directory / "metrics.json", {"settings": settings, "rows": published})
    env = preset.tasks[0].train_config["env"]
    rates = {row["checkpoint"]: 0.75 for row in published}
    write_json_atomic(directory / "success.json", {"settings": {"episodes": 2, "seed": 0, "env": env}, "rates": rates})

    def fake_sweep(cfg):  # as run_sweep: metrics.json gets the settings and the swept runs' rows only
        rows = [{"label": label, "run": str(run), "checkpoint": str(final_checkpoint(run, 6)), "step": 6, "npe": 0.1}
                for run, label in zip(cfg.runs, cfg.labels, strict=True)]  # fmt: skip
        write_json_atomic(cfg.output_dir / "metrics.json", {"settings": {"nll_steps": cfg.nll_steps}, "rows": rows})
        return rows, {}

    monkeypatch.setattr(evaluation, "run_sweep", fake_sweep)
    rolled_out = _record_rollouts(monkeypatch)
    rows = evaluation.evaluate_runs(preset, [here, *elsewhere], tmp_path)
    assert [(r["name"], r["npe"], r["success_rate"], r["avg_max_reward"]) for r in rows] == [
        (here.name, 0.1, 0.5, 0.8), *((s.name, 0.2, 0.75, None) for s in elsewhere)  # published without scores
    ]
    here_checkpoint = str(final_checkpoint(here.train_dir(tmp_path), 6))
    assert rolled_out == [here_checkpoint]  # not the runs trained elsewhere
    assert json.loads((directory / "success.json").read_text())["scores"] == {here_checkpoint: 0.8}
    stored = json.loads((directory / "metrics.json").read_text())["rows"]
    assert sorted(row["label"] for row in stored) == sorted(s.name for s in [here, *elsewhere])


def test_a_rollout_cached_while_the_run_was_unfinished_stays_off_the_finished_runs_schedule(tmp_path, monkeypatch):
    monkeypatch.setattr(executors, "POLL_S", 0.05)
    preset = dataclasses.replace(_tiny_preset(demos=(2,), seeds=(0,)), success_episodes=2, success_last_k=1,
                                 success_every=4)  # fmt: skip
    spec = plan_task(preset.tasks[0], preset, num_episodes=8)[0]
    _write_requests([spec], preset, tmp_path)
    _local(preset, tmp_path).run([spec])
    step2, step4, step6 = (str(d) for d in step_dirs(spec.train_dir(tmp_path)))
    directory = evaluation.metrics_dir(tmp_path, spec.group, spec.task, 0)
    env = preset.tasks[0].train_config["env"]
    settings = {"episodes": 2, "seed": 0, "env": env}  # a report at step 2 rolled out the run's last checkpoint then
    write_json_atomic(directory / "success.json", {"settings": settings, "rates": {step2: 0.25}, "scores": {step2: 0.3}})

    def fake_sweep(cfg):
        rows = [{"label": spec.name, "run": str(cfg.runs[0]), "checkpoint": c, "step": s, "npe": 0.1,
                 "success_rate": None} for s, c in ((2, step2), (4, step4), (6, step6))]  # fmt: skip
        return rows, {}

    monkeypatch.setattr(evaluation, "run_sweep", fake_sweep)
    rolled_out = _record_rollouts(monkeypatch)
    rows = evaluation.evaluate_runs(preset, [spec], tmp_path)
    assert [(r["step"], r["success_rate"]) for r in rows] == [(2, None), (4, 0.5), (6, 0.5)]
    assert rolled_out == [step4, step6]  # step 4 on the success_every schedule, step 6 the last
    assert json.loads((directory / "success.json").read_text())["rates"] == {step2: 0.25, step4: 0.5, step6: 0.5}


def test_adopting_a_published_study_adds_the_rows_and_rates_of_runs_the_cache_lacks_and_keeps_its_own(tmp_path):
    published, out = tmp_path / "results" / "metrics", tmp_path / "out"
    seed = Path("main") / "lift" / "seed1"

    def write(path: Path, content: dict) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(content))

    def rows(**npe_by_label: float) -> list[dict]:
        return [{"label": label, "step": 6, "npe": npe} for label, npe in npe_by_label.items()]

    write(out / "metrics" / seed / "metrics.json", {"settings": {"nll_steps": 4}, "rows": rows(d040=0.1)})
    write(published / seed / "metrics.json", {"settings": {"nll_steps": 4}, "rows": rows(d040=0.9, d020=0.2)})
    write(out / "metrics" / seed / "success.json", {"settings": {"episodes": 50}, "rates": {"/a/6": 0.5}})
    write(published / seed / "success.json",
          {"settings": {"episodes": 50}, "rates": {"/a/6": 0.9, "/b/6": 0.75}, "scores": {"/b/6": 0.8}})  # fmt: skip
    write(published / "main" / "lift" / "seed2" / "metrics.json", {"settings": {}, "rows": rows(d020=0.3)})
    write(out / "metrics" / seed / "datasets.json", {"fingerprints": {"d040": "aa"}})
    write(published / seed / "datasets.json", {"fingerprints": {"d040": "ff", "d020": "bb"}})
    write(out / "metrics" / "main" / "lift" / "seed0" / "metrics.json", {"settings": {"nll_steps": 4}, "rows": []})
    write(published / "main" / "lift" / "seed0" / "metrics.json", {"settings": {"nll_steps": 100}, "rows": rows(d020=0.4)})
    evaluation.adopt_published(published, out)

    def read(relative: str) -> dict:
        return json.loads((out / "metrics" / "main" / "lift" / relative).read_text())

    assert read("seed1/metrics.json")["rows"] == rows(d040=0.1, d020=0.2)  # its own d040 row wins
    assert read("seed1/success.json")["rates"] == {"/a/6": 0.5, "/b/6": 0.75}
    assert read("seed1/success.json")["scores"] == {"/b/6": 0.8}
    assert read("seed1/datasets.json")["fingerprints"] == {"d040": "aa", "d020": "bb"}
    assert read("seed2/metrics.json")["rows"] == rows(d020=0.3)  # a seed it had not got: copied whole
    assert read("seed0/metrics.json")["rows"] == []  # other settings: not mixed in


def test_a_run_stopped_by_sigterm_is_paused_not_failed_and_resumes(tmp_path, monkeypatch):
    preset, spec = _one_fake_run(tmp_path, monkeypatch, FAKE_TRAINER_KILL_AT="2")
    outcome = _local(preset, tmp_path).run([spec])
    assert outcome.paused == (spec,) and not outcome.failed and run_state(spec, tmp_path) == ("resume", 2)
    monkeypatch.delenv("FAKE_TRAINER_KILL_AT")
    assert _local(preset, tmp_path).run([spec]).done == (spec,)


def test_runs_of_one_seed_trained_on_other_recordings_of_the_demos_are_refused(tmp_path, monkeypatch):
    preset, two, _, _ = _finished_runs_of_2_and_3_demos(tmp_path, monkeypatch, kills=[])
    evaluation.evaluate_runs(preset, two, tmp_path)
    fake_sweep = evaluation.run_sweep

    def sweep_with_window_counts(cfg):
        rows, extra = fake_sweep(cfg)
        return [row | {"npe_episode_counts": [3, 4]} for row in rows], extra

    monkeypatch.setattr(evaluation, "run_sweep", sweep_with_window_counts)
    published = two[0]  # its checkpoints gone: reported from its stored row, as if trained in another checkout
    shutil.rmtree(published.train_dir(tmp_path) / "checkpoints")
    metrics_file = evaluation.metrics_dir(tmp_path, published.group, published.task, 0) / "metrics.json"

    def store_counts(counts: list[int]) -> None:
        stored = json.loads(metrics_file.read_text())
        for row in stored["rows"]:
            row["npe_episode_counts"] = counts if row["label"] == published.name else row.get("npe_episode_counts")
        metrics_file.write_text(json.dumps(stored))

    store_counts([3, 5])  # the last held-out episode one window longer: another recording
    with pytest.raises(StudyError, match="other recordings of the demos"):
        evaluation.evaluate_runs(preset, two, tmp_path)
    store_counts([3, 4])
    assert sorted(row["name"] for row in evaluation.evaluate_runs(preset, two, tmp_path)) == sorted(s.name for s in two)


def test_runs_of_one_seed_with_other_dataset_fingerprints_are_refused_and_each_runs_own_is_kept(
    tmp_path, monkeypatch
):
    preset, two, _, _ = _finished_runs_of_2_and_3_demos(tmp_path, monkeypatch, kills=[])
    for spec in two:
        write_json_atomic(spec.run_dir(tmp_path) / DATASET_FILE, {"fingerprint": "aaaa"})
    datasets_file = evaluation.metrics_dir(tmp_path, two[0].group, two[0].task, 0) / "datasets.json"
    evaluation.evaluate_runs(preset, two, tmp_path, fingerprints={"pusht": "aaaa"})
    assert json.loads(datasets_file.read_text()) == {"fingerprints": {s.name: "aaaa" for s in two}}
    published = two[0]  # its checkpoints gone: reported from stored files, as if trained in another checkout
    shutil.rmtree(published.train_dir(tmp_path) / "checkpoints")
    (published.run_dir(tmp_path) / DATASET_FILE).unlink()
    other = {s.name: "bbbb" if s == published else "aaaa" for s in two}
    datasets_file.write_text(json.dumps({"fingerprints": other}))
    with pytest.raises(StudyError, match=f"other recordings of the demos .*{published.name}: bbbb"):
        evaluation.evaluate_runs(preset, two, tmp_path, fingerprints={"pusht": "aaaa"})
    datasets_file.write_text(json.dumps({"fingerprints": {s.name: "aaaa" for s in two}}))
    assert len(evaluation.evaluate_runs(preset, two, tmp_path, fingerprints={"pusht": "aaaa"})) == 3
    with pytest.raises(StudyError, match="the demos in .*: cccc"):  # held-out demos of another recording
        evaluation.evaluate_runs(preset, two, tmp_path, fingerprints={"pusht": "cccc"})
    for spec in two:  # runs here whose fingerprint was not kept: unknown, so a stored one of their name goes
        (spec.run_dir(tmp_path) / DATASET_FILE).unlink(missing_ok=True)
    evaluation.evaluate_runs(preset, two[1:], tmp_path, fingerprints={"pusht": "cccc"})
    assert json.loads(datasets_file.read_text()) == {"fingerprints": {published.name: "aaaa"}}
