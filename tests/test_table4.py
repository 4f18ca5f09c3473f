"""The paper's Table 4 (§6.3, the humanoid): the annealed log std and the KL-adaptive step size of ppo_continuous.py,
as math against independent references, and as a short run of its real command line on 4 actors."""

import math

import numpy as np
import pytest
import torch
from conftest import load_script, run_cli, tb_scalars
from hypothesis import given, settings
from hypothesis import strategies as st

continuous = load_script("ppo_continuous.py")

# Table 4 on a tiny budget: 4 actors, 3 iterations of 4 x 64 steps, 2 epochs of 2 minibatches.
TABLE4_TINY = "--env-id Humanoid-v5 --num-envs 4 --num-steps 64 --minibatch-size 128 --update-epochs 2".split()
TABLE4_TINY += "--total-timesteps 768 --anneal-logstd -0.7 -1.6 --no-anneal-lr --lr-target-kl 0.01".split()
FINITE = st.floats(-10, 10)


@settings(max_examples=200, deadline=None)
@given(start=FINITE, end=FINITE, fraction=st.floats(0, 1))
def test_linear_anneal_is_numpys_interpolation_between_its_ends(start, end, fraction):
    assert continuous.linear_anneal(start, end, fraction) == pytest.approx(
        np.interp(fraction, [0.0, 1.0], [start, end]), abs=1e-12
    )


def test_linear_anneal_starts_and_ends_where_table4_says():
    assert continuous.linear_anneal(-0.7, -1.6, 0.0) == -0.7
    assert continuous.linear_anneal(-0.7, -1.6, 1.0) == pytest.approx(-1.6)


# (lr, kl, target) -> the next lr, worked by hand: outside [target / 2, 2 target] the step size moves by 1.5, and it
# stays within [1e-5, 1e-2].
STEP_SIZES = [
    (3e-4, 0.05, 0.01, 2e-4),  # KL above twice the target: divide by 1.5
    (3e-4, 0.001, 0.01, 4.5e-4),  # below half the target: multiply by 1.5
    (3e-4, 0.01, 0.01, 3e-4),  # near the target: unchanged
    (3e-4, 0.02, 0.01, 3e-4),  # exactly twice: unchanged
    (3e-4, 0.005, 0.01, 3e-4),  # exactly half: unchanged
    (1.2e-5, 1.0, 0.01, 1e-5),  # floored at 1e-5
    (9e-3, 0.0, 0.01, 1e-2),  # capped at 1e-2
]


@pytest.mark.parametrize("lr,kl,target,expected", STEP_SIZES)
def test_kl_adaptive_step_size_by_hand(lr, kl, target, expected):
    assert continuous.kl_adaptive_lr(lr, kl, target) == pytest.approx(expected, rel=1e-12)


def test_table4_run_follows_both_schedules(tmp_path):
    """The log std is the schedule's at each iteration and no gradient moves it (the logged entropy is that of a
    Gaussian with that log std, an analytic oracle); the step size follows the KL of each update."""
    run_dir = tmp_path / "run"
    out = run_cli(
        "ppo_continuous.py", *TABLE4_TINY, "--lr-target-kl", "1e-6", "--run-dir", run_dir, cwd=tmp_path
    ).stdout
    assert "step 768/768" in out
    scalars = tb_scalars(run_dir)
    num_iterations = 3
    act_dim = 17  # Humanoid's
    for i, (_, entropy) in enumerate(scalars["losses/entropy"]):
        logstd = -0.7 + (-1.6 + 0.7) * i / num_iterations
        assert entropy == pytest.approx(act_dim * (0.5 * math.log(2 * math.pi * math.e) + logstd), rel=1e-5)
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert torch.allclose(checkpoint["agent"]["actor_logstd"], torch.tensor(-0.7 - 0.9 * 2 / 3))
    # a target KL far below any update's: the step size falls by 1.5 after every update, the last one included
    lrs = [lr for _, lr in scalars["charts/learning_rate"]] + [checkpoint["optimizer"]["param_groups"][0]["lr"]]
    assert lrs == pytest.approx([3e-4 / 1.5**i for i in range(num_iterations + 1)], rel=1e-5)
