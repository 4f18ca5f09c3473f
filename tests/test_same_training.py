"""The scripts were rewritten for reading, not for what they compute: for a fixed seed, each trains to
bit-identical weights, normalization statistics, optimizer state, beta and RNG state as the same script at the
reference commit, which produced the committed benchmark results. Short eager runs, through the real command line."""

import dataclasses
import subprocess
import sys

import pytest
import torch
from conftest import ONE_THREAD, ROOT, TINY, load_script

REFERENCE = "7632f39"
MUJOCO = ["--num-steps", "128", "--minibatch-size", "32", "--update-epochs", "3", "--total-timesteps", "256"]
ATARI = ["--num-envs", "4", "--num-steps", "64", "--minibatch-size", "64", "--update-epochs", "2"]
ATARI += ["--total-timesteps", "512", "--max-episode-frames", "400"]
# One case a script: Hopper ends its episodes by termination, Pendulum by its 200-step time limit (a truncation,
# bootstrapped), and Breakout by both, with FIRE pressed after a lost life.
CASES = [
    ("ppo_continuous.py", ["--env-id", "Hopper-v5", *MUJOCO, "--num-envs", "2", "--ent-coef", "0.01"]),
    ("ppo_kl_penalty.py", ["--env-id", "Pendulum-v1", *MUJOCO, "--init-beta", "3"]),
    ("ppo_atari.py", ["--env-id", "BreakoutNoFrameskip-v4", *ATARI, "--vf-coef", "1.0", "--fire-on-life-loss"]),
]


def reference_source(script, commit=REFERENCE):
    proc = subprocess.run(["git", "show", f"{commit}:{script}"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, f"this test needs the git history of commit {commit}: {proc.stderr}"
    return proc.stdout


def checkpoint_after(path, flags, run_dir):
    cmd = [sys.executable, str(path), *flags, "--run-dir", str(run_dir), *ONE_THREAD]
    proc = subprocess.run(cmd, cwd=run_dir.parent, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return torch.load(run_dir / "checkpoint.pt", weights_only=True)


def assert_identical(a, b, where):
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_identical(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_identical(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a, b), where
    else:
        assert a == b, where


@pytest.mark.parametrize("script,flags", CASES, ids=[f"{s[4:-3]}-{f[1]}-{f[-1]}" for s, f in CASES])
def test_training_is_bit_identical_to_the_reference_commit(script, flags, tmp_path):
    (tmp_path / "reference").mkdir()
    old_script = tmp_path / "reference" / script
    old_script.write_text(reference_source(script))
    old = checkpoint_after(old_script, flags, tmp_path / "old")
    new = checkpoint_after(ROOT / script, flags, tmp_path / "new")
    assert new["global_step"] == old["global_step"] > 0
    for key in ("agent", "optimizer", "torch_rng_state", "iteration", "beta"):
        assert (key in old) == (key in new), key
        if key in old:
            assert_identical(old[key], new[key], key)
    # the run's arguments: the same, but for where it was written; flags added since (Table 4's, --track) at their
    # defaults, which change nothing
    added = new["args"].keys() - old["args"].keys()
    assert {k: v for k, v in old["args"].items() if k != "run_dir"} == {
        k: v for k, v in new["args"].items() if k != "run_dir" and k not in added
    }
    defaults = dataclasses.asdict(load_script(script).Args())
    assert {k: new["args"][k] for k in added} == {k: defaults[k] for k in added}


# ppo_rlhf.py before --rm-refresh, which trains the reward model during stage 3: without it (the default, 0), the
# three stages train as they did, bit for bit, for an outcome and for a process reward model.
RLHF_REFERENCE = "45c9356"


@pytest.mark.parametrize("reward", ["outcome", "process"])
def test_ppo_rlhf_without_a_refresh_trains_as_before_the_flag(reward, tmp_path):
    flags = [*TINY["ppo_rlhf.py"]["tiny"], "--reward", reward, "--kl-coef", "0"]
    (tmp_path / "reference").mkdir()
    old_script = tmp_path / "reference" / "ppo_rlhf.py"
    old_script.write_text(reference_source("ppo_rlhf.py", RLHF_REFERENCE))
    old = checkpoint_after(old_script, flags, tmp_path / "old")
    new = checkpoint_after(ROOT / "ppo_rlhf.py", flags, tmp_path / "new")
    assert new["iteration"] == old["iteration"] > 0
    assert "rm_optimizer" not in new and "refresh_labels" not in new
    for key in ("agent", "optimizer", "reference", "reward_model", "rm_pool", "kl_coef", "torch_rng_state"):
        assert_identical(old[key], new[key], key)
    old_rm, new_rm = (
        torch.load(run / "reward_model.pt", weights_only=True) for run in (tmp_path / "old", tmp_path / "new")
    )
    for key in old_rm.keys() - {"args"}:  # the same reward model, and what was said of it, and more (train_pairs)
        assert_identical(old_rm[key], new_rm[key], key)
    assert new["args"] == {**old["args"], "run_dir": new["args"]["run_dir"], "rm_refresh": 0}


def test_the_comparison_can_fail():
    with pytest.raises(AssertionError):
        assert_identical({"w": torch.tensor([1.0, 2.0])}, {"w": torch.tensor([1.0, 2.001])}, "w")
    with pytest.raises(AssertionError):
        assert_identical({"count": 3.0}, {"count": 3.0000001}, "count")
