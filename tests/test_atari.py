"""ppo_atari.py: the preprocessing of the ale-py vector env, episodic life, and the CNN."""

import re
from itertools import pairwise

import numpy as np
import pytest
import torch
from conftest import TINY, load_script, run_cli, tb_scalars

atari = load_script("ppo_atari.py")


def envs(num_envs=2, training=True, env_id="BreakoutNoFrameskip-v4", **args):
    return atari.make_envs(atari.Args(env_id=env_id, num_envs=num_envs, **args), training=training)


@pytest.mark.parametrize(
    "env_id,game,sticky",
    [
        ("BreakoutNoFrameskip-v4", "breakout", 0.0),
        ("ALE/Breakout-v5", "breakout", 0.25),
        ("BeamRiderNoFrameskip-v4", "beam_rider", 0.0),
        ("ALE/MsPacman-v5", "ms_pacman", 0.25),
        ("UpNDownNoFrameskip-v4", "up_n_down", 0.0),
    ],
)
def test_env_ids_mean_what_they_say(env_id, game, sticky):
    # The paper's NoFrameskip-v4 games repeat no action; v5 repeats the previous one with probability 0.25.
    assert atari.atari_game(env_id) == (game, sticky)


@pytest.mark.parametrize(
    "env_id,could_mean",
    [
        ("Breakout", "BreakoutNoFrameskip-v4 (the paper's) or ALE/Breakout-v5"),
        ("breakout", "BreakoutNoFrameskip-v4 (the paper's) or ALE/Breakout-v5"),
        ("PongDeterministic-v4", "PongNoFrameskip-v4 (the paper's) or ALE/Pong-v5"),
        ("ALE/BreakoutNoFrameskip-v5", "BreakoutNoFrameskip-v4 (the paper's) or ALE/Breakout-v5"),
        ("UpNDown", "UpNDownNoFrameskip-v4 (the paper's) or ALE/UpNDown-v5"),
    ],
)
def test_a_loose_name_is_refused_with_the_ids_it_could_mean(env_id, could_mean):
    with pytest.raises(ValueError, match=re.escape(could_mean)):
        atari.atari_game(env_id)
    with pytest.raises(ValueError, match="unknown env id 'NoSuchGame'"):
        atari.atari_game("NoSuchGame")


@pytest.mark.parametrize("env_id,sticky", [("ALE/Breakout-v5", 0.25), ("BreakoutNoFrameskip-v4", 0.0)])
def test_the_vector_env_gets_the_ids_sticky_actions(env_id, sticky, monkeypatch):
    import ale_py

    seen = {}
    real_init = ale_py.AtariVectorEnv.__init__

    def init(self, *args, **kwargs):
        seen.update(kwargs)
        real_init(self, *args, **kwargs)

    monkeypatch.setattr(ale_py.AtariVectorEnv, "__init__", init)
    envs(num_envs=1, env_id=env_id).close()
    assert seen["repeat_action_probability"] == sticky


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
    frames = info["episode_frame_number"]
    terminations, score, full_score = 0, 0.0, 0.0
    for _ in range(5000):
        action = rng.integers(0, 4, size=1)
        _, reward, term, trunc, info = e.step(action)
        _, full_reward, full_term, _, _ = full.step(action)
        score, full_score = score + reward[0], full_score + full_reward[0]
        terminations += int(term[0])
        if atari.game_over(term, trunc, frames, info["episode_frame_number"])[0]:
            break
        assert not term[0] or info["episode_frame_number"][0] == frames[0] + 4, "a lost life does not restart the game"
        frames = info["episode_frame_number"]
        assert not full_term[0], "the evaluation env ended the game early"
    e.close()
    full.close()
    assert terminations == 5, "Breakout: 4 lost lives and the end of the game"
    assert score == full_score and score > 0, "the raw score of the whole game, not one life's clipped reward"


@pytest.mark.parametrize(
    "term,trunc,frames,new_frames,expected",
    [
        (True, False, 400, 404, False),  # a lost life: the game's frame count goes on
        (True, False, 400, 7, True),  # the game ended: the count restarts with the next game's reset
        (True, False, 400, 0, True),  # ... a reset of no no-ops and no FIRE
        (False, True, 108_000, 12, True),  # cut by the frame cap
        (False, False, 400, 404, False),
        (True, True, 400, 3, True),
    ],
)
def test_game_over_table(term, trunc, frames, new_frames, expected):
    got = atari.game_over(np.array([term]), np.array([trunc]), np.array([frames]), np.array([new_frames]))
    assert got.tolist() == [expected]


