"""Stands in for lerobot-train in the study's tests: same CLI, same checkpoint files, no training.

Writes a complete `checkpoints/<step>/{pretrained_model,training_state}` (every file LeRobot writes, as
`lerobot_pacdp.train_runs.checkpoint_problem` checks them) every `save_freq` steps and points `last` at each.
FAKE_TRAINER_FAIL_AT=<step> exits 1 right after that checkpoint (an interrupted run); FAKE_TRAINER_KILL_AT=<step>
sends itself SIGTERM there instead (a user stopping it); FAKE_TRAINER_PREEMPT_AT=<step> sends SIGUSR2 (what
SLURM sends a job it preempts) to the process that started it there, on a fresh run only, and waits to be
stopped; FAKE_TRAINER_CALLS=<file> gets one line per call; FAKE_TRAINER_SLEEP=<s> waits after each checkpoint.
"""

import json
import os
import signal
import sys
import time
from pathlib import Path

EMPTY_SAFETENSORS = len(b"{}").to_bytes(8, "little") + b"{}"  # a header with no tensors: a complete file


def write_checkpoint(step_dir: Path, config: dict, step: int) -> None:
    """Every file LeRobot's save_checkpoint writes, with valid (tiny) contents."""
    pretrained, state = step_dir / "pretrained_model", step_dir / "training_state"
    pretrained.mkdir(parents=True, exist_ok=True)
    state.mkdir(parents=True, exist_ok=True)
    (pretrained / "config.json").write_text(json.dumps(config["policy"]))
    (pretrained / "model.safetensors").write_bytes(EMPTY_SAFETENSORS)
    (pretrained / "train_config.json").write_text(json.dumps(config))
    for name in ("policy_preprocessor.json", "policy_postprocessor.json"):
        (pretrained / name).write_text(json.dumps({"steps": []}))
    (state / "training_step.json").write_text(json.dumps({"step": step}))
    for name in ("rng_state.safetensors", "optimizer_state.safetensors"):
        (state / name).write_bytes(EMPTY_SAFETENSORS)
    (state / "optimizer_param_groups.json").write_text("[]")


def main() -> None:
    args = dict(a.removeprefix("--").split("=", 1) for a in sys.argv[1:])
    config_path = Path(args["config_path"])
    config = json.loads(config_path.read_text())
    out = Path(config["output_dir"])
    resume = args.get("resume") == "true"
    step = 0
    if resume:
        step = json.loads((config_path.parents[1] / "training_state" / "training_step.json").read_text())["step"]
    elif out.exists():
        sys.exit(f"Output directory {out} already exists and resume is False")
    if os.environ.get("FAKE_TRAINER_CALLS"):
        with open(os.environ["FAKE_TRAINER_CALLS"], "a") as f:
            f.write(f"{config['policy']['type']} {out.parent.name} resume={resume} from={step}\n")
    fail_at = int(os.environ.get("FAKE_TRAINER_FAIL_AT", -1))
    kill_at = int(os.environ.get("FAKE_TRAINER_KILL_AT", -1))
    preempt_at = -1 if resume else int(os.environ.get("FAKE_TRAINER_PREEMPT_AT", -1))
    while step < config["steps"]:
        step = min(step + config["save_freq"], config["steps"])
        ckpt = out / "checkpoints" / f"{step:06d}"
        write_checkpoint(ckpt, config, step)
        last = out / "checkpoints" / "last"
        if last.is_symlink():
            last.unlink()
        last.symlink_to(ckpt.name)
        print(f"Training: {step}/{config['steps']} [", flush=True)
        if step == fail_at:
            sys.exit(1)
        if step == kill_at:
            os.kill(os.getpid(), signal.SIGTERM)
        if step == preempt_at:
            os.kill(os.getppid(), signal.SIGUSR2)
            time.sleep(600)  # the job stops us
        time.sleep(float(os.environ.get("FAKE_TRAINER_SLEEP", 0)))


if __name__ == "__main__":
    main()
