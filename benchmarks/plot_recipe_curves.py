"""Training loss, held-out NPE and success rate against steps for the runs of benchmarks/recipe_curves.sh.

Reads each run's lerobot-train log (the training loss: LeRobot prints one `loss:` per `--log_freq` steps;
for PAC-DP it is Eq. 9 and `denoise_loss:` its denoising part) and, per checkpoint, its held-out NPE and
success rate from pacdp-metrics' metrics.json or from pacdp-summarize-run's summary.json (which also has
LeRobot's avg_max_reward, PushT's score, plotted when present); writes curves.csv, curves.json and curves.png.

    python benchmarks/plot_recipe_curves.py --metrics outputs/recipe_lift/curves/metrics.json \
        --log DP=outputs/recipe_lift/dp.log --log PAC-DP=outputs/recipe_lift/pacdp.log --log-freq 100 \
        --title "Lift, 40 scripted demos" --output results/recipes/lift
    python benchmarks/plot_recipe_curves.py --summary PAC-DP=EVAL_10000/summary.json --summary PAC-DP=... \
        --log PAC-DP=pacdp.log --log-freq 100 --title "PushT" --output results/recipes/pusht/long
"""

import argparse
import csv
import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

LOSS = re.compile(r" loss:(?P<loss>[0-9.]+)")
DENOISE = re.compile(r"denoise_loss:(?P<loss>[0-9.]+)")
COLOURS = {"DP": "tab:blue", "BDP": "tab:orange", "PAC-DP": "tab:green"}
SUMMARY_EXTRAS = ("successes", "n_episodes", "ci95", "avg_max_reward")


def training_losses(log: Path, log_freq: int) -> list[dict]:
    """(step, loss, denoise_loss) of every log line of a lerobot-train log, in order."""
    rows = []
    for line in log.read_text(errors="replace").splitlines():
        if "step:" not in line or " loss:" not in line:
            continue
        denoise = DENOISE.search(line)
        rows.append({"step": (len(rows) + 1) * log_freq, "loss": float(LOSS.search(line)["loss"]),
                     "denoise_loss": float(denoise["loss"]) if denoise else None})  # fmt: skip
    return rows


def summary_row(label: str, path: str) -> dict:
    """A checkpoint row, as pacdp-metrics writes them, from the summary.json of pacdp-summarize-run."""
    summary = json.loads(Path(path).read_text())
    return {"label": label, "step": summary["train_steps"], "npe": summary["heldout_npe"],
            "npe_sem": summary.get("heldout_npe_sem"), "success_rate": summary["success_rate"],
            "successes": summary["successes"], "n_episodes": summary["n_episodes"], "ci95": summary["ci95"],
            "avg_max_reward": summary.get("avg_max_reward")}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--metrics", action="append", default=[], type=Path, help="pacdp-metrics metrics.json (repeatable)")
    parser.add_argument("--summary", action="append", default=[], help="LABEL=PATH of a checkpoint's pacdp-summarize-run summary.json (repeatable)")
    parser.add_argument("--log", action="append", required=True, help="LABEL=PATH of a run's lerobot-train log")
    parser.add_argument("--log-freq", type=int, required=True)
    parser.add_argument("--title", default="")
    parser.add_argument("--output", required=True, type=Path, help="directory for curves.{csv,json,png}")
    args = parser.parse_args()

    if not args.metrics and not args.summary:
        parser.error("pass --metrics or --summary for the checkpoints")
    checkpoints = [row for path in args.metrics for row in json.loads(path.read_text())["rows"]]
    checkpoints += [summary_row(*item.split("=", 1)) for item in args.summary]
    logs = dict(item.split("=", 1) for item in args.log)
    curves = {
        label: {
            "training": training_losses(Path(path), args.log_freq),
            "checkpoints": sorted(
                ({"step": r["step"], "heldout_npe": r["npe"], "heldout_npe_sem": r.get("npe_sem"),
                  "success_rate": r.get("success_rate")} | {k: r[k] for k in SUMMARY_EXTRAS if r.get(k) is not None}
                 for r in checkpoints if r["label"] == label),
                key=lambda r: r["step"],
            ),  # fmt: skip
        }
        for label, path in logs.items()
    }
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "curves.json").write_text(json.dumps(curves, indent=2) + "\n")
    with open(args.output / "curves.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["method", "step", "training_loss", "training_denoise_loss", "heldout_npe", "success_rate", "avg_max_reward"])
        for label, curve in curves.items():
            by_step = {r["step"]: r for r in curve["checkpoints"]}
            for r in curve["training"]:
                c = by_step.get(r["step"], {})
                writer.writerow([label, r["step"], r["loss"], r["denoise_loss"], c.get("heldout_npe"), c.get("success_rate"),
                                 c.get("avg_max_reward")])  # fmt: skip

    scored = any("avg_max_reward" in r for curve in curves.values() for r in curve["checkpoints"])
    fig, axes = plt.subplots(1, 3 + scored, figsize=(14 + 4.5 * scored, 3.8))
    for label, curve in curves.items():
        colour = COLOURS.get(label)
        steps = [r["step"] for r in curve["training"]]
        denoise = [r["denoise_loss"] if r["denoise_loss"] is not None else r["loss"] for r in curve["training"]]
        axes[0].plot(steps, denoise, label=label, color=colour)
        ckpt = curve["checkpoints"]
        axes[1].plot([r["step"] for r in ckpt], [r["heldout_npe"] for r in ckpt], "o-", label=label, color=colour)
        rated = [r for r in ckpt if r["success_rate"] is not None]
        axes[2].plot([r["step"] for r in rated], [r["success_rate"] for r in rated], "o-", label=label, color=colour)
        if scored:
            rewarded = [r for r in ckpt if "avg_max_reward" in r]
            axes[3].plot([r["step"] for r in rewarded], [r["avg_max_reward"] for r in rewarded], "o-", label=label, color=colour)
            axes[3].set_ylim(-0.02, 1.02)
    names = ("training denoising loss", "held-out NPE (EMA, posterior mean)", "success rate", "avg max reward (PushT score)")
    for ax, name in zip(axes, names[: len(axes)], strict=True):
        ax.set_xlabel("training step")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[2].set_ylim(-0.02, 1.02)
    axes[2].legend()
    fig.suptitle(args.title)
    fig.tight_layout()
    fig.savefig(args.output / "curves.png", dpi=110)
    print(f"wrote {args.output}/curves.csv, curves.json, curves.png")


if __name__ == "__main__":
    main()
