"""kl^-1 against cases with a known answer."""

import math

import pytest

from lerobot_pacdp.metrics.kl_inverse import binary_kl, kl_inverse


@pytest.mark.parametrize("q", [0.0, 1e-4, 0.05, 0.3, 0.5, 0.9, 0.999])
@pytest.mark.parametrize("c", [1e-6, 1e-3, 0.05, 0.5, 2.0])
def test_the_returned_p_solves_kl_q_p_equals_c(q, c):
    p = kl_inverse(q, c)
    assert q < p <= 1.0
    # The upper end of a bracket of width <= 1e-12 around the exact inverse: never below it.
    assert binary_kl(q, p) >= c
    assert binary_kl(q, max(q, p - 1e-11)) <= c
    if 1.0 - p > 1e-6:  # away from p = 1, where kl(q || .) is steep, the value itself is matched too
        assert binary_kl(q, p) == pytest.approx(c, rel=1e-6)


@pytest.mark.parametrize("c", [1e-4, 0.01, 0.7, 3.0])
def test_q_zero_has_the_closed_form_one_minus_exp_minus_c(c):
    # kl(0 || p) = -ln(1 - p)
    assert kl_inverse(0.0, c) == pytest.approx(1.0 - math.exp(-c), abs=1e-11)


def test_monotone_in_q_and_in_c():
    cs = [0.0, 0.001, 0.01, 0.1, 1.0]
    qs = [0.0, 0.01, 0.1, 0.4, 0.8]
    for q in qs:
        values = [kl_inverse(q, c) for c in cs]
        assert values == sorted(values)
    for c in cs[1:]:
        values = [kl_inverse(q, c) for q in qs]
        assert all(a < b for a, b in zip(values, values[1:], strict=False))


def test_zero_complexity_gives_q_and_huge_complexity_gives_one():
    for q in (0.0, 0.2, 1.0):
        assert kl_inverse(q, 0.0) == q
    assert kl_inverse(0.3, 1e6) == 1.0
    assert kl_inverse(1.0, 0.5) == 1.0


def test_binary_kl_closed_values_and_invalid_inputs():
    assert binary_kl(0.5, 0.5) == 0.0
    assert binary_kl(0.5, 0.25) == pytest.approx(0.5 * math.log(2) + 0.5 * math.log(0.5 / 0.75))
    assert binary_kl(0.2, 0.0) == math.inf
    with pytest.raises(ValueError):
        kl_inverse(1.5, 0.1)
    with pytest.raises(ValueError):
        kl_inverse(0.5, -0.1)
