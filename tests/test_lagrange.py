"""The Lagrange multiplier's updates against hand computations, its validation, and its state."""

import math

import pytest
import torch

from drivelab.errors import DrivelabError
from drivelab.training.learning.hyperparams import ConstraintParams
from drivelab.training.learning.lagrange import LagrangeMultiplier


def _lams(hp: ConstraintParams, costs: list[float]) -> list[float]:
    multiplier = LagrangeMultiplier(hp)
    out = []
    for cost in costs:
        multiplier.update(cost)
        out.append(multiplier.lam)
    return out


def test_the_gradient_update_integrates_the_violation_and_stays_at_or_above_zero():
    # lambda <- max(0, lambda + 0.5 (J_c - 1)): 0 + 0.5 * 2 = 1, 1 - 0.5 = 0.5, 0.5 - 0.5 = 0, max(0, -0.5) = 0
    assert _lams(ConstraintParams(cost_limit=1.0, lagrange_lr=0.5), [3, 0, 0, 0]) == [1.0, 0.5, 0.0, 0.0]
    assert _lams(ConstraintParams(cost_limit=0.0, lagrange_lr=10, lagrange_max=2.0), [1.0]) == [2.0]


def test_the_pid_update_matches_a_hand_computation():
    # Kp 0.5, Ki 0.1, Kd 0.2, no smoothing, derivative against the previous update, d = 1:
    # J_c = 3: e 2, I 0.2, P 1.0, D 0 (no history)   -> 1.2
    # J_c = 2: e 1, I 0.3, P 0.5, D max(0, 2 - 3) = 0 -> 0.8
    # J_c = 4: e 3, I 0.6, P 1.5, D 4 - 2 = 2 (x 0.2) -> 2.5
    # J_c = 0: e -1, I 0.5, P -0.5, D 0               -> 0.0
    hp = ConstraintParams(cost_limit=1.0, lagrange="pid", pid_kp=0.5, pid_ki=0.1, pid_kd=0.2, pid_ema=0.0,
                          pid_d_delay=1)
    assert _lams(hp, [3, 2, 4, 0]) == pytest.approx([1.2, 0.8, 2.5, 0.0], abs=1e-12)


def test_measured_cost_is_the_mean_of_the_episodes_since_the_last_call():
    multiplier = LagrangeMultiplier(ConstraintParams())
    assert multiplier.measured_cost(0.0, 0) is None
    assert multiplier.measured_cost(5.0, 2) == 2.5
    assert multiplier.measured_cost(5.0, 2) is None          # no new episode
    assert multiplier.measured_cost(8.0, 5) == 1.0           # (8 - 5) / (5 - 2)


def test_the_state_round_trips_through_a_state_dict_bit_exactly():
    hp = ConstraintParams(lagrange="pid", pid_d_delay=3)
    first, second = LagrangeMultiplier(hp), LagrangeMultiplier(hp)
    for cost in [2.0, 0.3, 1.7]:
        first.update(cost)
    first.measured_cost(4.0, 3)
    second.load_state_dict(first.state_dict())
    assert all(v.dtype in (torch.float64, torch.int64) for v in first.state_dict().values())
    for cost in [2.5, 0.1]:
        assert first.update(cost) == second.update(cost)
    assert first.lam == second.lam


@pytest.mark.parametrize("field, value", [("cost_limit", -1.0), ("cost_limit", math.nan), ("cost_limit", math.inf),
                                          ("cost_limit", "abc"), ("cost_limit", True), ("lagrange", "pidd"),
                                          ("lagrange_lr", 0.0), ("pid_ema", 1.0), ("pid_d_delay", 0),
                                          ("cost_gamma", 1.5), ("lagrange_init", 1e9)])
def test_bad_constraint_values_are_one_line_naming_the_field(field, value):
    hp = ConstraintParams(**{field: value})
    with pytest.raises(DrivelabError, match=rf"'algo\.{field}'") as error:
        hp.validate_constraint("algo")
    assert "\n" not in str(error.value)
