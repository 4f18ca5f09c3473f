"""ppo_kl_penalty.py: the exact Gaussian KL, the beta rule and the penalized objective (paper §4)."""

import math

import numpy as np
import pytest
import torch
from conftest import TINY, load_script, run_cli, tb_scalars
from hypothesis import given, settings
from hypothesis import strategies as st

kl_script = load_script("ppo_kl_penalty.py")
gaussian_kl, kl_penalty_loss, adapt_beta = kl_script.gaussian_kl, kl_script.kl_penalty_loss, kl_script.adapt_beta


def test_kl_matches_monte_carlo_estimate():
    torch.manual_seed(0)
    mean_old, logstd_old = torch.tensor([0.3, -1.0, 2.0]), torch.tensor([0.0, -0.5, 0.4])
    mean_new, logstd_new = torch.tensor([0.1, -0.2, 1.5]), torch.tensor([0.3, -0.1, 0.2])
    old = torch.distributions.Normal(mean_old.double(), logstd_old.exp().double())
    new = torch.distributions.Normal(mean_new.double(), logstd_new.exp().double())
    x = old.sample((400_000,))
    mc = (old.log_prob(x) - new.log_prob(x)).sum(-1).mean().item()  # E_old[log old - log new]
    exact = gaussian_kl(mean_old, logstd_old, mean_new, logstd_new).item()
    assert exact == pytest.approx(mc, abs=0.01)


@settings(max_examples=100, deadline=None)
@given(m1=st.floats(-3, 3), m2=st.floats(-3, 3), s1=st.floats(0.1, 3), s2=st.floats(0.1, 3))
def test_kl_matches_the_1d_closed_form(m1, m2, s1, s2):
    # KL(N(m1, s1^2) || N(m2, s2^2)) = log(s2/s1) + (s1^2 + (m1 - m2)^2) / (2 s2^2) - 1/2
    expected = math.log(s2 / s1) + (s1**2 + (m1 - m2) ** 2) / (2 * s2**2) - 0.5
    t = lambda x: torch.tensor([x], dtype=torch.float64)  # noqa: E731
    got = gaussian_kl(t(m1), t(math.log(s1)), t(m2), t(math.log(s2))).item()
    assert got == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_kl_is_zero_for_identical_distributions_and_sums_dimensions():
    mean, logstd = torch.randn(5, 3), torch.randn(3)
    kl = gaussian_kl(mean, logstd, mean, logstd)
    assert kl.shape == (5,)
    torch.testing.assert_close(kl, torch.zeros(5))
    # independent dimensions: the KL of the whole is the sum over dimensions
    other = mean + 1.0
    per_dim = [
        gaussian_kl(mean[:, i : i + 1], logstd[i : i + 1], other[:, i : i + 1], logstd[i : i + 1]) for i in range(3)
    ]
    torch.testing.assert_close(gaussian_kl(mean, logstd, other, logstd), sum(per_dim))


TARGET = 0.01
BETA_CASES = [
    (TARGET / 1.5 * 0.99, 0.5),  # just below d_targ / 1.5: halve
    (TARGET / 1.5, 1.0),  # exactly at the lower boundary: keep
    (TARGET, 1.0),  # on target: keep
    (TARGET * 1.5, 1.0),  # exactly at the upper boundary: keep
    (TARGET * 1.5 * 1.01, 2.0),  # just above d_targ x 1.5: double
    (0.0, 0.5),
    (1.0, 2.0),
]


@pytest.mark.parametrize("kl,factor", BETA_CASES)
def test_adapt_beta_table(kl, factor):
    assert adapt_beta(3.0, kl, TARGET) == 3.0 * factor


def test_penalty_with_beta_zero_is_cpi():
    ratio = torch.tensor([0.5, 1.0, 1.7], requires_grad=True)
    adv = torch.tensor([1.0, -2.0, 0.5])
    loss = kl_penalty_loss(ratio, adv, torch.tensor([0.3, 0.1, 0.9]), 0.0)
    loss.backward()
    assert loss.item() == pytest.approx(-(ratio * adv).mean().item())
    torch.testing.assert_close(ratio.grad, -adv / 3)


