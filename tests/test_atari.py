"""ppo_atari.py: the preprocessing of the ale-py vector env, episodic life, and the CNN."""

import numpy as np
import pytest
import torch
from conftest import TINY, load_script, run_cli, tb_scalars

atari = load_script("ppo_atari.py")


def envs(num_envs=2, training=True, env_id="BreakoutNoFrameskip-v4"):
    return atari.make_envs(atari.Args(env_id=env_id, num_envs=num_envs), training=training)


@pytest.mark.parametrize(
    "env_id,game",
    [("BreakoutNoFrameskip-v4", "breakout"), ("ALE/Breakout-v5", "breakout"), ("Breakout", "breakout"),
     ("breakout", "breakout"), ("BeamRiderNoFrameskip-v4", "beam_rider"), ("ALE/MsPacman-v5", "ms_pacman"),
     ("PongDeterministic-v4", "pong"), ("UpNDownNoFrameskip-v4", "up_n_down"), ("UpNDown", "up_n_down")],
)  # fmt: skip
def test_env_ids_name_their_game(env_id, game):
    assert atari.game_name(env_id) == game


def test_observations_are_stacked_uint8_84x84_oldest_first():
    e = envs()
    obs, _ = e.reset(seed=0)
    assert obs.shape == (2, 4, 84, 84) and obs.dtype == np.uint8
    assert e.single_action_space.n == 4
    rng = np.random.default_rng(0)
    moved = False
    for _ in range(50):
        new_obs, _, term, trunc, _ = e.step(rng.integers(0, 4, size=2))
        for i in np.flatnonzero(~(term | trunc)):
            # The newest frame is last: what was frames 1..3 is now frames 0..2.
            np.testing.assert_array_equal(new_obs[i, :3], obs[i, 1:])
            moved |= not np.array_equal(new_obs[i, 3], obs[i, 3])
        obs = new_obs
    assert moved
    e.close()


def test_noop_reset_starts_games_at_different_frames():
    e = envs(num_envs=1)
    starts = {int(e.reset(seed=seed)[1]["episode_frame_number"][0]) for seed in range(12)}
    e.close()
    assert len(starts) > 3, starts


def test_fire_reset_launches_the_ball():
    # Breakout's ball waits for FIRE. With only NOOPs after the reset a life is still lost, because
    # the reset pressed FIRE.
    e = envs(num_envs=1)
    _, info = e.reset(seed=0)
    lives = info["lives"][0]
    for _ in range(300):
        _, _, term, _, info = e.step(np.zeros(1, dtype=np.int64))
        if info["lives"][0] < lives:
            break
    e.close()
    assert info["lives"][0] < lives and term[0], "the ball was never launched"


def test_life_loss_terminates_for_learning_but_the_game_and_its_score_go_on():
    e, full = envs(num_envs=1), envs(num_envs=1, training=False)
    rng = np.random.default_rng(1)
    e.reset(seed=3)
    _, info = full.reset(seed=3)
    lives = info["lives"]
    terminations, score, full_score = 0, 0.0, 0.0
    for _ in range(5000):
        action = rng.integers(0, 4, size=1)
        _, reward, term, trunc, info = e.step(action)
        _, full_reward, full_term, _, _ = full.step(action)
        score, full_score = score + reward[0], full_score + full_reward[0]
        terminations += int(term[0])
        if atari.game_over(term, trunc, lives, info["lives"])[0]:
            break
        lives = info["lives"]
        assert not full_term[0], "the evaluation env ended the game early"
    e.close()
    full.close()
    assert terminations == 5, "Breakout: 4 lost lives and the end of the game"
    assert score == full_score and score > 0, "the raw score of the whole game, not one life's clipped reward"


@pytest.mark.parametrize(
    "term,trunc,lives,new_lives,expected",
    [(True, False, 5, 4, False), (True, False, 1, 5, True), (True, False, 0, 0, True),
     (False, True, 3, 3, True), (False, False, 3, 3, False), (True, True, 3, 2, True)],
)  # fmt: skip
def test_game_over_table(term, trunc, lives, new_lives, expected):
    got = atari.game_over(np.array([term]), np.array([trunc]), np.array([lives]), np.array([new_lives]))
    assert got.tolist() == [expected]


