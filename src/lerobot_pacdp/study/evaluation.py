"""The metrics of a study's runs: `lerobot_pacdp.metrics.sweep` on every checkpoint, on each seed's held-out
demos, plus the success rate and score (`avg_max_reward`) of each run's last checkpoints (the sweep's
`rollout_outcome`, LeRobot's own rollout loop).

Each (group, task, seed) keeps its rows in `<output_dir>/metrics/<group>/<task>/seed<k>/metrics.json`, its
success rates and scores in `success.json` beside it, and the fingerprint of the demos each run trained on
(where kept) in `datasets.json`; rerunning reuses them. A run with no checkpoint on
disk (its checkpoints deleted, or published from another checkout into the committed `results/`) is reported
from those files alone, beside the runs of its seed that are swept here.
"""

import json
import logging
import multiprocessing
from collections import defaultdict
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import draccus

from lerobot_pacdp.metrics.checkpoints import load_policy
from lerobot_pacdp.metrics.sweep import RolloutOutcome, SweepConfig, rollout_outcome, run_sweep
from lerobot_pacdp.study.plan import RunSpec
from lerobot_pacdp.study.presets import Preset, StudyError
from lerobot_pacdp.study.state import run_state, trained_on, write_json_atomic
from lerobot_pacdp.train_runs import step_dirs

logger = logging.getLogger("pacdp-study")

SPEC_FIELDS = ("task", "demos", "seed", "method", "kl_weight", "prior_rho", "name", "group")


def metrics_dir(output_dir: Path, group: str, task: str, seed: int) -> Path:
    return output_dir / "metrics" / group / task / f"seed{seed}"


def _spec_fields(spec: RunSpec) -> dict:
    return {name: getattr(spec, name) for name in SPEC_FIELDS}


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _stored_rows(directory: Path, names: set[str]) -> list[dict]:
    stored = _read_json(directory / "metrics.json")
    return [row for row in stored["rows"] if row["label"] in names] if stored else []


def _merge_stored(target: Path, other: dict | None) -> None:
    """Add to `target` (a metrics.json, success.json or datasets.json) the rows, success rates or fingerprints
    of the runs it lacks from `other`, where both were computed with the same settings; a missing `target`
    gets `other` whole. Keeps the cached results of runs a call did not sweep (a subset of demos or methods,
    seeds published elsewhere)."""
    if other is None:
        return
    ours = _read_json(target)
    if ours is None:
        write_json_atomic(target, other)
    elif ours.get("settings") == other.get("settings") and "rows" in ours:
        labels = {row["label"] for row in ours["rows"]}
        write_json_atomic(target, ours | {"rows": ours["rows"] + [r for r in other["rows"] if r["label"] not in labels]})
    elif ours.get("settings") == other.get("settings") and "rates" in ours:
        merged = {key: other.get(key, {}) | ours.get(key, {}) for key in ("rates", "scores")}
        write_json_atomic(target, ours | merged)
    elif "fingerprints" in ours:
        write_json_atomic(target, {"fingerprints": other["fingerprints"] | ours["fingerprints"]})


def adopt_published(published: Path, output_dir: Path) -> None:
    """Merge a published study's `metrics/` (the committed `results/.../metrics`) into `output_dir`'s cache, run
    by run (`_merge_stored`): lets one checkout publish tables over seeds trained in others."""
    for source in sorted(published.rglob("*.json")):
        _merge_stored(output_dir / "metrics" / source.relative_to(published), _read_json(source))


def _sweep_rows(preset: Preset, ready: list[RunSpec], directory: Path, output_dir: Path) -> list[dict]:
    """`run_sweep` over the checkpoints of `ready` runs of one seed, on its held-out demos."""
    logger.info("metrics: %s, %d runs on %d held-out demos", directory, len(ready), len(ready[0].heldout_episodes))
    sweep = SweepConfig(
        runs=[s.train_dir(output_dir) for s in ready],
        labels=[s.name for s in ready],
        output_dir=directory,
        episodes=list(ready[0].heldout_episodes),
        batch_size=preset.metrics_batch_size,
        nll_steps=preset.nll_steps,
        frame_stride=preset.frame_stride,
        last_k=preset.last_k,
        device=preset.device,
    )
    metrics_file, backup = directory / "metrics.json", directory / "metrics.before_sweep.json"
    if backup.is_file():  # a pass killed mid-sweep: the rows of the runs it was not sweeping are only here
        _merge_stored(metrics_file, _read_json(backup))
    previous = _read_json(metrics_file)
    if previous is not None:
        write_json_atomic(backup, previous)
    swept, _ = run_sweep(sweep)  # rewrites metrics.json with the swept runs' rows only
    _merge_stored(metrics_file, previous)
    backup.unlink(missing_ok=True)
    return swept


