"""Exponential moving average of the trained weights, as Diffusion Policy acts with (Chi et al.'s EMAModel).

Decay of the update that follows `step` earlier ones (Chi's `get_decay(optimization_step)` with
inv_gamma = 1, min_value = 0, update_after_step = 0):
    k = step - 1;  decay = 0 if k <= 0 else min(1 - (1 + k)^-power, max_decay)
so the first two updates copy the weights and the average then lengthens with training (power 0.75:
decay 0.999 after ~10^4 updates). Each update: ema <- decay * ema + (1 - decay) * trained for every trained
parameter (mu and rho of the Bayesian layers, deterministic weights); parameters that are not trained and
buffers are copied. The Bayesian prior buffers are constants and skipped.
"""

import torch
from torch import nn

_CONSTANT_BUFFER_SUFFIXES = ("_prior_mu", "prior_rho")


def ema_decay(step: int, power: float, max_decay: float) -> float:
    """Chi et al.'s EMA decay for the update that follows `step` earlier updates (module docstring)."""
    k = step - 1
    if k <= 0:
        return 0.0
    return max(0.0, min(1.0 - (1.0 + k) ** -power, max_decay))


@torch.no_grad()
def update_ema(averaged: nn.Module, trained: nn.Module, decay: float) -> None:
    """One EMA step of `averaged` (a copy of `trained` with the same structure) towards `trained`."""
    ema_params, new_params, copied, sources = [], [], [], []
    for (_, ema), (_, new) in zip(averaged.named_parameters(), trained.named_parameters(), strict=True):
        if new.requires_grad:
            ema_params.append(ema)
            new_params.append(new)
        else:
            copied.append(ema)
            sources.append(new)
    for (name, ema), (_, new) in zip(averaged.named_buffers(), trained.named_buffers(), strict=True):
        if not name.endswith(_CONSTANT_BUFFER_SUFFIXES):
            copied.append(ema)
            sources.append(new)
    if ema_params:
        torch._foreach_lerp_(ema_params, new_params, 1.0 - decay)
    if copied:
        torch._foreach_copy_(copied, sources)
