import math

import pytest
import torch

from lerobot_pacdp.objective import confidence_term, pac_bayes_objective


@pytest.mark.parametrize("kl_weight", [0.0, 1e-4, 1.0])
def test_objective_matches_hand_computation_of_eq9(kl_weight):
    risk, kl, n, delta = 0.08, 3500.0, 25_650, 0.025
    b = kl_weight * kl + math.log(2 * math.sqrt(n) / delta)
    expected = risk + math.sqrt(2 * risk * b / n) + 2 * b / n
    result = pac_bayes_objective(
        torch.tensor(risk, dtype=torch.float64), torch.tensor(kl, dtype=torch.float64), n, delta, kl_weight
    )
    assert result.total.item() == pytest.approx(expected, rel=1e-12)
    assert result.complexity.item() == pytest.approx(b, rel=1e-12)
    assert result.sqrt_term.item() == pytest.approx(math.sqrt(2 * risk * b / n), rel=1e-12)
    assert result.linear_term.item() == pytest.approx(2 * b / n, rel=1e-12)


def test_confidence_term():
    assert confidence_term(100, 0.05) == pytest.approx(math.log(2 * 10 / 0.05))


def test_objective_gradients_are_finite_at_zero_risk_and_flow_to_kl():
    risk = torch.tensor(0.0, requires_grad=True)
    kl = torch.tensor(10.0, dtype=torch.float64, requires_grad=True)
    pac_bayes_objective(risk, kl, 100, 0.025, 0.5).total.backward()
    assert torch.isfinite(risk.grad)
    assert kl.grad.item() > 0


def test_objective_keeps_the_risk_dtype():
    result = pac_bayes_objective(torch.tensor(0.1), torch.tensor(5.0, dtype=torch.float64), 10, 0.1, 1.0)
    assert result.total.dtype == torch.float32
