"""The changes a learner makes after pasting a gym script into a project, each of which once met a trap: a new flag
whose default is 0, a network of their own, a flag typed on --resume, a renamed copy, an env of their own filmed with
--capture-video, one more quantity stored in the rollout, a term added to the loss, a copy's network given the script's
checkpoint, and filming without the videos' writer installed. Each test makes the change as a user would, on the real
script or on a copy of it, and runs it."""

import dataclasses
import os
import subprocess
import sys
import typing

import pytest
import torch
from conftest import (
    ONE_THREAD,
    ROOT,
    TINY,
    call_main,
    load_script,
    roll_back,
    run_cli,
    script_at,
    tb_scalars,
    train_tiny,
)

GYM_SCRIPTS = ["ppo_continuous.py", "ppo_atari.py", "ppo_kl_penalty.py"]
MUJOCO_SCRIPTS = ["ppo_continuous.py", "ppo_kl_penalty.py"]


def copy_of(script, path, after=None, insert=""):
    """A copy of a script at `path`, with the lines `insert` added after the first line that contains `after`."""
    lines = (ROOT / script).read_text().splitlines(keepends=True)
    if after is not None:
        at = next((i for i, line in enumerate(lines) if after in line), None)
        assert at is not None, f"{script} has no line with {after!r} to add a line after"
        indent = lines[at][: len(lines[at]) - len(lines[at].lstrip())]
        lines[at + 1 : at + 1] = [indent + line + "\n" for line in insert.splitlines()]
    path.write_text("".join(lines))
    return path


def run_copy(path, *args, cwd, env=None, check=True):
    cmd = [sys.executable, str(path), *map(str, args), *ONE_THREAD]
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=300, env=env)
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_new_float_flag_at_zero_is_accepted_unless_a_range_is_declared(script, monkeypatch):
    module = load_script(script)

    @dataclasses.dataclass
    class WithAuxLoss(module.Args):
        aux_coef: float = 0.0  # a learner's new coefficient, off by default

    monkeypatch.setattr(module, "Args", WithAuxLoss)  # load_checkpoint and check_args see the learner's Args
    module.check_args(WithAuxLoss(env_id=TINY[script]["env_id"]))
    module.check_args(WithAuxLoss(env_id=TINY[script]["env_id"], aux_coef=-2.5))
    with pytest.raises(ValueError, match="--aux-coef must be a finite number"):
        module.check_args(WithAuxLoss(env_id=TINY[script]["env_id"], aux_coef=float("nan")))
    monkeypatch.setitem(module.RANGES, "aux_coef", (0, 1))  # a declared range is checked
    with pytest.raises(ValueError, match=r"--aux-coef must be in \[0, 1\]"):
        module.check_args(WithAuxLoss(env_id=TINY[script]["env_id"], aux_coef=-2.5))


