"""The policy and value losses, as properties that must hold for any input (hypothesis)."""

import inspect

import numpy as np
import pytest
import torch
from conftest import load_script, scripts_with
from hypothesis import given, settings
from hypothesis import strategies as st

CLIP_SCRIPTS = scripts_with("clipped_surrogate_loss")
VALUE_SCRIPTS = scripts_with("value_loss")


def with_unclipped_form(name):
    """Whether the script's value loss can be unclipped (--no-clip-vloss); ppo_rlhf.py's is always clipped."""
    return "clip_vloss" in inspect.signature(load_script(name).value_loss).parameters


UNCLIPPABLE = [name for name in VALUE_SCRIPTS if with_unclipped_form(name)]

ratios = st.floats(0.01, 5.0)
# Subnormal advantages (below 2.2e-308) are left out: there a product underflows to 0 or not
# depending only on the order of the multiplications, which says nothing about the loss.
advantages = st.floats(-10.0, 10.0, allow_subnormal=False)
clips = st.floats(0.05, 0.5)


@pytest.fixture(params=CLIP_SCRIPTS)
def clip_loss(request):
    return load_script(request.param).clipped_surrogate_loss


@pytest.fixture(params=UNCLIPPABLE)
def v_loss(request):
    return load_script(request.param).value_loss


def test_every_clip_script_is_checked():
    assert "ppo_continuous.py" in CLIP_SCRIPTS


@settings(max_examples=200, deadline=None)
@given(r=st.lists(ratios, min_size=1, max_size=8), a=st.lists(advantages, min_size=1, max_size=8), eps=clips)
def test_clip_is_a_lower_bound_of_cpi(r, a, eps):
    # L^CLIP <= L^CPI (paper §3): the loss, -L^CLIP, is at least -L^CPI = -mean(r A).
    n = min(len(r), len(a))
    ratio, adv = torch.tensor(r[:n], dtype=torch.float64), torch.tensor(a[:n], dtype=torch.float64)
    for name in CLIP_SCRIPTS:
        loss = load_script(name).clipped_surrogate_loss(ratio, adv, eps)
        assert loss.item() >= -(ratio * adv).mean().item() - 1e-9, name


@settings(max_examples=100, deadline=None)
@given(a=st.lists(advantages, min_size=1, max_size=8), eps=clips)
def test_clip_equals_cpi_at_ratio_one_in_value_and_gradient(a, eps):
    adv = torch.tensor(a, dtype=torch.float64)
    for name in CLIP_SCRIPTS:
        ratio = torch.ones_like(adv, requires_grad=True)
        load_script(name).clipped_surrogate_loss(ratio, adv, eps).backward()
        cpi_ratio = torch.ones_like(adv, requires_grad=True)
        (-(cpi_ratio * adv).mean()).backward()
        np.testing.assert_allclose(ratio.grad.numpy(), cpi_ratio.grad.numpy(), err_msg=name)
        assert load_script(name).clipped_surrogate_loss(torch.ones_like(adv), adv, eps).item() == pytest.approx(
            -adv.mean().item()
        )


@settings(max_examples=200, deadline=None)
@given(r=ratios, a=advantages, eps=clips)
def test_gradient_is_zero_exactly_where_clipping_is_profitable(r, a, eps):
    # Outside the clip range on the side that would improve the objective (r > 1 + eps with A > 0,
    # or r < 1 - eps with A < 0), the objective is flat in r. Everywhere else it is -A/n.
    ratio = torch.tensor([r], dtype=torch.float64, requires_grad=True)
    adv = torch.tensor([a], dtype=torch.float64)
    for name in CLIP_SCRIPTS:
        ratio.grad = None
        load_script(name).clipped_surrogate_loss(ratio, adv, eps).backward()
        profitable_and_clipped = (a > 0 and r > 1 + eps) or (a < 0 and r < 1 - eps)
        expected = 0.0 if profitable_and_clipped else -a
        assert ratio.grad.item() == pytest.approx(expected, abs=1e-12), name


def test_clip_loss_hand_worked(clip_loss):
    # eps 0.2: min(1.5*2, 1.2*2) = 2.4; min(0.5*-1, 0.8*-1) = -0.8; mean 0.8, so the loss is -0.8.
    loss = clip_loss(torch.tensor([1.5, 0.5]), torch.tensor([2.0, -1.0]), 0.2)
    assert loss.item() == pytest.approx(-0.8)


def test_value_loss_unclipped_is_the_papers_squared_error(v_loss):
    # L^VF of eq. 9 is (V - V_targ)^2, not half of it (CleanRL's convention): errors 1 and 2 give (1 + 4) / 2.
    new, old, ret = torch.tensor([1.0, 3.0]), torch.tensor([0.0, 0.0]), torch.tensor([0.0, 1.0])
    assert v_loss(new, old, ret, 0.2, False).item() == pytest.approx((1.0 + 4.0) / 2)


@settings(max_examples=200, deadline=None)
@given(new=st.floats(-10, 10), old=st.floats(-10, 10), ret=st.floats(-10, 10), eps=clips)
def test_value_loss_clipped_is_pessimistic(new, old, ret, eps):
    for name in VALUE_SCRIPTS:
        f = load_script(name).value_loss
        t = lambda x: torch.tensor([x], dtype=torch.float64)  # noqa: E731
        if with_unclipped_form(name):
            clipped, unclipped = (
                f(t(new), t(old), t(ret), eps, True).item(),
                f(t(new), t(old), t(ret), eps, False).item(),
            )
        else:  # always clipped, over the tokens of a mask (none here: every entry counts)
            clipped, unclipped = f(t(new), t(old), t(ret), eps, None).item(), (new - ret) ** 2
        assert clipped >= unclipped - 1e-12, name
        if abs(new - old) <= eps:
            assert clipped == pytest.approx(unclipped), name
        else:  # the clipped prediction is old +- eps
            v_clipped = old + np.clip(new - old, -eps, eps)
            assert clipped == pytest.approx(max((new - ret) ** 2, (v_clipped - ret) ** 2)), name
