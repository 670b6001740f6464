"""NPE: paired, seeded per-example draws; masking like training; errors clustered by episode; the held-out
data plumbing."""

import math

import pytest
import torch

from lerobot_pacdp.metrics.checkpoints import load_policy
from lerobot_pacdp.metrics.data import EvaluationData, split_from_train_config
from lerobot_pacdp.metrics.noise_prediction import (
    EpisodeSums,
    MeanWithError,
    alphas_cumprod,
    noise_prediction_errors,
    npe_draws,
    policy_denoiser,
)
from lerobot_pacdp.metrics.sweep import evaluate_checkpoint

from metrics_testing import EPISODE_LENGTHS, REPO_ID


def test_draws_depend_only_on_seed_and_example_index():
    indices = torch.tensor([3, 10, 11, 57])
    steps, noise = npe_draws(indices, seed=5, num_steps=100, chunk_shape=(8, 2))
    for i, index in enumerate(indices):  # one example at a time = any batch size
        step, eps = npe_draws(index.reshape(1), seed=5, num_steps=100, chunk_shape=(8, 2))
        assert step.item() == steps[i].item()
        assert torch.equal(eps[0], noise[i])
    reordered_steps, reordered_noise = npe_draws(indices.flip(0), seed=5, num_steps=100, chunk_shape=(8, 2))
    assert torch.equal(reordered_noise.flip(0), noise) and torch.equal(reordered_steps.flip(0), steps)
    other_steps, other_noise = npe_draws(indices, seed=6, num_steps=100, chunk_shape=(8, 2))
    assert not torch.equal(other_noise, noise)
    assert len(set(steps.tolist())) > 1  # t varies across examples


def test_the_run_split_is_lerobot_trains_held_out_split(tiny_runs):
    split = split_from_train_config(tiny_runs["pacdp_s0"] / "checkpoints" / "000100" / "pretrained_model")
    n = len(EPISODE_LENGTHS)
    assert split.repo_id == REPO_ID
    assert split.heldout_episodes == [3, 4, 5]  # the last ceil(6 * 0.34) = 3 episodes
    assert split.train_episodes == list(range(n - 3))


@pytest.fixture(scope="module")
def heldout(tiny_runs, tiny_dataset):
    loaded = load_policy(tiny_runs["pacdp_s0"] / "checkpoints" / "000100")
    return loaded, EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [3, 4, 5])


def test_windows_are_selected_like_training(heldout):
    _, data = heldout
    drop = data.config.drop_n_last_frames
    assert len(data) == sum(EPISODE_LENGTHS[e] - drop for e in (3, 4, 5))


def test_npe_does_not_depend_on_the_batch_size(heldout):
    loaded, data = heldout
    small = evaluate_checkpoint(loaded, data, seed=1, batch_size=5, nll=False)
    large = evaluate_checkpoint(loaded, data, seed=1, batch_size=64, nll=False)
    assert small.npe.n == large.npe.n == len(data)
    assert small.npe.mean == pytest.approx(large.npe.mean, rel=1e-6)
    assert small.npe.sem == pytest.approx(large.npe.sem, rel=1e-5)
    assert evaluate_checkpoint(loaded, data, seed=2, batch_size=64, nll=False).npe.mean != large.npe.mean


def test_two_checkpoints_see_identical_steps_and_noisy_inputs(tiny_runs, heldout):
    _, data = heldout
    seen = {"000100": [], "000300": []}
    for name, calls in seen.items():
        loaded = load_policy(tiny_runs["pacdp_s0"] / "checkpoints" / name)
        hook = loaded.policy.diffusion.unet.register_forward_pre_hook(
            lambda module, args, calls=calls: calls.append((args[0].clone(), args[1].clone()))
        )
        evaluate_checkpoint(loaded, data, seed=0, batch_size=16, nll=False)
        hook.remove()
    assert len(seen["000100"]) == len(seen["000300"]) > 1
    for (noisy_a, steps_a), (noisy_b, steps_b) in zip(seen["000100"], seen["000300"], strict=True):
        assert torch.equal(steps_a, steps_b)
        assert torch.equal(noisy_a, noisy_b)  # same actions, same normalisation, same t and eps


