"""A PAC-DP prior learnt on a disjoint split of the demonstrations (data-dependent prior, PBB recipe).

With a data-free prior (sigma_p = 0.011 around a random init) a U-Net's KL(Q||P) dwarfs the number of
demonstrations and the certificate is vacuous. Centring the prior on a network trained on split A and
certifying on a disjoint split B keeps the bound valid (the prior never sees B) and the KL small.

Recipe (split A = demos 0-69, split B = demos 70-199 here; results/certificate/ runs it on PushT):

1. Train DP (or BDP/PAC-DP) on split A:
   lerobot-train --policy.type=diffusion ... --dataset.episodes='[0,...,69]' --output_dir=outputs/prior_A
2. Build the PAC-DP prior checkpoint from it (prior means = initial posterior means = its weights; its
   deterministic tensors stay fixed during fine-tuning, `freeze_deterministic=true`):
   pacdp-learned-prior --source=outputs/prior_A/checkpoints/last/pretrained_model \
       --output_dir=outputs/prior_A_pacdp --prior_rho=-4.5 --kl_weight=1e-4
3. Fine-tune PAC-DP on split B (N is derived from split B's training windows):
   lerobot-train --policy.path=outputs/prior_A_pacdp --dataset.repo_id=... \
       --dataset.episodes='[70,...,199]' --dataset.eval_split=0.3 --output_dir=outputs/pacdp_B
4. Certify on split B's training demonstrations (and bound the mean network on B's held-out ones):
   pacdp-certify --checkpoint=outputs/pacdp_B/checkpoints/last/pretrained_model --prior=outputs/prior_A_pacdp

`learned_prior.json` in the built directory records split A's episodes (its run's training and held-out
ones), and `pacdp-certify --prior` refuses to certify on, or test on, any of them; it also refuses a
checkpoint whose prior tensors, deterministic tensors or normalisation statistics are not the prior
directory's. Normalisation: lerobot-train normalises with the dataset's `meta/stats.json`, so for a prior
(and a loss) independent of split B those statistics must come from split A alone (results/certificate/
shows how); with LeRobot's default whole-dataset statistics they depend, weakly, on split B.
"""

import json
import logging
import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lerobot.configs.policies import PreTrainedConfig
from safetensors.torch import load_file

from lerobot_pacdp.atomic_io import staged_directory
from lerobot_pacdp.bayesian_layers import kl_divergence
from lerobot_pacdp.cli_errors import run_draccus_cli
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.metrics.checkpoints import (
    CheckpointNotFoundError,
    MetricsError,
    checkpoint_policy_type,
    resolve_pretrained_dir,
)
from lerobot_pacdp.metrics.data import split_from_train_config
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

logger = logging.getLogger(__name__)

PROVENANCE_FILE = "learned_prior.json"
PROCESSOR_PATTERNS = ("policy_preprocessor*", "policy_postprocessor*")
_PRIOR_MU_SUFFIX = "_prior_mu"
_KEPT_SUFFIXES = ("_rho", "prior_rho")  # the new posterior's rho starts at the prior's rho (Q = P)
_COMPILED_PREFIX = "_orig_mod."  # torch.compile'd U-Nets save their keys under this prefix
_ACTING_PREFIX, _RAW_PREFIX = "diffusion.", "raw_diffusion."  # with EMA: the average acts, the raw copy trains
_UPDATES_KEY = "num_updates"  # the EMA's update counter: a fresh run starts at 0


def learned_prior_state(policy: PacdpPolicy, source: dict) -> dict:
    """The PAC-DP state dict with prior means and posterior means both set to the source's weights.

    A DP checkpoint's `...weight` / `...bias` have the names of PAC-DP's mu; a PAC-DP/BDP source contributes
    its mu (its own rho and prior are dropped). Every other tensor (GroupNorm, FiLM projections,
    observation encoders) is copied as is. The source's acting network (its EMA, if it has one) is what
    both copies of an EMA policy start from.
    """
    source = {key.replace(_COMPILED_PREFIX, ""): value for key, value in source.items()}
    source = {k: v for k, v in source.items() if not k.startswith(_RAW_PREFIX) and k != _UPDATES_KEY}
    state, used, problems = policy.state_dict(), set(), []
    for key, value in state.items():
        if key.endswith(_KEPT_SUFFIXES) or key == _UPDATES_KEY:
            continue
        source_key = _ACTING_PREFIX + key.removeprefix(_RAW_PREFIX) if key.startswith(_RAW_PREFIX) else key
        source_key = source_key.removesuffix(_PRIOR_MU_SUFFIX)
        if source_key not in source:
            problems.append(f"{source_key} missing")
        elif source[source_key].shape != value.shape:
            problems.append(f"{source_key} has shape {tuple(source[source_key].shape)}, expected {tuple(value.shape)}")
        else:
            state[key] = source[source_key].to(value.dtype)
            used.add(source_key)
    unused = [k for k in source if k not in used and not k.endswith((*_KEPT_SUFFIXES, _PRIOR_MU_SUFFIX))]
    problems += [f"{k} has no place in the PAC-DP network" for k in unused]
    if problems:
        raise MetricsError(
            f"the source weights do not fit a PAC-DP network of the same configuration: {'; '.join(problems[:6])}"
            f"{' ...' if len(problems) > 6 else ''}"
        )
    return state


