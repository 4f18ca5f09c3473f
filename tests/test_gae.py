"""compute_gae, in every script, against references that share none of its code."""

import numpy as np
import pytest
import torch
from conftest import SCRIPTS, TINY, load_script
from hypothesis import given, settings
from hypothesis import strategies as st

# GAE over env steps, with terminations and truncations. ppo_rlhf.py's compute_gae runs over the tokens of responses,
# with a mask: tests/test_rlhf.py checks it against a double loop of its own.
ENV_SCRIPTS = [name for name in SCRIPTS if "no_env" not in TINY[name]]


@pytest.fixture(params=ENV_SCRIPTS)
def gae(request):
    return load_script(request.param).compute_gae


def reference_gae(rewards, values, next_values, terms, truncs, gamma, lam):
    """A forward double loop: A_t = sum_l (gamma lam)^l delta_{t+l}, up to the end of t's episode."""
    T, N = rewards.shape
    adv = np.zeros((T, N))
    for i in range(N):
        for t in range(T):
            total, weight = 0.0, 1.0
            for k in range(t, T):
                delta = rewards[k, i] + gamma * (1 - terms[k, i]) * next_values[k, i] - values[k, i]
                total += weight * delta
                if terms[k, i] or truncs[k, i]:
                    break
                weight *= gamma * lam
            adv[t, i] = total
    return adv


def as_tensors(*arrays):
    return [torch.tensor(np.asarray(a), dtype=torch.float32) for a in arrays]


@settings(max_examples=60, deadline=None)
@given(
    T=st.integers(1, 12),
    N=st.integers(1, 3),
    gamma=st.floats(0.0, 1.0),
    lam=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_matches_double_loop(T, N, gamma, lam, seed):
    rng = np.random.default_rng(seed)
    rewards, values, next_values = rng.normal(size=(3, T, N))
    terms = rng.random((T, N)) < 0.2
    truncs = (rng.random((T, N)) < 0.2) & ~terms
    expected = reference_gae(rewards, values, next_values, terms, truncs, gamma, lam)
    for name in ENV_SCRIPTS:
        compute_gae = load_script(name).compute_gae
        adv, ret = compute_gae(*as_tensors(rewards, values, next_values, terms, truncs), gamma, lam)
        assert adv.shape == (T, N)
        np.testing.assert_allclose(adv.numpy(), expected, rtol=1e-4, atol=1e-4, err_msg=name)
        np.testing.assert_allclose(ret.numpy(), expected + values, rtol=1e-4, atol=1e-4, err_msg=name)


def test_bool_and_float_flags_agree(gae):
    rng = np.random.default_rng(0)
    r, v, nv = as_tensors(*rng.normal(size=(3, 6, 2)))
    terms = torch.tensor(rng.random((6, 2)) < 0.3)
    truncs = torch.tensor(rng.random((6, 2)) < 0.3) & ~terms
    a_bool, _ = gae(r, v, nv, terms, truncs, 0.9, 0.8)
    a_float, _ = gae(r, v, nv, terms.float(), truncs.float(), 0.9, 0.8)
    torch.testing.assert_close(a_bool, a_float)


def test_termination_does_not_bootstrap_but_truncation_does(gae):
    # One step, reward 1, V(s) = 0, V(final observation) = 10, gamma = 0.5.
    r, v, nv = torch.tensor([[1.0]]), torch.tensor([[0.0]]), torch.tensor([[10.0]])
    one, zero = torch.tensor([[1.0]]), torch.tensor([[0.0]])
    adv_term, _ = gae(r, v, nv, one, zero, 0.5, 0.95)
    adv_trunc, _ = gae(r, v, nv, zero, one, 0.5, 0.95)
    assert adv_term.item() == pytest.approx(1.0)  # r only
    assert adv_trunc.item() == pytest.approx(1.0 + 0.5 * 10.0)  # r + gamma V(s_final)


def test_advantage_does_not_cross_episode_boundary(gae):
    # Step 0 ends an episode (truncated); step 1 has a huge TD error in the next episode.
    r = torch.tensor([[0.0], [100.0]])
    v = torch.zeros(2, 1)
    nv = torch.zeros(2, 1)
    for term, trunc in [([[1.0], [0.0]], [[0.0], [0.0]]), ([[0.0], [0.0]], [[1.0], [0.0]])]:
        adv, _ = gae(r, v, nv, torch.tensor(term), torch.tensor(trunc), 0.99, 0.95)
        assert adv[0, 0].item() == pytest.approx(0.0)
        assert adv[1, 0].item() == pytest.approx(100.0)


def test_lambda_zero_gives_td_error(gae):
    rng = np.random.default_rng(1)
    r, v, nv = as_tensors(*rng.normal(size=(3, 5, 2)))
    terms = torch.tensor(rng.random((5, 2)) < 0.3).float()
    truncs = torch.zeros(5, 2)
    adv, ret = gae(r, v, nv, terms, truncs, 0.9, 0.0)
    torch.testing.assert_close(adv, r + 0.9 * (1 - terms) * nv - v)
    torch.testing.assert_close(ret, r + 0.9 * (1 - terms) * nv)


def test_lambda_one_gives_discounted_return_minus_value(gae):
    # One episode that terminates at its last step: A_t = sum_k gamma^(k-t) r_k - V(s_t).
    rng = np.random.default_rng(2)
    T, gamma = 7, 0.9
    rewards, values = rng.normal(size=(2, T))
    next_values = np.append(values[1:], 123.0)  # V after termination must be ignored
    terms = np.zeros(T)
    terms[-1] = 1
    discounted = [sum(gamma ** (k - t) * rewards[k] for k in range(t, T)) for t in range(T)]
    r, v, nv, te = as_tensors(rewards[:, None], values[:, None], next_values[:, None], terms[:, None])
    adv, ret = gae(r, v, nv, te, torch.zeros(T, 1), gamma, 1.0)
    np.testing.assert_allclose(adv[:, 0].numpy(), np.array(discounted) - values, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(ret[:, 0].numpy(), discounted, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("gamma,lam", [(0.99, 0.95), (0.9, 0.5), (1.0, 1.0), (0.5, 0.0)])
def test_analytic_oracle_constant_value_single_terminal_reward(gae, gamma, lam):
    # V = c everywhere, reward R only at the terminal step T-1. Then delta_t = (gamma - 1) c for
    # t < T-1 and delta_{T-1} = R - c, so with k = T-1-t steps to go:
    #   A_t = (gamma - 1) c (1 - (gamma lam)^k) / (1 - gamma lam) + (gamma lam)^k (R - c).
    T, c, R = 9, 2.0, 5.0
    rewards = torch.zeros(T, 1)
    rewards[-1] = R
    terms = torch.zeros(T, 1)
    terms[-1] = 1
    adv, _ = gae(rewards, torch.full((T, 1), c), torch.full((T, 1), c), terms, torch.zeros(T, 1), gamma, lam)
    gl = gamma * lam
    for t in range(T):
        k = T - 1 - t
        geometric = k if gl == 1 else (1 - gl**k) / (1 - gl)
        expected = (gamma - 1) * c * geometric + gl**k * (R - c)
        assert adv[t, 0].item() == pytest.approx(expected, rel=1e-5, abs=1e-5)