def test_padded_actions_are_masked_like_training(heldout):
    loaded, data = heldout
    batch = next(data.batches(loaded, batch_size=len(data)))
    assert (~batch.valid).any()  # the held-out windows do reach past episode ends
    alpha_bar = alphas_cumprod(loaded.policy)
    denoiser = policy_denoiser(loaded.policy, batch.global_cond)
    errors = noise_prediction_errors(denoiser, batch.actions, batch.valid, batch.index, alpha_bar, seed=0)
    garbage = batch.actions.masked_fill(~batch.valid.unsqueeze(-1), 1e3)  # what is padded cannot matter...
    moved = noise_prediction_errors(denoiser, garbage, batch.valid, batch.index, alpha_bar, seed=0)
    padded_rows = (~batch.valid).any(dim=1)
    # ...except through the U-Net's receptive field; unpadded windows are untouched.
    torch.testing.assert_close(errors[~padded_rows], moved[~padded_rows])
    # Per example: the mean over real entries of ||eps - eps_hat||^2, as LeRobot's masked loss for a batch of one.
    steps, noise = npe_draws(batch.index, 0, len(alpha_bar), tuple(batch.actions.shape[1:]))
    ab = alpha_bar.float()[steps].reshape(-1, 1, 1)
    prediction = denoiser(ab.sqrt() * batch.actions + (1 - ab).sqrt() * noise, steps)
    row = int(torch.nonzero(padded_rows)[0])
    real = batch.valid[row]
    expected = (prediction[row][real] - noise[row][real]).square().mean().item()
    assert errors[row].item() == pytest.approx(expected, rel=1e-5)


def test_standard_error_is_over_examples():
    values = torch.tensor([1.0, 2.0, 3.0, 4.0])
    stats = MeanWithError.of(values)
    assert stats.mean == 2.5 and stats.n == 4
    assert stats.sem == pytest.approx(values.std().item() / 2)


def test_the_standard_error_is_clustered_by_episode_by_hand():
    values, episodes = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]), torch.tensor([7, 7, 7, 9, 9, 9])
    clustered = EpisodeSums.of(values, episodes).mean_with_error()
    # mean 3.5; residual sums per episode 6 - 3 * 3.5 = -4.5 and 15 - 10.5 = 4.5;
    # var = G / (G - 1) * sum r_g^2 / n^2 = 2 * 40.5 / 36 = 2.25.
    assert clustered.mean == 3.5 and clustered.n == 6 and clustered.clusters == 2
    assert clustered.sem == pytest.approx(1.5)
    assert MeanWithError.of(values).sem == pytest.approx(values.std().item() / math.sqrt(6))  # 0.76: too optimistic
    # One window per episode: the clustered error is the independent-examples error.
    singletons = EpisodeSums.of(values, torch.arange(6)).mean_with_error()
    assert singletons.sem == pytest.approx(MeanWithError.of(values).sem)


def test_paired_difference_of_two_checkpoints_by_hand():
    episodes = torch.tensor([0, 0, 1, 1])
    a, b = EpisodeSums.of(torch.tensor([1.0, 2.0, 3.0, 4.0]), episodes), EpisodeSums.of(torch.tensor([1.0, 1.0, 2.0, 2.0]), episodes)
    diff = a.minus(b).mean_with_error()
    # differences 0, 1, 1, 2: mean 1; residual sums 1 - 2 = -1 and 3 - 2 = 1; var = 2 * 2 / 16.
    assert diff.mean == 1.0 and diff.sem == pytest.approx(0.5)
    with pytest.raises(ValueError, match="same windows"):
        a.minus(EpisodeSums.of(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0, 0, 1])))


def test_cached_windows_are_lerobots_windows(heldout):
    loaded, data = heldout
    cached = next(data.batches(loaded, batch_size=len(data)))
    lerobot = EvaluationData(data.config, REPO_ID, data.dataset.root, [3, 4, 5], cache=False)
    direct = next(lerobot.batches(loaded, batch_size=len(data)))
    for name in ("actions", "valid", "global_cond", "index", "episode"):
        assert torch.equal(getattr(cached, name), getattr(direct, name)), name
