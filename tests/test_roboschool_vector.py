"""roboschool_humanoid.py's vector env (gym.make_vec's vector_entry_point) against gymnasium's SyncVectorEnv of the
single envs: the same seeds and actions give the same observations, rewards, ends and infos, step for step, bit for
bit, over episodes that hold every event the rules have."""

import sys

import numpy as np
import pytest
from conftest import ROOT

gym = pytest.importorskip("gymnasium")
sys.path.insert(0, str(ROOT))
import roboschool_humanoid  # noqa: E402, F401  (registers the ids)

N = 64
STEPS = 1050


def same(x, y):
    """Equal to the bit, dtype included, through nested infos and object arrays of final observations."""
    if isinstance(x, dict):
        return isinstance(y, dict) and x.keys() == y.keys() and all(same(x[key], y[key]) for key in x)
    if isinstance(x, np.ndarray) and x.dtype == object:
        pairs = zip(x, y, strict=True)
        return y.dtype == object and all((a is None) == (b is None) and (a is None or same(a, b)) for a, b in pairs)
    return np.asarray(x).dtype == np.asarray(y).dtype and np.array_equal(x, y)


def hold(datas, model, steps):
    """A harness that holds a body's torso up, so that bodies stand long enough for the cubes: the even bodies all
    their episode, the odd ones for their episode's first 200 steps, then they fall."""
    torso = model.body("torso").id
    weight = model.body_subtreemass[torso] * 9.81
    for i, data in enumerate(datas):
        on = i % 2 == 0 or steps[i] < 200
        data.xfrc_applied[torso, 2] = weight if on else 0.0
        data.xfrc_applied[torso, 3:] = -5.0 * data.qvel[3:6] if on else 0.0


def last(info, ended, key):
    """Each env's value of an info key for its step: from final_info where the step ended the episode."""
    value = info.get(key, np.zeros(N, info["final_info"][key].dtype if ended.any() else float))
    return np.where(ended, info["final_info"][key], value) if ended.any() else value


@pytest.mark.parametrize("task", ["HumanoidForward", "HumanoidFlagrun", "HumanoidFlagrunHarder"])
def test_the_vector_env_gives_the_episodes_of_the_single_envs(task):
    env_id = f"roboschool_humanoid:{task}-v0"
    single = gym.vector.SyncVectorEnv(
        [lambda: gym.make(env_id) for _ in range(N)], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
    )
    vector = gym.make_vec(env_id, N, vectorization_mode="vector_entry_point")
    assert type(vector).__name__ == f"{task}Vector"
    seeds = list(range(1000, 1000 + N))
    first = single.reset(seed=seeds)
    assert all(same(x, y) for x, y in zip(first, vector.reset(seed=seeds), strict=True))
    model = vector.bodies.model
    rng = np.random.default_rng(0)
    steps = np.zeros(N, int)
    events = dict(ends=0, truncations=0, lying_starts=int((first[0][:, 0] < 0).sum()), throws=0, moves=0, knocks=0)
    up = first[0][:, 0] > 0  # the state's first number is the torso's height above 0.8 m
    cubes = np.zeros(N, int)
    last_throw = np.full(N, -100)
    for step in range(STEPS):
        hold([env.unwrapped.data for env in single.envs], model, steps)
        hold(vector.bodies.datas, model, steps)
        action = np.clip(rng.normal(0.0, 0.3, (N, 17)), -1, 1).astype(np.float32)
        result = single.step(action)
        assert all(same(x, y) for x, y in zip(result, vector.step(action), strict=True)), step
        obs, _, terminated, truncated, info = result
        ended = terminated | truncated
        thrown = last(info, ended, "cubes_thrown") > cubes
        last_throw[thrown] = step
        down = last(info, ended, "torso_z") < 0.8
        events["knocks"] += int((up & down & (step - last_throw <= 30)).sum())
        events["throws"] += int(thrown.sum())
        events["moves"] += int(last(info, ended, "flag_moved").sum())
        events["ends"] += int(ended.sum())
        events["truncations"] += int(truncated.sum())
        events["lying_starts"] += int((ended & (obs[:, 0] < 0)).sum())
        up = np.where(ended, obs[:, 0] > 0, ~down)
        cubes = np.where(ended, 0, last(info, ended, "cubes_thrown"))
        steps = np.where(ended, 0, steps + 1)
    # every event of the rules happened on the way: resets after falls and after the time limit, and the task's own
    assert events["ends"] > N and events["truncations"] > 0, events
    if task != "HumanoidForward":
        assert events["moves"] > 0, events
    if task == "HumanoidFlagrunHarder":
        assert events["lying_starts"] > 0 and events["throws"] > 0 and events["knocks"] > 0, events
    single.close()
    vector.close()