def test_large_beta_pulls_the_new_policy_toward_the_old():
    # One gradient step on the loss must move the new mean and log std toward the old ones when the
    # penalty dominates, whatever the advantages say.
    torch.manual_seed(1)
    mean_old, logstd_old = torch.zeros(8, 2), torch.zeros(2)
    mean_new = torch.full((8, 2), 0.5, requires_grad=True)
    logstd_new = torch.full((2,), 0.3, requires_grad=True)
    actions = torch.randn(8, 2)
    logp = lambda m, s: torch.distributions.Normal(m, s.exp()).log_prob(actions).sum(-1)  # noqa: E731
    ratio = torch.exp(logp(mean_new, logstd_new) - logp(mean_old, logstd_old))
    kl = gaussian_kl(mean_old, logstd_old, mean_new, logstd_new)
    kl_penalty_loss(ratio, torch.randn(8), kl, 100.0).backward()
    with torch.no_grad():
        stepped_mean, stepped_logstd = mean_new - 1e-3 * mean_new.grad, logstd_new - 1e-3 * logstd_new.grad
        assert (stepped_mean - mean_old).abs().sum() < (mean_new - mean_old).abs().sum()
        assert (stepped_logstd - logstd_old).abs().sum() < (logstd_new - logstd_old).abs().sum()
        assert gaussian_kl(mean_old, logstd_old, stepped_mean, stepped_logstd).sum() < kl.sum()


def test_beta_is_logged_adapted_and_restored_on_resume(tmp_path):
    script, cfg = "ppo_kl_penalty.py", TINY["ppo_kl_penalty.py"]
    run_dir = tmp_path / "run"
    run_cli(script, "--env-id", cfg["env_id"], *cfg["tiny"], "--run-dir", run_dir, "--kl-target", "1e-9", cwd=tmp_path)
    scalars = tb_scalars(run_dir)
    betas = [v for _, v in scalars["losses/beta"]]
    assert betas == [1.0, 2.0], "with a tiny target the KL is always too large: beta doubles"
    assert all(v > 0 for _, v in scalars["losses/kl"])
    checkpoint = kl_script.load_checkpoint(str(run_dir / "checkpoint.pt"), kl_script.Args())[0]
    assert checkpoint["beta"] == 4.0

    # Roll the checkpoint back to after iteration 1 with a distinctive beta; the resumed iteration 2
    # must use it.
    checkpoint.update(iteration=1, global_step=64, beta=7.0)
    torch.save(checkpoint, run_dir / "checkpoint.pt")
    run_cli(script, "--resume", run_dir / "checkpoint.pt", cwd=tmp_path)
    assert tb_scalars(run_dir)["losses/beta"] == [(64, 1.0), (128, 7.0)]
    assert kl_script.load_checkpoint(str(run_dir / "checkpoint.pt"), kl_script.Args())[0]["beta"] == 14.0


def test_fixed_beta_stays_fixed(tmp_path):
    script, cfg = "ppo_kl_penalty.py", TINY["ppo_kl_penalty.py"]
    run_dir = tmp_path / "run"
    run_cli(
        script,
        "--env-id",
        cfg["env_id"],
        *cfg["tiny"],
        "--run-dir",
        run_dir,
        "--init-beta",
        "3",
        "--no-adaptive-beta",
        cwd=tmp_path,
    )
    assert [v for _, v in tb_scalars(run_dir)["losses/beta"]] == [3.0, 3.0]
    assert np.isfinite([v for _, v in tb_scalars(run_dir)["losses/kl"]]).all()


def test_zero_beta_cannot_be_adaptive(tmp_path):
    proc = run_cli("ppo_kl_penalty.py", "--init-beta", "0", cwd=tmp_path, check=False)
    assert proc.returncode == 2 and "--no-adaptive-beta" in proc.stderr
    assert not (tmp_path / "runs").exists()


def test_penalty_worked_example():
    # -E[r A - beta KL] by hand: ratios 1 and 2, advantages 1 and 1, KLs 0.1 and 0.3, beta 2:
    # -((1 - 2 x 0.1) + (2 - 2 x 0.3)) / 2 = -(0.8 + 1.4) / 2 = -1.1; d/dKL_i = beta / 2 = 1 each.
    kl = torch.tensor([0.1, 0.3], requires_grad=True)
    loss = kl_penalty_loss(torch.tensor([1.0, 2.0]), torch.tensor([1.0, 1.0]), kl, 2.0)
    loss.backward()
    assert loss.item() == pytest.approx(-1.1)
    torch.testing.assert_close(kl.grad, torch.tensor([1.0, 1.0]))