def test_evaluation_uses_the_agents_own_method(tmp_path, monkeypatch):
    """A learner's network with other attribute names: evaluation acts through get_action_and_value, the one method
    that training uses too, and takes the mean of the distribution it returns."""
    module = load_script("ppo_continuous.py")

    class RenamedAgent(module.Agent):
        def __init__(self, obs_dim, act_dim, norm_obs=True):
            super().__init__(obs_dim, act_dim, norm_obs)
            self.policy_net = self.actor_mean
            del self.actor_mean

        def get_action_and_value(self, obs, action=None):
            probs = module.Independent(module.Normal(self.policy_net(obs), self.actor_logstd.exp()), 1)
            action = probs.sample() if action is None else action
            return action, probs.log_prob(action), probs, self.get_value(obs)

    monkeypatch.setattr(module, "Agent", RenamedAgent)
    tiny = dict(num_steps=64, minibatch_size=32, update_epochs=1, total_timesteps=64)
    args = module.Args(env_id="Pendulum-v1", run_dir=str(tmp_path / "run"), **tiny)
    module.train(args)
    eval_args = module.Args(eval_checkpoint=str(tmp_path / "run" / "checkpoint.pt"), eval_episodes=1)
    returns = module.evaluate(eval_args)
    assert len(returns) == 1 and returns[0] < 0  # Pendulum's rewards are never positive


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_hyperparameter_typed_with_resume_is_refused_and_a_runtime_flag_applied(script, tmp_path, monkeypatch):
    run_dir, _ = train_tiny(script, tmp_path)
    checkpoint = run_dir / "checkpoint.pt"
    proc = run_cli(script, "--resume", checkpoint, "--learning-rate", "0.123", cwd=tmp_path, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "--learning-rate 0.123" in lines[0] and "resumed run keeps" in lines[0], lines[0]
    # The checkpoint's own value typed again changes nothing, and a runtime flag reaches train().
    module = load_script(script)
    lr = torch.load(checkpoint, weights_only=True)["args"]["learning_rate"]
    argv = [script, "--resume", str(checkpoint), "--learning-rate", str(lr), "--save-every", "7", *ONE_THREAD]
    trained = []
    monkeypatch.setattr(sys, "argv", argv)
    monkeypatch.setattr(
        module, "train", lambda args, stop=(): trained.append(module.load_checkpoint(args.resume, args))
    )
    monkeypatch.setattr(module.signal, "signal", lambda *args: None)  # main()'s handlers stay out of pytest's way
    module.main()
    resumed = trained[0][1]
    assert resumed.save_every == 7 and resumed.learning_rate == lr and resumed.run_dir == str(run_dir)


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_checkpoint_with_a_field_args_no_longer_has_is_refused_in_one_line(script, tmp_path):
    run_dir, _ = train_tiny(script, tmp_path)
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    checkpoint["args"]["aux_coef"] = 0.5  # written by a copy that had this flag
    torch.save(checkpoint, tmp_path / "renamed-field.pt")
    proc = run_cli(script, "--resume", tmp_path / "renamed-field.pt", cwd=tmp_path, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "aux_coef" in lines[0], proc.stderr


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_renamed_copy_resumes_its_own_checkpoints_and_refuses_another_scripts(script, tmp_path):
    run_dir, _ = train_tiny(script, tmp_path)  # a run of the script under its own name; then the file is renamed
    copy = copy_of(script, tmp_path / "my_ppo.py")
    proc = run_copy(copy, "--resume", run_dir / "checkpoint.pt", cwd=tmp_path)
    assert "saved" in proc.stdout
    cfg = TINY[script]
    run_copy(copy, "--env-id", cfg["env_id"], *cfg["tiny"], "--run-dir", tmp_path / "copy-run", cwd=tmp_path)
    run_cli(script, "--resume", tmp_path / "copy-run" / "checkpoint.pt", cwd=tmp_path)  # and back
    other = next(s for s in GYM_SCRIPTS if s != script)
    other_run, _ = train_tiny(other, tmp_path, "other")
    proc = run_copy(copy, "--resume", other_run / "checkpoint.pt", cwd=tmp_path, check=False)
    assert proc.returncode == 2 and "not a checkpoint written by" in proc.stderr, proc.stderr


MYPKG = '''
import gymnasium as gym
import numpy as np


class MyEnv(gym.Env):
    """A point on a line, pushed toward 0; drawn as a 32x48 picture. Not MuJoCo: it has no model."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, render_mode=None):
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (2,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.t = self.np_random.uniform(-1, 1), 0
        return np.array([self.x, 0.0]), {}

    def step(self, action):
        self.x += 0.1 * float(action[0])
        self.t += 1
        return np.array([self.x, self.t / 20]), -abs(self.x), False, self.t >= 20, {}

    def render(self):
        frame = np.zeros((32, 48, 3), dtype=np.uint8)
        frame[:, int(np.clip(24 + 10 * self.x, 0, 47))] = 255
        return frame


gym.register("MyEnv-v0", entry_point=MyEnv, max_episode_steps=20)
'''


# ppo_kl_penalty.py films with the same make_env (tests/test_alignment.py keeps the two identical), checked alike.
@pytest.mark.parametrize("script", MUJOCO_SCRIPTS[:1])
@pytest.mark.parametrize("how", ["import in the script", "module:id"])
def test_capture_video_films_any_env_that_renders_rgb_array(script, how, tmp_path):
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text(MYPKG)
    if how == "import in the script":
        copy = copy_of(script, tmp_path / "train.py", after="import torch.nn as nn", insert="import mypkg  # noqa")
        env_id = "MyEnv-v0"
    else:
        copy = copy_of(script, tmp_path / "train.py")
        env_id = "mypkg:MyEnv-v0"
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    tiny = "--num-steps 64 --minibatch-size 32 --update-epochs 1 --total-timesteps 128".split()
    run_dir = tmp_path / "run"
    run_copy(copy, "--env-id", env_id, *tiny, "--capture-video", "--run-dir", run_dir, cwd=tmp_path, env=env)
    videos = sorted((run_dir / "videos").glob("*.mp4"))
    assert videos and all(v.stat().st_size > 0 for v in videos)


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_new_rollout_quantity_is_one_line_of_storage(script, tmp_path, monkeypatch):
    """One line declares the quantity beside the others, one line fills it in the rollout, and the update's
    minibatches have it, shuffled with the rest."""
    path = copy_of(
        script,
        tmp_path / "one_more.py",
        after="buf.actions = torch.zeros(",
        insert=("buf.step_number = torch.zeros((T, N_rank), device=device)"),
    )
    path.write_text(
        path.read_text().replace(
            "                    buf.obs[step] = next_obs\n",
            "                    buf.obs[step] = next_obs\n                    buf.step_number[step] = step\n",
        )
    )
    module = load_script_at(path)
    seen = []
    real = module.minibatch_loss

    def recording(agent, batch, mb_inds, *rest):
        seen.append((batch["step_number"][mb_inds], batch["obs"][mb_inds]))
        return real(agent, batch, mb_inds, *rest)

    monkeypatch.setattr(module, "minibatch_loss", recording)
    args = one_iteration(module, script, tmp_path / "run")
    module.train(args)
    steps = torch.cat([s for s, _ in seen])
    n = args.num_envs
    assert sorted(steps.tolist()) == sorted(
        [float(t) for t in range(args.num_steps) for _ in range(n)] * args.update_epochs
    )


def one_iteration(module, script, run_dir):
    """The Args of one iteration of a script's TINY run, written to run_dir, for its train() in this process."""
    cfg = TINY[script]
    args = module.Args(env_id=cfg["env_id"], run_dir=str(run_dir), torch_threads=1)
    flags = dict(zip(cfg["tiny"][::2], cfg["tiny"][1::2], strict=True))
    for flag, value in flags.items():
        field = flag[2:].replace("-", "_")
        setattr(args, field, type(getattr(args, field))(value))
    args.total_timesteps = args.num_envs * args.num_steps
    return args


def load_script_at(path):
    import importlib.util

    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


# A learner's own network in a copy: (the script's lines, the copy's, the first parameter that then differs).
ANOTHER_NETWORK = {
    "ppo_continuous.py": (
        "    hidden = [layer_init(nn.Linear(n_in, 64)), nn.Tanh(), layer_init(nn.Linear(64, 64)), nn.Tanh()]\n"
        "    return nn.Sequential(*hidden, layer_init(nn.Linear(64, n_out), std=std))",
        "    sizes = [n_in, 128, 128, 128]  # 3 x 128 ReLU\n"
        "    hidden = [m for a, b in itertools.pairwise(sizes) for m in (layer_init(nn.Linear(a, b)), nn.ReLU())]\n"
        "    return nn.Sequential(*hidden, layer_init(nn.Linear(128, n_out), std=std))",
        "critic.0.weight [64, 11] where this script's has critic.0.weight [128, 11]",
    ),
    "ppo_atari.py": (
        "fc = layer_init(nn.Linear(64 * 7 * 7, 512))",
        "fc = layer_init(nn.Linear(64 * 7 * 7, 256))",
        "network.7.weight [512, 3136] where this script's has network.7.weight [256, 3136]",
    ),
}
ANOTHER_NETWORK["ppo_kl_penalty.py"] = ANOTHER_NETWORK["ppo_continuous.py"]


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_copy_with_another_network_refuses_the_scripts_checkpoint_in_one_line_before_writing(script, tmp_path):
    run_dir, _ = train_tiny(script, tmp_path)
    old, new, first_difference = ANOTHER_NETWORK[script]
    copy = copy_of(script, tmp_path / "my_ppo.py")
    assert old in copy.read_text()
    copy.write_text(copy.read_text().replace(old, new))
    written = {path: path.stat().st_mtime_ns for path in run_dir.rglob("*")}
    for flag in ("--resume", "--eval-checkpoint"):
        proc = run_copy(copy, flag, run_dir / "checkpoint.pt", cwd=tmp_path, check=False)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert f"holds another network: {first_difference}" in lines[0], lines[0]
    assert {path: path.stat().st_mtime_ns for path in run_dir.rglob("*")} == written, "nothing is written"


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_term_added_to_the_loss_is_in_the_finite_check_and_in_the_logged_loss(script, tmp_path):
    """A learner adds a term to the loss at the end of minibatch_loss: the loss logged is the loss minimized, and a
    term that is not finite stops the run, though the gradient (of a constant) leaves the weights finite."""
    path = copy_of(script, tmp_path / "aux.py", after='stats["clipfrac"] = ', insert="loss = loss + EXTRA")
    module = load_script_at(path)
    module.EXTRA = 1000.0
    args = one_iteration(module, script, tmp_path / "logged")
    module.train(args)
    scalars = {tag: values[0][1] for tag, values in tb_scalars(tmp_path / "logged").items()}
    terms = scalars["losses/policy_loss"] - args.ent_coef * scalars["losses/entropy"]
    terms += args.vf_coef * scalars["losses/value_loss"]
    assert scalars["losses/loss"] == pytest.approx(terms + 1000.0, abs=1e-3)
    module.EXTRA = float("inf")
    args.run_dir = str(tmp_path / "checked")
    with pytest.raises(module.Diverged, match="not finite after iteration 1"):
        module.train(args)


# How the runtime flags are typed in the test below: values the command line takes (check_args is not its subject).
RUNTIME_VALUES = {"device": "cpu", "run_dir": "elsewhere", "resume": None}


def another_value(field, value, tmp_path):
    """Command-line words that set a field of Args to another value than `value`, of its type."""
    flag = "--" + field.name.replace("_", "-")
    if field.name in RUNTIME_VALUES:
        typed = RUNTIME_VALUES[field.name]
        return [] if typed is None else [flag, str(tmp_path / typed) if field.name == "run_dir" else typed]
    if isinstance(value, bool):
        return [f"--no-{flag[2:]}" if value else flag]
    if typing.get_origin(field.type) is typing.Literal:
        return [flag, next(choice for choice in typing.get_args(field.type) if choice != value)]
    kind = type(value) if value is not None else next(t for t in typing.get_args(field.type) if t is not type(None))
    if kind in (int, float):
        return [flag, str((value or 0) + 1)]
    if typing.get_origin(kind) is tuple or kind is tuple:
        return [flag, "0.5", "0.25"]
    return [flag, f"other-{field.name}"]


# The flags that change how a run goes on or where it is logged, never what it computes: typed with --resume, each
# applies. Any other field of Args, a hyperparameter, is refused.
RUNTIME = {"device", "compile", "torch_threads", "save_every", "resume", "run_dir", "exp_name", "track"}
RUNTIME |= {"wandb_project_name", "wandb_entity", "capture_video", "eval_checkpoint", "eval_episodes"}
# What main() may start once the command line is read: each is replaced, to see the Args it would get.
STARTS = ("train", "evaluate", "start_tracking")


def check_the_two_lists(module, checkpoint, tmp_path, monkeypatch, capsys):
    saved = torch.load(checkpoint, weights_only=True)["args"]
    fields = dataclasses.fields(module.Args)
    assert set(module.RUNTIME_FIELDS) == RUNTIME & {field.name for field in fields}
    for field in fields:
        typed = another_value(field, saved[field.name], tmp_path)
        got = call_main(module, ["--resume", checkpoint, *typed], monkeypatch, STARTS, checked=False)
        err = capsys.readouterr().err.strip().splitlines()
        if field.name in module.RUNTIME_FIELDS:
            assert not isinstance(got, int | str | None), (field.name, err)
            assert getattr(got, field.name) != saved[field.name] or field.name == "resume", field.name
            assert {k: v for k, v in dataclasses.asdict(got).items() if k not in RUNTIME} == {
                k: v for k, v in saved.items() if k not in RUNTIME
            }, field.name
        else:
            assert got == 2 and len(err) == 1 and "a resumed run keeps its checkpoint's" in err[0], (field.name, err)
            assert "--" + field.name.replace("_", "-") in err[0], (field.name, err)


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_on_resume_a_runtime_flag_applies_and_a_hyperparameter_is_refused(
    script, tmp_path, tiny_run, monkeypatch, capsys
):
    check_the_two_lists(load_script(script), tiny_run(script)[0] / "checkpoint.pt", tmp_path, monkeypatch, capsys)


# The writers of the videos: gymnasium's RecordVideo uses moviepy; Atari's write_video, imageio's ffmpeg plugin.
VIDEO_WRITER = {"ppo_continuous.py": "moviepy", "ppo_kl_penalty.py": "moviepy", "ppo_atari.py": "imageio_ffmpeg"}


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_capture_video_without_its_writer_is_refused_in_one_line(script, tmp_path):
    cfg = TINY[script]
    argv = [script, "--env-id", cfg["env_id"], *cfg["tiny"], "--capture-video", "--run-dir", str(tmp_path / "run")]
    code = (
        f"import runpy, sys; sys.modules[{VIDEO_WRITER[script]!r}] = None; sys.argv = {[*argv, *ONE_THREAD]!r};"
        f" runpy.run_path({str(ROOT / script)!r}, run_name='__main__')"
    )  # sys.modules[name] = None: `import name` fails as if the package were not installed
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert "--capture-video" in lines[0] and VIDEO_WRITER[script].replace("_", "-") in lines[0], lines[0]


OLD = "45c9356"  # a commit before checkpoints were checked against the network that reads them


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_checkpoint_written_at_the_earlier_commit_resumes(script, tmp_path):
    old = script_at(OLD, script, tmp_path / "old")
    cfg = TINY[script]
    run_copy(old, "--env-id", cfg["env_id"], *cfg["tiny"], "--run-dir", tmp_path / "run", cwd=tmp_path)
    path = tmp_path / "run" / "checkpoint.pt"
    checkpoint = roll_back(path)
    proc = run_cli(script, "--resume", path, cwd=tmp_path)
    assert f"resuming {tmp_path / 'run'} at step {checkpoint['global_step']:,}" in proc.stdout, proc.stdout
    assert torch.load(path, weights_only=True)["iteration"] == checkpoint["iteration"] + 1


def test_on_resume_a_runtime_flag_of_ppo_rlhf_applies_and_a_hyperparameter_is_refused(tmp_path, monkeypatch, capsys):
    rlhf = load_script("ppo_rlhf.py")
    args = rlhf.Args(d_model=16, n_layer=1, n_head=2, seed=5)
    rlhf.save_checkpoint(str(tmp_path / "checkpoint.pt"), "ppo", args, iteration=1, global_step=64)
    check_the_two_lists(rlhf, tmp_path / "checkpoint.pt", tmp_path, monkeypatch, capsys)