def test_cnn_shapes_and_scaling():
    agent = atari.Agent(6)
    obs = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    action, logprob, entropy, value = agent.get_action_and_value(obs)
    assert action.shape == logprob.shape == entropy.shape == value.shape == (3,)
    # the frames are scaled to [0, 1] inside the network, and the log-prob is that of a softmax policy
    hidden = agent.network(obs.float() / 255.0)
    expected = torch.log_softmax(agent.actor(hidden), -1).gather(-1, action[:, None]).squeeze(-1)
    torch.testing.assert_close(logprob, expected)
    torch.testing.assert_close(value, agent.critic(hidden).squeeze(-1))
    torch.testing.assert_close(agent.get_value(obs), value)


def test_orthogonal_init_gains():
    agent = atari.Agent(4)
    layers = [m for m in agent.network if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    for layer, gain in [*[(m, 2**0.5) for m in layers], (agent.actor, 0.01), (agent.critic, 1.0)]:
        w = layer.weight.detach().reshape(layer.weight.shape[0], -1).double()
        # orthogonal rows (all these matrices have fewer rows than columns), scaled by the gain
        torch.testing.assert_close(w @ w.T, gain**2 * torch.eye(w.shape[0], dtype=torch.float64), atol=1e-5, rtol=1e-5)
        assert torch.count_nonzero(layer.bias) == 0


def test_logged_return_is_the_whole_game(tmp_path):
    # A random Breakout game lasts a few hundred agent steps over 5 lives; one life, a few dozen.
    run_dir = tmp_path / "run"
    run_cli("ppo_atari.py", "--env-id", TINY["ppo_atari.py"]["env_id"], "--num-envs", "2", "--num-steps", "128",
            "--minibatch-size", "128", "--update-epochs", "1", "--total-timesteps", "1536", "--run-dir", run_dir, cwd=tmp_path)  # fmt: skip
    lengths = [v for _, v in tb_scalars(run_dir)["charts/episodic_length"]]
    assert lengths and min(lengths) > 60, lengths


def test_clip_range_and_learning_rate_anneal_together(tmp_path):
    run_dir = tmp_path / "run"
    run_cli("ppo_atari.py", "--env-id", TINY["ppo_atari.py"]["env_id"], *TINY["ppo_atari.py"]["tiny"], "--run-dir", run_dir, cwd=tmp_path)
    scalars = tb_scalars(run_dir)
    n = len(scalars["charts/clip_coef"])
    alpha = [1 - i / n for i in range(n)]  # 1 at the first iteration, falling linearly towards 0
    assert n >= 2
    assert [v for _, v in scalars["charts/clip_coef"]] == pytest.approx([0.1 * a for a in alpha])
    assert [v for _, v in scalars["charts/learning_rate"]] == pytest.approx([2.5e-4 * a for a in alpha])


def test_training_video_frames_are_not_overwritten_by_later_rollouts(tmp_path):
    # The rollout buffer is reused every iteration; a recorded frame must be a copy, or a game longer
    # than one rollout shows the last rollout's frames again and again.
    import imageio.v3 as iio

    run_dir = tmp_path / "run"
    run_cli("ppo_atari.py", "--env-id", TINY["ppo_atari.py"]["env_id"], "--num-envs", "2", "--num-steps", "32",
            "--minibatch-size", "64", "--update-epochs", "1", "--total-timesteps", "640", "--capture-video",
            "--run-dir", run_dir, cwd=tmp_path)  # fmt: skip
    video = max((run_dir / "videos").rglob("*.mp4"), key=lambda p: p.stat().st_size)
    frames = np.stack(list(iio.imiter(video))).astype(float)
    assert len(frames) > 64
    period_diffs = [np.abs(frames[k] - frames[k + 32]).mean() for k in range(len(frames) - 32)]
    assert max(period_diffs) > 1.0, "frames repeat with the rollout's period"