def _check_same_demos(swept: list[dict], stored: list[dict], where: str) -> None:
    """The runs of one seed swept here and those reported from stored rows (trained in another checkout) must
    have trained on the same demos: their held-out window counts, which follow from the demos' lengths, agree
    (another recording of scripted demos, e.g. before OpenBLAS's kernels were pinned, has other lengths). The
    check for runs with no fingerprint kept (`_keep_and_check_fingerprints`); a recording that differs only in
    its values passes it."""
    counts = {tuple(row["npe_episode_counts"]) for row in swept + stored if row.get("npe_episode_counts")}
    if len(counts) > 1:
        raise StudyError(f"{where}: the runs here and the stored (published) ones held out windows of other lengths, "
                         "so they trained on other recordings of the demos; train the stored runs here too, or "
                         "record the demos with the pacdp-scripted-demos those runs used.")  # fmt: skip


def _keep_and_check_fingerprints(runs: list[RunSpec], on_disk: list[RunSpec], directory: Path,
                                 output_dir: Path, current: str | None, where: str) -> None:
    """Keep in `datasets.json` the fingerprint of the demos each run here trained on, and refuse runs of one
    seed (here, or stored from another checkout) that trained on other recordings, or on another one than the
    demos under `output_dir`, whose held-out episodes the metrics use. Runs with no fingerprint kept pass."""
    file = directory / "datasets.json"
    stored = (_read_json(file) or {}).get("fingerprints", {})
    here = {s.name: trained_on(s, output_dir) for s in on_disk}  # their own, not a stored one of their name
    kept = {name: fingerprint for name, fingerprint in stored.items() if name not in here}
    kept |= {name: fingerprint for name, fingerprint in here.items() if fingerprint is not None}
    if kept != stored:
        write_json_atomic(file, {"fingerprints": kept})
    known = {s.name: kept[s.name] for s in runs if s.name in kept}
    if current is not None:
        known[f"the demos in {output_dir}"] = current
    if len(set(known.values())) > 1:
        listed = ", ".join(f"{name}: {fingerprint}" for name, fingerprint in sorted(known.items()))
        raise StudyError(f"{where}: runs trained on other recordings of the demos ({listed}); train them on "
                         "one recording, in one --output_dir.")  # fmt: skip


def evaluate_runs(preset: Preset, specs: list[RunSpec], output_dir: Path, unfinished: bool = False,
                  fingerprints: dict[str, str | None] | None = None) -> list[dict]:  # fmt: skip
    """One row per checkpoint of every finished run (the sweep's columns plus the run's spec); with
    `unfinished`, also of runs stopped before their last step, up to their last checkpoint. `fingerprints`
    (by task) are those of the demos under `output_dir` (`data.dataset_fingerprint`)."""
    wanted = ("done", "resume") if unfinished else ("done",)
    groups: dict[tuple, list[RunSpec]] = defaultdict(list)
    for spec in specs:
        groups[(spec.group, spec.task, spec.seed)].append(spec)
    rows = []
    for (group, task, seed), runs in groups.items():
        directory = metrics_dir(output_dir, group, task, seed)
        by_name = {s.name: s for s in runs}
        on_disk = [s for s in runs if step_dirs(s.train_dir(output_dir))]
        current = (fingerprints or {}).get(task)
        _keep_and_check_fingerprints(runs, on_disk, directory, output_dir, current, f"{task} seed {seed}")
        ready = [s for s in on_disk if run_state(s, output_dir).status in wanted]
        group_rows = _sweep_rows(preset, ready, directory, output_dir) if ready else []
        # runs with no checkpoint here (published from another checkout, or deleted) keep their stored rows
        elsewhere = {s.name for s in runs if s not in on_disk}
        if stored := _stored_rows(directory, elsewhere):
            logger.info("metrics: %d rows of runs with no checkpoint on disk from %s", len(stored), directory)
            _check_same_demos(group_rows, stored, f"{task} seed {seed}")
        group_rows += stored
        if not group_rows:
            continue
        group_rows = [row | _spec_fields(by_name[row["label"]]) for row in group_rows]
        if preset.success_episodes > 0:
            add_success_rates(preset, group_rows, directory / "success.json")
        rows += group_rows
    return rows


