"""Stands in for lerobot-train in the runner's tests: same CLI, same checkpoint layout, no training.

Writes `checkpoints/<step>/{pretrained_model,training_state}` every `save_freq` steps and points `last`
at each. FAKE_TRAINER_FAIL_AT=<step> exits 1 right after that checkpoint (an interrupted run);
FAKE_TRAINER_KILL_AT=<step> sends itself SIGTERM there instead (a user stopping it); FAKE_TRAINER_CALLS=<file>
gets one line per call; FAKE_TRAINER_SLEEP=<s> waits after each checkpoint.
"""

import json
import os
import signal
import sys
import time
from pathlib import Path

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
while step < config["steps"]:
    step = min(step + config["save_freq"], config["steps"])
    ckpt = out / "checkpoints" / f"{step:06d}"
    (ckpt / "pretrained_model").mkdir(parents=True, exist_ok=True)
    (ckpt / "training_state").mkdir(parents=True, exist_ok=True)
    (ckpt / "pretrained_model" / "model.safetensors").write_bytes(b"")
    (ckpt / "pretrained_model" / "train_config.json").write_text(json.dumps(config))
    (ckpt / "training_state" / "training_step.json").write_text(json.dumps({"step": step}))
    last = out / "checkpoints" / "last"
    if last.is_symlink():
        last.unlink()
    last.symlink_to(ckpt.name)
    print(f"Training: {step}/{config['steps']} [", flush=True)
    if step == fail_at:
        sys.exit(1)
    if step == kill_at:
        os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(float(os.environ.get("FAKE_TRAINER_SLEEP", 0)))