def test_games_are_cut_at_max_episode_frames():
    assert atari.Args().max_episode_frames == 30 * 60 * 60, "the default is 30 minutes of play at 60 frames a second"
    e = envs(num_envs=1, env_id="PongNoFrameskip-v4", max_episode_frames=400)  # a Pong game lasts thousands of frames
    _, info = e.reset(seed=0)
    frames = info["episode_frame_number"]
    for step in range(1, 200):  # noqa: B007 -- step is read after the loop: the steps to the truncation
        _, _, term, trunc, info = e.step(np.zeros(1, dtype=np.int64))
        if term[0] or trunc[0]:
            break
        frames = info["episode_frame_number"]
    e.close()
    assert trunc[0] and not term[0], "a time limit is a truncation: its value is bootstrapped, not zeroed"
    assert 4 * step == 400 and "final_obs" in info, "400 frames of play, 4 to an agent step, after the reset's"
    assert atari.game_over(term, trunc, frames, info["episode_frame_number"])[0]


def play_one_game(env_id, seed, training=False):
    """A whole game of random actions in ppo_atari.py's env: its reset's frame count, and each step's action, reward
    and lives."""
    e = envs(num_envs=1, training=training, env_id=env_id)
    rng = np.random.default_rng(seed)
    _, info = e.reset(seed=seed)
    reset_frames, actions, rewards, lives = int(info["episode_frame_number"][0]), [], [], []
    while True:
        actions.append(int(rng.integers(e.single_action_space.n)))
        _, reward, term, trunc, info = e.step(np.array(actions[-1:]))
        rewards.append(float(reward[0]))
        lives.append(int(info["lives"][0]))
        if term[0] or trunc[0]:
            break
    e.close()
    return reset_frames, actions, rewards, lives[:-1]  # the last step returns the next game's lives


@pytest.mark.parametrize("env_id", ["BreakoutNoFrameskip-v4", "BeamRiderNoFrameskip-v4"])
def test_video_replays_the_same_game_in_colour_at_60_hz(env_id, tmp_path, monkeypatch):
    import ale_py
    import imageio.v3 as iio

    reset_frames, actions, rewards, lives = play_one_game(env_id, seed=4)
    replayed, replayed_lives, emulators = [], [], []

    class Recording(ale_py.ALEInterface):  # write_video's emulator, with every frame's reward noted
        def __init__(self):
            super().__init__()
            emulators.append(self)

        def act(self, action, *args):
            replayed.append(super().act(action, *args))
            replayed_lives.append(self.lives())
            return replayed[-1]

    monkeypatch.setattr(ale_py, "ALEInterface", Recording)
    path = tmp_path / "videos" / "game.mp4"
    atari.write_video(env_id, reset_frames, actions, str(path))
    # The same game: each agent step's reward (over its 4 frames) and lives where the env had them, and the game over.
    assert len(replayed) == reset_frames + 4 * len(actions)
    assert np.reshape(replayed[reset_frames:], (-1, 4)).sum(1).tolist() == rewards
    assert replayed_lives[reset_frames + 3 :: 4][:-1] == lives and lives[0] > lives[-1]
    assert emulators[0].game_over()
    # Every frame, in colour, at the game's size and rate: what a person watching the game sees.
    video = iio.imread(path)
    assert video.shape == (reset_frames + 4 * len(actions), 210, 160, 3)
    assert iio.immeta(path)["fps"] == 60
    assert np.abs(video[..., 0].astype(int) - video[..., 2]).mean() > 2, "the frames are gray"