def build_learned_prior(
    source: str | Path,
    output_dir: str | Path,
    *,
    prior_rho: float | None = None,
    kl_weight: float | None = None,
    delta: float | None = None,
    bayesian_conditioning: bool | None = None,
    freeze_deterministic: bool = True,
) -> Path:
    """Save a PAC-DP checkpoint whose prior and initial posterior means are `source`'s weights.

    The architecture, features, normalisation and diffusion settings are the source's; the PAC-Bayes
    fields are the source's (PAC-DP/BDP) or PacdpConfig's defaults (DP), unless overridden. N is left
    unset so that lerobot-train derives it from the split the prior is fine-tuned on. With
    `freeze_deterministic` (default) fine-tuning keeps the source's deterministic tensors, which
    `pacdp-certify --prior` requires.
    """
    source_dir = resolve_pretrained_dir(source)
    source_type = checkpoint_policy_type(source_dir)
    output_dir = Path(output_dir)
    if output_dir.exists() and any(output_dir.iterdir()):
        raise MetricsError(f"{output_dir} exists and is not empty; choose a new --output_dir.")
    source_config = PreTrainedConfig.from_pretrained(source_dir)
    overrides = {"prior_rho": prior_rho, "kl_weight": kl_weight, "delta": delta,
                 "bayesian_conditioning": bayesian_conditioning}  # fmt: skip
    config = PacdpConfig.from_diffusion(
        source_config, compile_model=False, num_train_samples=None, device="cpu", pretrained_path=None,
        bayesian=True, freeze_deterministic=freeze_deterministic,
        **{k: v for k, v in overrides.items() if v is not None},
    )  # fmt: skip

    policy = PacdpPolicy(config)
    policy.load_state_dict(learned_prior_state(policy, load_file(source_dir / "model.safetensors")), strict=True)
    kl = kl_divergence(policy.unet).item()
    if kl != 0.0:
        raise AssertionError(f"KL(Q||P) of the freshly built prior checkpoint is {kl}, expected exactly 0")

    with staged_directory(output_dir) as staging:
        _write_prior_checkpoint(policy, source_dir, source_type, staging)
    return output_dir


def _write_prior_checkpoint(policy: PacdpPolicy, source_dir: Path, source_type: str, output_dir: Path) -> None:
    """The prior checkpoint, the source's processors and the provenance record (which episodes it saw)."""
    policy.save_pretrained(output_dir)
    for pattern in PROCESSOR_PATTERNS:
        for path in source_dir.glob(pattern):
            shutil.copy2(path, output_dir / path.name)
    try:  # the split-A run's training and held-out episodes (held-out ones may have guided model selection)
        split = split_from_train_config(source_dir)
        prior_episodes = sorted(split.train_episodes + split.heldout_episodes)
    except MetricsError as exc:
        logger.warning("cannot record the prior's episodes (%s); `pacdp-certify --prior` cannot check the split.", exc)
        prior_episodes = None
    provenance = {"source": str(source_dir), "source_type": source_type, "prior_episodes": prior_episodes}
    (output_dir / PROVENANCE_FILE).write_text(json.dumps(provenance, indent=2))


def check_disjoint_from_prior(prior_dir: str | Path, certified_episodes: Sequence[int]) -> None:
    """Refuse to certify on demonstrations the learnt prior was trained on (the bound would be invalid)."""
    provenance_file = Path(prior_dir) / PROVENANCE_FILE
    if not provenance_file.is_file():
        raise CheckpointNotFoundError(f"{prior_dir} has no {PROVENANCE_FILE}: it was not built by pacdp-learned-prior.")
    prior_episodes = json.loads(provenance_file.read_text())["prior_episodes"]
    if prior_episodes is None:
        raise MetricsError(
            f"{provenance_file} does not record the prior's episodes; check the split by hand and certify "
            "without --prior."
        )
    overlap = sorted(set(prior_episodes) & set(certified_episodes))
    if overlap:
        raise MetricsError(
            f"the prior of {prior_dir} was learnt from {len(overlap)} of the certified demonstrations "
            f"(e.g. {overlap[:10]}); certify on a split disjoint from the prior's."
        )


@dataclass
class LearnedPriorConfig:
    """`pacdp-learned-prior`: a PAC-DP checkpoint centred on a DP/BDP/PAC-DP checkpoint trained on split A."""

    source: Path | None = None  # .../checkpoints/<step>/pretrained_model of the split-A run
    output_dir: Path | None = None
    prior_rho: float | None = None
    kl_weight: float | None = None
    delta: float | None = None
    bayesian_conditioning: bool | None = None
    # Keep the source's deterministic tensors fixed while fine-tuning (needed by pacdp-certify --prior).
    freeze_deterministic: bool = True


def _build_and_report(cfg: LearnedPriorConfig) -> int:
    if cfg.source is None or cfg.output_dir is None:
        raise MetricsError("pass --source=<split-A checkpoint> and --output_dir=<new directory>")
    out = build_learned_prior(
        cfg.source,
        cfg.output_dir,
        prior_rho=cfg.prior_rho,
        kl_weight=cfg.kl_weight,
        delta=cfg.delta,
        bayesian_conditioning=cfg.bayesian_conditioning,
        freeze_deterministic=cfg.freeze_deterministic,
    )
    print(f"Wrote the PAC-DP prior checkpoint {out}. Fine-tune it on the disjoint split with:")
    print(f"  lerobot-train --policy.path={out} --dataset.episodes='[<split B>]' ...")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_draccus_cli("pacdp-learned-prior", LearnedPriorConfig, _build_and_report, argv)


if __name__ == "__main__":
    sys.exit(main())
