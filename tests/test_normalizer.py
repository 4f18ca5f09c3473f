"""RunningMeanStd against numpy's mean and var of all the data seen."""

import numpy as np
import pytest
import torch
from conftest import load_script, scripts_with


@pytest.fixture(params=scripts_with("RunningMeanStd"))
def rms_class(request):
    return load_script(request.param).RunningMeanStd


@pytest.mark.parametrize("shape", [(), (5,)])
def test_matches_numpy_over_uneven_batches(rms_class, shape):
    rng = np.random.default_rng(0)
    rms = rms_class(shape)
    batches = [rng.normal(3.0, 2.0, size=(n, *shape)) for n in [1, 1, 7, 64, 3, 1, 200]]
    for b in batches:
        rms.update(b)
    data = np.concatenate(batches)
    # The initial count of 1e-4 at mean 0, var 1 shifts the result by about 1e-6 here.
    np.testing.assert_allclose(rms.mean, data.mean(0), rtol=1e-5)
    np.testing.assert_allclose(rms.var, data.var(0), rtol=1e-5)
    assert rms.count == pytest.approx(len(data), abs=1e-3)


def test_one_sample_at_a_time_matches_numpy(rms_class):
    rng = np.random.default_rng(1)
    rms = rms_class((3,))
    data = rng.exponential(5.0, size=(500, 3))
    for row in data:
        rms.update(row[None])
    np.testing.assert_allclose(rms.mean, data.mean(0), rtol=1e-5)
    np.testing.assert_allclose(rms.var, data.var(0), rtol=1e-5)


def test_statistics_travel_in_the_state_dict(rms_class):
    rms = rms_class((2,))
    rms.update(np.array([[1.0, 2.0], [3.0, 5.0]]))
    state = rms.state_dict()
    restored = rms_class((2,))
    restored.load_state_dict(state)
    np.testing.assert_array_equal(restored.mean, rms.mean)
    np.testing.assert_array_equal(restored.var, rms.var)
    assert restored.count == rms.count
    # and survive a round trip through torch.save / torch.load(weights_only=True)
    import io

    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    again = rms_class((2,))
    again.load_state_dict(torch.load(buf, weights_only=True))
    np.testing.assert_array_equal(again.var, rms.var)