@pytest.mark.parametrize("fire_on_life_loss", [True, False])
def test_fire_on_life_loss(fire_on_life_loss, tmp_path, monkeypatch):
    # Breakout: after a lost life the ball waits for FIRE. With the flag, the env presses it as the next action.
    import ale_py

    steps, real_step = [], ale_py.AtariVectorEnv.step

    def step(self, actions):
        result = real_step(self, actions)
        steps.append((actions.copy(), result[2].copy(), result[4]["episode_frame_number"].copy()))
        return result

    monkeypatch.setattr(ale_py.AtariVectorEnv, "step", step)
    atari.train(
        atari.Args(
            num_envs=4,
            num_steps=128,
            minibatch_size=128,
            update_epochs=1,
            total_timesteps=512,
            fire_on_life_loss=fire_on_life_loss,
            torch_threads=1,
            run_dir=str(tmp_path / "run"),
        )
    )
    fire = [a.name for a in atari.make_envs(atari.Args(num_envs=1)).ale.get_action_set()].index("FIRE")
    after_lost_life = [
        next_actions[i]
        for (_, term, frames), (next_actions, _, new_frames) in pairwise(steps)
        for i in np.flatnonzero(term & (new_frames > frames))
    ]
    assert len(after_lost_life) > 5
    assert all(a == fire for a in after_lost_life) == fire_on_life_loss, after_lost_life


def test_cnn_shapes_and_scaling():
    agent = atari.Agent(6)
    obs = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    action, logprob, probs, value = agent.get_action_and_value(obs)
    assert action.shape == logprob.shape == probs.entropy().shape == value.shape == (3,)
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


def test_logged_return_is_the_whole_game(tiny_run):
    # A random Breakout game lasts a few hundred agent steps over 5 lives; one life, a few dozen.
    lengths = [v for _, v in tb_scalars(tiny_run("ppo_atari.py")[0])["charts/episodic_length"]]
    assert lengths and min(lengths) > 60, lengths


def test_clip_range_and_learning_rate_anneal_together(tiny_run):
    scalars = tb_scalars(tiny_run("ppo_atari.py")[0])
    n = len(scalars["charts/clip_coef"])
    alpha = [1 - i / n for i in range(n)]  # 1 at the first iteration, falling linearly towards 0
    assert n >= 2
    assert [v for _, v in scalars["charts/clip_coef"]] == pytest.approx([0.1 * a for a in alpha])
    assert [v for _, v in scalars["charts/learning_rate"]] == pytest.approx([2.5e-4 * a for a in alpha])


def test_training_and_evaluation_videos_are_whole_games_in_colour(tmp_path):
    # Games 0 and 1 of the first env, each longer than one rollout, and the evaluation game.
    import imageio.v3 as iio

    run_dir = tmp_path / "run"
    run_cli(
        "ppo_atari.py",
        "--env-id",
        TINY["ppo_atari.py"]["env_id"],
        "--num-envs",
        "2",
        "--num-steps",
        "32",
        "--minibatch-size",
        "64",
        "--update-epochs",
        "1",
        "--total-timesteps",
        "1280",
        "--capture-video",
        "--run-dir",
        run_dir,
        cwd=tmp_path,
    )
    run_cli(
        "ppo_atari.py",
        "--eval-checkpoint",
        run_dir / "checkpoint.pt",
        "--eval-episodes",
        "1",
        "--capture-video",
        cwd=tmp_path,
    )
    names = sorted(p.name.split("-game-")[1] for p in (run_dir / "videos").glob("*.mp4"))
    assert names[:2] == ["0.mp4", "1.mp4"], names
    for path in [*(run_dir / "videos").glob("*.mp4"), run_dir / "videos-eval" / "eval-game-0.mp4"]:
        video = iio.imread(path)
        assert video.shape[1:] == (210, 160, 3) and len(video) > 4 * 60 and iio.immeta(path)["fps"] == 60, path
        assert np.abs(video[..., 0].astype(int) - video[..., 2]).mean() > 2, f"{path} is gray"


def test_videos_of_sticky_games_are_refused_before_training(tmp_path, monkeypatch, capsys):
    # A video replays a game from its actions, which sticky actions would not repeat.
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["ppo_atari.py", "--env-id", "ALE/Breakout-v5", "--capture-video"])
    monkeypatch.setattr(atari, "train", lambda args: pytest.fail("training started"))
    with pytest.raises(SystemExit) as stopped:
        atari.main()
    err = capsys.readouterr().err.strip().splitlines()
    assert stopped.value.code == 2 and len(err) == 1 and "sticky actions" in err[0], err