def add_success_rates(preset: Preset, rows: list[dict], cache_file: Path) -> None:
    """Success rate and score (`avg_max_reward`) of each run's `success_checkpoints`, cached in `cache_file` as
    each lands; checkpoints not on disk (runs published from another checkout) get only what is cached, and a
    rate cached before scores were kept keeps no score (remove it from the cache to roll it out again). Only
    the checkpoints scheduled now get a rate: one cached by a report of the run while unfinished (its last
    checkpoint then) stays cached but off its curve."""
    task = preset.task(rows[0]["task"])
    env_dict = task.train_config["env"]
    settings = {"episodes": preset.success_episodes, "seed": 0, "env": env_dict}
    cache = json.loads(cache_file.read_text()) if cache_file.is_file() else {}
    same = cache.get("settings") == settings
    rates, scores = (cache.get("rates", {}), cache.get("scores", {})) if same else ({}, {})
    by_run: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        by_run[row["run"]].append(row)
    wanted = [c for run_rows in by_run.values()
              for c in success_checkpoints(run_rows, preset.success_last_k, preset.success_every)]  # fmt: skip
    todo = [c for c in wanted if c not in rates and Path(c).is_dir()]
    for ckpt, outcome in _rollouts(todo, env_dict, preset):
        rates[ckpt], scores[ckpt] = outcome.success_rate, outcome.avg_max_reward
        logger.info("success rate %s: %.3f (score %.3f) over %d rollouts", ckpt, outcome.success_rate,
                    outcome.avg_max_reward, preset.success_episodes)  # fmt: skip
        write_json_atomic(cache_file, {"settings": settings, "rates": rates, "scores": scores})
    scheduled = set(wanted)
    for row in rows:
        if row["checkpoint"] in rates and row["checkpoint"] in scheduled:
            row["success_rate"] = rates[row["checkpoint"]]
            row["avg_max_reward"] = scores.get(row["checkpoint"])


def success_checkpoints(run_rows: list[dict], last_k: int, every: int = 0) -> list[str]:
    """The checkpoints of one run to roll out, by step: its last `last_k`, and (for the success curves) each
    one whose step is a multiple of `every` (0: none)."""
    ordered = sorted(run_rows, key=lambda r: r["step"])
    last = {r["checkpoint"] for r in ordered[-last_k:]} if last_k > 0 else set()
    return [r["checkpoint"] for r in ordered if r["checkpoint"] in last or (every > 0 and r["step"] % every == 0)]


def checkpoint_rollouts(checkpoint: str, env_dict: dict, episodes: int, device: str | None) -> RolloutOutcome:
    """`rollout_outcome` of one checkpoint over `episodes` rollouts (seeds 0..episodes-1) in fresh envs
    (LeRobot's loop closes the envs it is given)."""
    from lerobot.envs.configs import EnvConfig

    env_cfg = draccus.decode(EnvConfig, env_dict)
    return rollout_outcome(load_policy(checkpoint, device), env_cfg, min(10, episodes), episodes, seed=0)


def _one_thread_worker() -> None:
    import torch

    torch.set_num_threads(1)


def _rollouts(checkpoints: list[str], env_dict: dict, preset: Preset) -> Iterator[tuple[str, RolloutOutcome]]:
    """(checkpoint, its rollouts' outcome) as each finishes: `preset.jobs` checkpoints side by side (one thread
    each, in spawned processes; rollouts are most of a CPU study's metrics time), or one after another."""
    episodes = preset.success_episodes
    if preset.jobs < 2 or len(checkpoints) < 2:
        for ckpt in checkpoints:
            yield ckpt, checkpoint_rollouts(ckpt, env_dict, episodes, preset.device)
        return
    workers = min(preset.jobs, len(checkpoints))
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_one_thread_worker) as pool:  # fmt: skip
        futures = {pool.submit(checkpoint_rollouts, c, env_dict, episodes, preset.device): c for c in checkpoints}
        for future in as_completed(futures):
            yield futures[future], future.result()
