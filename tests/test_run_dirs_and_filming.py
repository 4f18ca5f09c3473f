"""Runs that start together never share a folder, and filming that cannot start stops the run in one line before it
begins. Both through the scripts' real command lines."""

import os
import subprocess
import sys

import pytest
import torch
from conftest import ONE_THREAD, ROOT, TINY, train_tiny

# Every process sees the same second: int(time.time()) stays put for 500 s, while time still advances (a thousandth
# as fast, still far above float's resolution), so that rates and ETAs stay finite. Python imports this module at
# startup from PYTHONPATH.
FROZEN_CLOCK = """import time
_real, _start = time.time, time.time()
time.time = lambda: 1_800_000_000.25 + (_real() - _start) * 1e-3
"""


@pytest.mark.parametrize("script", sorted(TINY))
def test_two_runs_started_together_with_one_seed_keep_two_folders(script, tmp_path):
    clock = tmp_path / "clock"
    clock.mkdir()
    (clock / "sitecustomize.py").write_text(FROZEN_CLOCK)
    env_flags = ["--env-id", TINY[script]["env_id"]] if "env_id" in TINY[script] else []
    cmd = [sys.executable, str(ROOT / script), *env_flags, *TINY[script]["tiny"], "--seed", "7", *ONE_THREAD]
    env = {**os.environ, "PYTHONPATH": str(clock), "PYTHONUNBUFFERED": "1"}
    procs = [subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)]
    procs.append(
        subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    )
    outputs = [p.communicate(timeout=400) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err[-2000:] for _, err in outputs]
    folders = sorted(path for path in (tmp_path / "runs").rglob("*__1800000000*") if path.is_dir())
    # both named after the env, the experiment, the seed and the (frozen) time; the second one with a suffix
    assert [f.name.endswith("__7__1800000000") for f in folders] == [True, False], folders
    assert folders[1].name == folders[0].name + "-2"
    for folder in folders:
        saved = [name for name in os.listdir(folder) if name.endswith(".pt")]
        assert "checkpoint.pt" in saved, (folder, saved)
        for name in saved:
            torch.load(folder / name, weights_only=True)  # intact


def test_a_given_run_dir_that_holds_a_run_is_still_refused(tmp_path):
    run_dir, _ = train_tiny("ppo_continuous.py", tmp_path)
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "ppo_continuous.py"),
            *TINY["ppo_continuous.py"]["tiny"],
            "--run-dir",
            str(run_dir),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "already holds a run" in proc.stderr


def fake_opengl(folder):
    """A stand-in for PyOpenGL where EGL cannot start, as on a GPU server without libEGL: loading a library raises
    OSError, and OpenGL.EGL raises the AttributeError PyOpenGL raised there."""
    package = folder / "OpenGL"
    (package / "platform").mkdir(parents=True)
    (package / "EGL").mkdir()
    (package / "__init__.py").write_text("")
    (package / "error.py").write_text("class GLError(Exception): ...\nclass Error(Exception): ...\n")
    (package / "platform" / "__init__.py").write_text("")
    (package / "platform" / "ctypesloader.py").write_text(
        "def loadLibrary(*args, **kwargs):\n    raise OSError('libEGL.so.1: cannot open shared object file')\n"
    )
    (package / "EGL" / "__init__.py").write_text(
        "raise AttributeError(\"'NoneType' object has no attribute 'eglQueryString'\")\n"
    )
    return folder


def without_mujoco_gl(**more):
    """The environment of a user who has not chosen MuJoCo's GL backend (mujoco loads it at import when one is set)."""
    return {**{k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}, **more}


FILMING = [
    ("ppo_continuous.py", ["--capture-video"]),
    ("ppo_kl_penalty.py", ["--capture-video"]),
    ("ppo_continuous.py", ["--eval-checkpoint", "CHECKPOINT", "--capture-video"]),
]


@pytest.mark.parametrize("script,flags", FILMING, ids=["train", "train-kl", "eval"])
def test_filming_that_cannot_start_is_one_line_before_the_run(script, flags, tmp_path):
    if "CHECKPOINT" in flags:
        run_dir, _ = train_tiny(script, tmp_path, "trained")
        flags = [str(run_dir / "checkpoint.pt") if f == "CHECKPOINT" else f for f in flags]
    env = without_mujoco_gl(PYTHONPATH=str(fake_opengl(tmp_path / "gl")))  # the script picks EGL to film
    cmd = [sys.executable, str(ROOT / script), *TINY[script]["tiny"], "--run-dir", str(tmp_path / "run"), *flags]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--capture-video cannot render" in lines[0], proc.stderr[-3000:]
    assert "MUJOCO_GL=egl" in lines[0] and "MUJOCO_GL=osmesa" in lines[0] and "libegl1" in lines[0]
    assert not (tmp_path / "run").exists()  # stopped before its run directory
    assert not any((tmp_path / "trained").glob("videos-eval*"))


def test_a_run_that_films_nothing_never_touches_gl(tmp_path):
    env = without_mujoco_gl(PYTHONPATH=str(fake_opengl(tmp_path / "gl")))
    cmd = [sys.executable, str(ROOT / "ppo_continuous.py"), *TINY["ppo_continuous.py"]["tiny"], "--run-dir", "run"]
    proc = subprocess.run([*cmd, *ONE_THREAD], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "run" / "checkpoint.pt").exists()
