"""benchmarks/figure2.py: the points the paper's Figure 2 makes, on a small first update of ppo_continuous.py."""

import sys

import numpy as np
import pytest
from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import figure2  # noqa: E402

SMALL = dict(num_steps=512, minibatch_size=64, update_epochs=4)
ALPHAS = [0.0, 1e-3] + [0.1 * i for i in range(1, 31)]  # from theta_old to three times the update


@pytest.fixture(scope="module")
def curves():
    return np.array(figure2.interpolate(ALPHAS, **SMALL))


def test_l_clip_is_a_lower_bound_of_l_cpi(curves):
    _, cpi, _, clip, _ = curves.T
    assert (clip <= cpi + 1e-7).all()
    assert (clip < cpi - 1e-4).any(), "the bound is strict somewhere, where the ratio left [1 - eps, 1 + eps]"


def test_l_clip_and_l_cpi_agree_to_first_order_at_theta_old(curves):
    _, cpi, _, clip, kl = curves.T
    assert cpi[0] == pytest.approx(clip[0], abs=1e-6) and kl[0] == pytest.approx(0, abs=1e-9)
    slope_cpi, slope_clip = (cpi[1] - cpi[0]) / 1e-3, (clip[1] - clip[0]) / 1e-3
    assert slope_cpi > 0, "the update ascends the surrogate"
    assert slope_clip == pytest.approx(slope_cpi, rel=1e-3)


def test_l_clip_peaks_inside_the_interpolation_range(curves):
    alpha, cpi, _, clip, kl = curves.T
    peak = int(np.argmax(clip))
    assert 0 < peak < len(alpha) - 1, f"L^CLIP peaks at the edge, a = {alpha[peak]}"
    assert cpi[-1] > cpi[peak], "past the peak L^CPI still rises: only the clipped objective stops the step"
    assert np.all(np.diff(kl[1:]) > 0), "the KL grows as the policy moves away from theta_old"
