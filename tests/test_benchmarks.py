"""benchmarks/run.py and benchmarks/report.py: the runner never loses or repeats work, rejects a bad
grid before it starts anything, and the report's arithmetic is the paper's."""

import contextlib
import csv
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from conftest import ROOT, signal_at_checkpoint

sys.path.insert(0, str(ROOT / "benchmarks"))
import report  # noqa: E402
import run  # noqa: E402

from results import RLHF_STATS, UPDATE_STATS, read_csv, write_csv, write_series  # noqa: E402

# One iteration of ppo_continuous.py's default batch is 2048 steps; InvertedPendulum is the cheapest env.
TINY_GRID = ["--envs", "InvertedPendulum", "--seeds", "1"]


def runner(*args, tmp_path, check=True, timeout=300):
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "run.py"),
            *args,
            "--results-dir",
            str(tmp_path / "results"),
            "--runs-dir",
            str(tmp_path / "runs"),
            "--status-every",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"run.py {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.mark.parametrize(
    "args, message",
    [
        (["nosuchsuite"], "unknown suite 'nosuchsuite'"),
        (["table1", "--variants", "clip0.25"], "has no variant 'clip0.25'"),
        (["mujoco", "--envs", "Hoppper-v5"], "unknown env id 'Hoppper-v5'"),
        (["mujoco", "--envs", "CartPole-v1"], "needs a Box action space"),
        (["mujoco", "--workers", "0"], "--workers must be positive"),
    ],
)
def test_runner_rejects_a_bad_grid_before_starting(tmp_path, args, message):
    proc = runner(*args, tmp_path=tmp_path, check=False)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "runs").exists(), "nothing may start"


def test_check_grid_rejects_a_flag_the_script_lacks(tmp_path):
    job = run.make_grid("mujoco", envs=["Hopper"], seeds=[1], results_root=tmp_path, runs_root=tmp_path)[0]
    job.flags = ["--kl-target", "0.01"]  # ppo_kl_penalty.py's flag, not ppo_continuous.py's
    with pytest.raises(ValueError, match="does not accept the flags --kl-target 0.01"):
        run.check_grid([job])


@pytest.mark.parametrize("suite", list(run.SUITES))
def test_every_suite_is_a_valid_grid(suite):
    """Each variant's flags parse with its script's own parser, and each env passes its checks."""
    jobs = run.make_grid(suite)
    spec = run.SUITES[suite]
    sizes = [
        len(spec.only[v][0]) * len(spec.only[v][1]) if v in spec.only else len(spec.envs) * len(spec.seeds)
        for v in spec.variants
    ]
    assert len(jobs) == sum(sizes)
    run.check_grid(jobs)


def test_atari_suite_is_three_games_three_seeds_and_the_arms_of_issue_30():
    runs = {(job.variant, job.env_id.split("NoFrameskip")[0], job.seed) for job in run.make_grid("atari")}
    assert {(e, s) for v, e, s in runs if v == "ppo"} == {
        (e, s) for e in ("Pong", "Breakout", "BeamRider") for s in (1, 2, 3)
    }
    for arm in ("vf0.5", "e4", "zoo", "sb3"):  # where we trail the peer: Pong and Breakout, 3 seeds each
        assert {(e, s) for v, e, s in runs if v == arm} == {(e, s) for e in ("Pong", "Breakout") for s in (1, 2, 3)}
    assert {(e, s) for v, e, s in runs if v == "novclip"} == {("Pong", s) for s in (1, 2, 3)}
    assert run.SUITES["atari"].variants["vf0.5"] == ("ppo_atari.py", ["--compile", "--vf-coef", "0.5"])
    assert run.SUITES["atari"].variants["e4"] == ("ppo_atari.py", ["--compile", "--update-epochs", "4"])
    assert run.SUITES["atari"].variants["novclip"] == ("ppo_atari.py", ["--compile", "--no-clip-vloss"])
    zoo = ["--compile", "--update-epochs", "4", "--vf-coef", "0.5", "--no-clip-vloss"]
    assert run.SUITES["atari"].variants["zoo"] == ("ppo_atari.py", zoo)
    assert {job.total_timesteps for job in run.make_grid("atari")} == {1_000_000}


def test_table1_rows_are_the_papers():
    import tyro

    variants = run.SUITES["table1"].variants
    parsed = {
        name: (script, tyro.cli(run.load_script(script).Args, args=flags)) for name, (script, flags) in variants.items()
    }
    assert parsed["no-clip"][1].init_beta == 0 and not parsed["no-clip"][1].adaptive_beta
    assert [parsed[f"clip{e}"][1].clip_coef for e in ("0.1", "0.2", "0.3")] == [0.1, 0.2, 0.3]
    for d in ("0.003", "0.01", "0.03"):
        args = parsed[f"kl{d}"][1]
        assert (
            parsed[f"kl{d}"][0] == "ppo_kl_penalty.py"
            and args.adaptive_beta
            and args.kl_target == float(d)
            and args.init_beta == 1
        )
    for b in ("0.3", "1", "3", "10"):
        args = parsed[f"beta{b}"][1]
        assert not args.adaptive_beta and args.init_beta == float(b)
    assert set(run.SUITES["table1"].envs) == set(run.MUJOCO) and len(run.MUJOCO) == 7


def test_runner_finishes_skips_and_shares_identical_runs(tmp_path):
    first = runner("mujoco", *TINY_GRID, "--total-timesteps", "4096", tmp_path=tmp_path)
    out = tmp_path / "results" / run.results_folder("mujoco", 4096) / "InvertedPendulum-v5__clip0.2__seed1.csv"
    assert out.exists(), first.stdout
    meta, rows = read_csv(out)
    for key in ("command", "commit", "versions", "machine", "wall_time_s"):
        assert meta[key], key
    assert meta["command"].startswith("python ppo_continuous.py ") and "--total-timesteps 4096" in meta["command"]
    assert int(meta["global_step"]) == 4096 and "torch" in meta["versions"]
    steps = [step for step, _, _ in rows]
    assert len(rows) > 10 and steps == sorted(steps) and steps[-1] <= 4096
    assert all(length > 0 for _, _, length in rows)
    updates = (
        (out.parent / "updates" / out.name).read_text().splitlines()
    )  # the update's statistics, one row per iteration
    assert updates[0] == "global_step,entropy,approx_kl,clipfrac,explained_variance,value_loss"
    assert [int(line.split(",")[0]) for line in updates[1:]] == [2048, 4096]
    assert all(math.isfinite(float(x)) for line in updates[1:] for x in line.split(","))
    content = out.read_bytes()

    again = runner("mujoco", *TINY_GRID, "--total-timesteps", "4096", tmp_path=tmp_path)
    assert "1/1 runs finished, 0 to run" in again.stdout and "start" not in again.stdout
    assert out.read_bytes() == content
    attempts = (
        (
            tmp_path
            / "runs"
            / run.results_folder("mujoco", 4096)
            / "InvertedPendulum-v5__clip0.2__seed1"
            / "attempts.txt"
        )
        .read_text()
        .splitlines()
    )
    assert len(attempts) == 1, "a finished run is not run again"

    # table1's clip0.2 row is the same run: copied, not run again.
    shared = runner("table1", "--variants", "clip0.2", *TINY_GRID, "--total-timesteps", "4096", tmp_path=tmp_path)
    assert "copied" in shared.stdout
    assert (
        tmp_path / "results" / run.results_folder("table1", 4096) / "InvertedPendulum-v5__clip0.2__seed1.csv"
    ).read_bytes() == content
    assert (tmp_path / "results" / run.results_folder("table1", 4096) / "updates" / out.name).read_text() == "\n".join(
        updates
    ) + "\n"
    assert not (tmp_path / "runs" / run.results_folder("table1", 4096)).exists()


def test_a_shared_kl_run_brings_its_beta_series(tmp_path):
    # beta_collapse's kl0.01 runs are table1's: the copy must carry the beta series that the beta plot reads.
    source = tmp_path / "results" / run.results_folder("table1", 4096)
    fake_run(source, "Hopper-v5", "kl0.01", 1, 100.0, steps=4096)
    (source / "beta").mkdir()
    (source / "beta" / "Hopper-v5__kl0.01__seed1.csv").write_text("global_step,beta,kl\n2048,1,0.01\n4096,0.5,0.001\n")
    shared = runner(
        "beta_collapse", "--variants", "kl0.01", "--seeds", "1", "--total-timesteps", "4096", tmp_path=tmp_path
    )
    assert "copied" in shared.stdout and "start" not in shared.stdout
    copy = tmp_path / "results" / run.results_folder("beta_collapse", 4096)
    assert (copy / "Hopper-v5__kl0.01__seed1.csv").read_bytes() == (
        source / "Hopper-v5__kl0.01__seed1.csv"
    ).read_bytes()
    assert (copy / "beta" / "Hopper-v5__kl0.01__seed1.csv").read_text() == (
        source / "beta" / "Hopper-v5__kl0.01__seed1.csv"
    ).read_text()


def tiny_sweep(tmp_path, total, *extra, status_every="1"):
    """The runner's command for one KL run of `total` steps that saves after each iteration, and its run's folder."""
    cmd = [
        sys.executable,
        str(ROOT / "benchmarks" / "run.py"),
        "table1",
        "--variants",
        "kl0.01",
        *TINY_GRID,
        "--total-timesteps",
        str(total),
        "--save-every",
        "1",
        "--results-dir",
        str(tmp_path / "results"),
        "--runs-dir",
        str(tmp_path / "runs"),
        "--status-every",
        status_every,
        *extra,
    ]
    return cmd, tmp_path / "runs" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1"


def interrupt_at_first_checkpoint(tmp_path, total, *extra):
    """Start a sweep of one KL run of `total` steps, SIGTERM the runner once the run has saved a checkpoint,
    and check that it stopped there. Returns the runner's command and the checkpoint's step."""
    cmd, run_dir = tiny_sweep(tmp_path, total, *extra)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGTERM, wait=180)
    assert proc.returncode == 130, (out, err)
    assert "its checkpoint is kept" in out and "Traceback" not in err
    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert 0 < saved["global_step"] < total
    return cmd, saved["global_step"], run_dir


def test_runner_resumes_an_interrupted_run(tmp_path):
    total = 6 * 2048  # six iterations, with a checkpoint after each
    _, saved_step, run_dir = interrupt_at_first_checkpoint(tmp_path, total)
    csv_path = tmp_path / "results" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1.csv"
    assert not csv_path.exists(), "an unfinished run has no CSV"

    resumed = runner(
        "table1",
        "--variants",
        "kl0.01",
        *TINY_GRID,
        "--total-timesteps",
        str(total),
        "--save-every",
        "1",
        tmp_path=tmp_path,
    )
    assert "resume InvertedPendulum-v5__kl0.01__seed1" in resumed.stdout
    assert f"at step {saved_step:,}" in (run_dir / "log.txt").read_text()
    meta, rows = read_csv(csv_path)
    assert int(meta["global_step"]) == total and int(meta["attempts"]) == 2
    assert meta["command"].startswith("python ppo_kl_penalty.py ") and "beta_range" in meta
    beta = (csv_path.parent / "beta" / csv_path.name).read_text().splitlines()
    assert beta[0] == "global_step,beta,kl" and len(beta) - 1 == total // 2048, "beta after each of the run's updates"
    assert [int(line.split(",")[0]) for line in beta[1:]] == list(range(2048, total + 1, 2048))
    updates = (csv_path.parent / "updates" / csv_path.name).read_text().splitlines()
    assert [int(line.split(",")[0]) for line in updates[1:]] == list(range(2048, total + 1, 2048)), (
        "one row per update, across the resume"
    )
    steps = [step for step, _, _ in rows]
    assert steps == sorted(steps), "one curve, without a fold at the resume"
    attempts = [line.split("\t") for line in (run_dir / "attempts.txt").read_text().splitlines()]
    assert [a[4] for a in attempts] == ["start", "resume"] and [a[3] for a in attempts] == ["130", "0"]


def test_a_run_another_runner_finished_meanwhile_is_skipped(tmp_path):
    """Two runners may share a grid (one per core, say): a run whose CSV appeared after this runner listed it is not
    resumed and written again."""
    total = 2048
    folder = run.results_folder("mujoco", total)
    first_dir = tmp_path / "runs" / folder / "InvertedPendulum-v5__clip0.2__seed1"
    second_csv = tmp_path / "results" / folder / "InvertedPendulum-v5__clip0.2__seed2.csv"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "run.py"), "mujoco", "--envs", "InvertedPendulum"]
    cmd += ["--seeds", "1", "2", "--workers", "1", "--total-timesteps", str(total)]
    cmd += ["--results-dir", str(tmp_path / "results"), "--runs-dir", str(tmp_path / "runs")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(600):  # the first run has started: the runner has listed both
            if (first_dir / "pid").exists() or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert proc.poll() is None, "the first run ended before the test could finish the second"
        write_csv(second_csv, [("note", "finished by another runner")], [(1, 1.0, 1)])
        out, err = proc.communicate(timeout=300)
    finally:
        with contextlib.suppress(OSError):
            proc.kill()
    assert proc.returncode == 0, out + err
    assert "skip   InvertedPendulum-v5__clip0.2__seed2: another runner finished it" in out
    assert read_csv(second_csv)[0] == {"note": "finished by another runner"}, "not written again"
    assert not (tmp_path / "runs" / folder / "InvertedPendulum-v5__clip0.2__seed2").exists()


def test_a_runner_killed_outright_loses_no_attempt(tmp_path):
    """SIGKILL (or a machine that shuts down) gives the runner no chance to log the attempt; the next runner logs
    it from the file the killed one kept current, so the run's wall time and commits count it."""
    total = 6 * 2048
    cmd, run_dir = tiny_sweep(tmp_path, total, status_every="0.2")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGKILL, wait=180)
    finally:
        with contextlib.suppress(OSError, ValueError):  # its run dies with it, as on a shutdown
            os.kill(int((run_dir / "pid").read_text()), signal.SIGKILL)
    noted = (run_dir / "attempt.txt").read_text().split("\t")
    assert noted[3] == "running" and noted[4].strip() == "start" and int(noted[2]) >= 1
    assert not (run_dir / "attempts.txt").exists(), "the killed runner logged nothing"
    runner("table1", "--variants", "kl0.01", *TINY_GRID, "--total-timesteps", str(total), tmp_path=tmp_path)
    attempts = [line.split("\t") for line in (run_dir / "attempts.txt").read_text().splitlines()]
    assert [a[3:] for a in attempts] == [["killed", "start"], ["0", "resume"]]
    assert int(attempts[0][2]) >= int(noted[2]) and not (run_dir / "attempt.txt").exists()
    csv_path = tmp_path / "results" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1.csv"
    meta, _ = read_csv(csv_path)
    assert int(meta["attempts"]) == 2 and int(meta["global_step"]) == total
    assert int(meta["wall_time_s"]) == sum(int(a[2]) for a in attempts)


# ---------------------------------------------------------------- the Ray backend, on a local Ray instance


def test_ray_backend_makes_the_same_results_as_the_local_one_and_skips_them_after(tmp_path):
    pytest.importorskip("ray")  # benchmarks/requirements.txt; .ci/run installs it
    grid = ["table1", "--variants", "kl0.01", *TINY_GRID, "--total-timesteps", "2048"]
    runner(*grid, tmp_path=tmp_path / "local")
    first = runner(*grid, "--backend", "ray", tmp_path=tmp_path / "ray")
    assert "done   InvertedPendulum-v5__kl0.01__seed1" in first.stdout and "1/1 runs finished" in first.stdout
    files = {p.relative_to(tmp_path / "ray" / "results") for p in (tmp_path / "ray" / "results").rglob("*.csv")}
    assert files == {
        p.relative_to(tmp_path / "local" / "results") for p in (tmp_path / "local" / "results").rglob("*.csv")
    }
    for path in files:  # the same run, to the episode and to every value of its series: only when, and how long, differ
        local, ray = (tmp_path / backend / "results" / path for backend in ("local", "ray"))
        if path.parent.name in ("beta", "updates"):
            assert local.read_text() == ray.read_text()
            continue
        (meta_l, rows_l), (meta_r, rows_r) = read_csv(local), read_csv(ray)
        assert rows_l == rows_r and meta_l.keys() == meta_r.keys()
        assert meta_l["command"].replace(str(tmp_path / "local"), "") == meta_r["command"].replace(
            str(tmp_path / "ray"), ""
        )
    again = runner(*grid, "--backend", "ray", tmp_path=tmp_path / "ray")
    assert "1/1 runs finished, 0 to run" in again.stdout and "start" not in again.stdout


def test_ray_backend_stops_every_run_at_a_checkpoint_and_resumes(tmp_path):
    pytest.importorskip("ray")
    total = 6 * 2048
    cmd, _, _ = interrupt_at_first_checkpoint(tmp_path, total, "--backend", "ray")
    resumed = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0 and "resume InvertedPendulum-v5__kl0.01__seed1" in resumed.stdout, (
        resumed.stdout + resumed.stderr
    )
    meta, _ = read_csv(
        tmp_path / "results" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1.csv"
    )
    assert int(meta["global_step"]) == total and int(meta["attempts"]) == 2


@pytest.mark.parametrize(
    "args, message",
    [
        (["table1", "--variants", "clip0.25", "--backend", "ray"], "has no variant 'clip0.25'"),
        (
            ["table1", *TINY_GRID, "--backend", "ray", "--ray-address", "127.0.0.1:1"],
            "no Ray cluster answers at --ray-address 127.0.0.1:1",
        ),
    ],
)
def test_ray_backend_rejects_a_bad_grid_or_address_in_one_line(tmp_path, args, message):
    proc = runner(*args, tmp_path=tmp_path, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1 and message in lines[0], proc.stderr
    assert not (tmp_path / "runs").exists(), "nothing may start"


# ---------------------------------------------------------------- the report, on hand-made CSVs


def fake_run(folder, env_id, variant, seed, last100_mean, steps=100_000):
    """A CSV whose last 100 episodes average last100_mean, after 50 early episodes that must not count."""
    returns = [-1e4] * 50 + [last100_mean - 1.0, last100_mean + 1.0] * 50
    rows = [((i + 1) * steps // len(returns), r, 10) for i, r in enumerate(returns)]
    header = [
        ("command", "test"),
        ("env_id", env_id),
        ("seed", seed),
        ("global_step", steps),
        ("commit", "abc1234"),
        ("versions", "test versions"),
        ("machine", "test machine"),
        ("wall_time_s", "60"),
    ]
    write_csv(folder / f"{env_id}__{variant}__seed{seed}.csv", header, rows)


def fake_random(results, env_id, returns):
    path = results / "random" / f"{env_id}.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        f.write("# command: test\n")
        writer = csv.writer(f)
        writer.writerow(["episode", "episodic_return", "episodic_length"])
        writer.writerows((i, r, 1) for i, r in enumerate(returns))


def test_report_normalizes_as_the_paper_does(tmp_path):
    results = tmp_path / "results"
    folder = results / "table1"
    # Env A: random scores 0; clip0.2 scores 10 and 20 (mean 15, the best), no-clip 5.
    # Env B: random scores -10; clip0.2 scores 10, no-clip 30 (the best).
    fake_random(results, "A-v0", [-1.0, 1.0])
    fake_random(results, "B-v0", [-12.0, -8.0])
    fake_run(folder, "A-v0", "clip0.2", 1, 10.0)
    fake_run(folder, "A-v0", "clip0.2", 2, 20.0)
    fake_run(folder, "A-v0", "no-clip", 1, 5.0)
    fake_run(folder, "B-v0", "clip0.2", 1, 10.0)
    fake_run(folder, "B-v0", "no-clip", 1, 30.0)
    # A variant run on env A only does not enter the common set of envs.
    runs = report.load_runs(folder)
    assert sorted(r.score for r in runs) == [5.0, 10.0, 10.0, 20.0, 30.0]
    random = {"A-v0": report.random_score("A-v0", results), "B-v0": report.random_score("B-v0", results)}
    assert random == {"A-v0": 0.0, "B-v0": -10.0}

    norm, envs, best = report.normalized_scores(runs, random)
    assert envs == ["A-v0", "B-v0"] and best == {"A-v0": "clip0.2", "B-v0": "no-clip"}
    clip = ((10 - 0) / (15 - 0) + (20 - 0) / (15 - 0) + (10 + 10) / (30 + 10)) / 3
    noclip = ((5 - 0) / (15 - 0) + (30 + 10) / (30 + 10)) / 2
    assert norm["clip0.2"][0] == pytest.approx(clip) and norm["clip0.2"][1] == 3
    assert norm["no-clip"][0] == pytest.approx(noclip) and norm["no-clip"][1] == 2

    text = report.report(folder, results=results)
    assert f"| clip0.2 | {clip:.2f} | 3 | 0.82 |" in text
    assert f"| no-clip | {noclip:.2f} | 2 | -0.39 |" in text
    assert "| kl0.01 | not run | – | 0.74 |" in text
    assert "15.00 ± 7.07 (2)" in text  # A, clip0.2: mean and sample std of 10 and 20
    assert "Seeds: 1, 2; 5 runs." in text and "abc1234" in text and "test machine" in text
    assert (folder / "report.md").read_text() == text
    for env in ("A-v0", "B-v0"):
        png = folder / "curves" / f"{env}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
        assert f"curves/{env}.png" in text


def test_a_suite_of_changes_is_compared_with_its_default(tmp_path):
    results = tmp_path / "results"
    folder = results / "shortfalls"
    fake_random(results, "Swimmer-v5", [0.0])
    for seed, (default, gamma) in enumerate([(80.0, 110.0), (90.0, 120.0), (100.0, 130.0)], start=1):
        fake_run(folder, "Swimmer-v5", "clip0.2", seed, default)
        fake_run(folder, "Swimmer-v5", "gamma0.999", seed, gamma)
    fake_run(folder, "Swimmer-v5", "const-lr", 1, 95.0)  # one seed: no std, so no difference is claimed
    reference = {("paper_fig3", "Swimmer", "clip0.2"): (110.0, None, "the paper")}
    text = report.report(folder, reference=reference, results=results)
    se = math.sqrt(100 / 3 + 100 / 3)  # both samples have variance 100
    assert f"| Swimmer-v5 | gamma0.999 | 120.0 ± 10.0 (3) | **+30.0 ± {se:.1f}** | yes (110.0) |" in text
    assert "| Swimmer-v5 | clip0.2 | 90.00 ± 10.00 (3) | – | no (110.0) |" in text
    assert "| Swimmer-v5 | const-lr | 95.00 (1) | – | no (110.0) |" in text


def test_atari_report_gives_each_arms_difference_from_the_default(tmp_path):
    results = tmp_path / "results"
    folder = results / "atari"
    scores = {
        "ppo": [10.0, 12.0, 14.0],
        "vf0.5": [20.0, 22.0, 24.0],  # ahead by 10, far beyond 2 standard errors
        "sb3": [9.0, 13.0, 17.0],  # ahead by 1, well within them
    }
    for variant, values in scores.items():
        for seed, value in enumerate(values, start=1):
            fake_run(folder, "A-v0", variant, seed, value)
    fake_run(folder, "A-v0", "default", 1, 30.0)  # one seed: no standard error, so no verdict
    fake_run(folder, "A-v0", "zoo", 1, 25.0)
    text = report.report(folder, reference={}, results=results)
    # The scores, one row per game and setting: both of the paper's metrics, the mean over all of training
    # (fake_run's 50 episodes at -1e4, then the 100 that make the score; in the thousands, so no decimals) and
    # over the last 100 episodes.
    for variant, name in (("ppo", "ours"), ("vf0.5", "ours, --vf-coef 0.5"), ("sb3", "SB3 PPO (RL Zoo)")):
        whole = [(50 * -1e4 + 100 * v) / 150 for v in scores[variant]]
        last = scores[variant]
        row = (
            f"| A-v0 | {name} | {statistics.mean(whole):,.0f} ± {statistics.stdev(whole):,.0f} (3)"
            f" | {statistics.mean(last):.2f} ± {statistics.stdev(last):.2f} (3) |"
            + (" not measured |" if variant == "ppo" else "  |")  # the random policy, on the game's first row only
        )
        assert row in text
    # By hand: ppo's and vf0.5's scores vary by 4 over their 3 seeds, sb3's by 16, so the standard errors of the
    # differences are sqrt(4/3 + 4/3) and sqrt(16/3 + 4/3). Over all of training (fake_run's 50 early episodes at
    # -1e4, then the 100 that make the score), each difference and its error shrink to 100/150 of these.
    se_vf = math.sqrt(4 / 3 + 4 / 3)
    se_sb3 = math.sqrt(16 / 3 + 4 / 3)
    scale = 100 / 150
    d_vf = statistics.mean(scores["vf0.5"]) - statistics.mean(scores["ppo"])
    d_sb3 = statistics.mean(scores["sb3"]) - statistics.mean(scores["ppo"])
    vf = (
        f"**{d_vf:+.1f} ± {se_vf:.1f}** | **{d_vf * scale:+.1f} ± {se_vf * scale:.1f}**"
        " | ahead of ppo by more than 2 standard errors"
    )
    sb3 = f"{d_sb3:+.1f} ± {se_sb3:.1f} | {d_sb3 * scale:+.1f} ± {se_sb3 * scale:.1f} | within 2 standard errors"
    for variant, name in (("vf0.5", "ours, --vf-coef 0.5"), ("sb3", "SB3 PPO (RL Zoo)")):
        cell = f"{statistics.mean(scores[variant]):.2f} ± {statistics.stdev(scores[variant]):.2f} (3)"
        assert f"| A-v0 | {name} | {cell} | {vf if variant == 'vf0.5' else sb3} |" in text
    assert "| A-v0 | ours, before the issue-14 fixes | 30.00 (1) | – | – | fewer than 2 seeds a side |" in text
    behind = [0.0, 2.0, 4.0]  # vf0.5 now behind ppo by 10, with the same spread
    for seed, value in enumerate(behind, start=1):
        fake_run(folder, "A-v0", "vf0.5", seed, value)
    d_vf = statistics.mean(behind) - statistics.mean(scores["ppo"])
    text = report.report(folder, reference={}, results=results)
    assert f"**{d_vf:+.1f} ± {se_vf:.1f}**" in text and "behind ppo by more than 2 standard errors" in text
    # The README's short block: ours at the defaults, with the RL Zoo's settings, and the peer; the single arms and
    # the history only in the full one.
    short = report.readme_block(results=results, reference={})
    zoo = [line for line in short.splitlines() if line.startswith("| A-v0 | ours with the RL Zoo's hyperparameters (")]
    assert len(zoo) == 1 and "| 25.00 (1) |" in zoo[0]  # its last 100 games
    assert "| A-v0 | ours | " in short and "| A-v0 | SB3 PPO (RL Zoo) |" in short
    assert "| A-v0 | ours, --vf-coef 0.5 |" not in short and "issue-14" not in short
    assert "| A-v0 | ours, --vf-coef 0.5 |" in report.readme_block(results=results, reference={}, full=True)


def test_an_older_env_version_is_compared_with_the_default_on_the_newest(tmp_path):
    results = tmp_path / "results"
    folder = results / "shortfalls"
    for seed, (v5, v4) in enumerate([(5000.0, 7000.0), (6000.0, 8000.0), (7000.0, 9000.0)], start=1):
        fake_run(folder, "InvertedDoublePendulum-v5", "clip0.2", seed, v5)
        fake_run(folder, "InvertedDoublePendulum-v4", "clip0.2", seed, v4)
        fake_run(folder, "InvertedDoublePendulum-v5", "const-lr", seed, v5 + 100.0)
    reference = {("paper_fig3", "InvertedDoublePendulum", "clip0.2"): (8000.0, None, "the paper")}
    lines = report.report(folder, reference=reference, results=results).splitlines()
    se = math.sqrt(1e6 / 3 + 1e6 / 3)  # both samples have variance 1000²
    rows = [
        line
        for line in lines
        if line.startswith("| InvertedDoublePendulum") and "reaches" not in line and line.count("|") == 6
    ]
    assert rows == [
        "| InvertedDoublePendulum-v5 | clip0.2 | 6,000 ± 1,000 (3) | – | no (8,000) |",
        f"| InvertedDoublePendulum-v5 | const-lr | 6,100 ± 1,000 (3) | +100.0 ± {se:,.1f} | no (8,000) |",
        # v4's gap is beyond 2 standard errors: in bold
        f"| InvertedDoublePendulum-v4 | clip0.2 | 8,000 ± 1,000 (3) | **+2,000.0 ± {se:,.1f}** | yes (8,000) |",
    ]


@pytest.mark.parametrize("kl003_score, holds", [(80.0, True), (120.0, False)])
def test_table1_verdict_is_computed_from_the_scores(tmp_path, kl003_score, holds):
    results = tmp_path / "results"
    folder = results / "table1"
    fake_random(results, "A-v0", [0.0])
    scores = {v: 50.0 for v in run.SUITES["table1"].variants} | {
        "clip0.2": 100.0,
        "no-clip": 10.0,
        "kl0.03": kl003_score,
    }
    for variant, value in scores.items():
        fake_run(folder, "A-v0", variant, 1, value)
    text = report.report(folder, results=results)
    assert f"**The paper's order {'holds' if holds else 'does not hold'} here, in the mean scores:**" in text
    if holds:  # one seed: no standard errors, so the gaps stand alone
        assert (
            "clip 0.2 is the best of the 11 rows, ahead of kl0.03 by 0.20;"
            " no clipping or penalty is the worst, behind clip0.1 by 0.40;"
            " every adaptive KL row is below clip 0.2: the best, kl0.03 (0.80), is behind it by 0.20."
        ) in text
    else:  # kl0.03 (1.20 on the scale where the best, itself, is 1) beats clip 0.2 (100 / 120)
        assert "clip 0.2 (0.83) is not the best row: kl0.03 is (1.00), ahead by 0.17" in text
        assert "adaptive KL kl0.03 (1.00) is not below clip 0.2 (0.83): it is ahead by 0.17." in text
    assert "±" not in text.split("The paper's order")[1].split("\n")[0]
    assert "| clip0.2 | " + f"{100 / max(100.0, kl003_score):.2f} (1) | abc1234 |" in text, (
        "the per-env breakdown, with its commits"
    )
    assert (
        f"**The paper's order {'holds' if holds else 'does not hold'} here, in the mean scores:**"
        in report.readme_block(results=results)
    ), "README too"
    (folder / "A-v0__beta10__seed1.csv").unlink()
    assert "waits for all 11 rows on every env and seed: 10 of 11 runs are in." in report.report(
        folder, results=results
    )
    fake_run(folder, "A-v0", "beta10", 1, 50.0)
    fake_random(results, "B-v0", [0.0])
    fake_run(folder, "B-v0", "clip0.2", 1, 100.0)  # a second env, on which only clip 0.2 has run: every row has a score
    text = report.report(folder, results=results)  # on A-v0 alone, but the verdict waits for the whole grid
    assert (
        "waits for all 11 rows on every env and seed: 12 of 22 runs are in. Until then the scores are over A-v0,"
        in text
    )
    assert "The paper's order" not in text and "The paper's order" not in report.readme_block(results=results)
    (folder / "B-v0__clip0.2__seed1.csv").unlink()
    fake_run(folder, "A-v0", "clip0.2", 2, 100.0)  # and a second seed, which only clip 0.2 has
    assert "waits for all 11 rows on every env and seed: 12 of 22 runs are in." in report.report(
        folder, results=results
    )


def test_table1_standard_errors_pool_the_seeds_of_each_env(tmp_path):
    results = tmp_path / "results"
    folder = results / "table1"
    scores = {
        ("A-v0", "clip0.2"): [10.0, 20.0],
        ("A-v0", "no-clip"): [4.0, 8.0],
        ("B-v0", "clip0.2"): [10.0, 14.0, 12.0],
        ("B-v0", "no-clip"): [0.0, 30.0, 15.0],
    }
    for (env, variant), values in scores.items():
        for seed, value in enumerate(values, start=1):
            fake_run(folder, env, variant, seed, value)
    fake_run(folder, "A-v0", "kl0.01", 1, 9.0)  # one run on one env: no standard error, and no entry in the common envs
    runs, random = report.load_runs(folder), {"A-v0": 0.0, "B-v0": -15.0}
    norm, envs, best = report.normalized_scores(runs, random)
    assert envs == ["A-v0"] and sorted(report.standard_errors(runs, random, envs, best)) == [
        "clip0.2",
        "no-clip",
    ]  # kl0.01: one run
    runs = [r for r in runs if r.variant != "kl0.01"]
    norm, envs, best = report.normalized_scores(runs, random)
    se = report.standard_errors(runs, random, envs, best)
    # By hand: A's scale is clip0.2's mean, 15 (random 0); B's is 30 (no-clip's mean 15, random -15). The score of a
    # row is the mean of its 5 runs, 2 on A and 3 on B; the variance of that mean is (2 var_A + 3 var_B) / 5².
    var = {
        "clip0.2": (2 * statistics.variance([10 / 15, 20 / 15]) + 3 * statistics.variance([25 / 30, 29 / 30, 27 / 30])),
        "no-clip": (2 * statistics.variance([4 / 15, 8 / 15]) + 3 * statistics.variance([15 / 30, 45 / 30, 30 / 30])),
    }
    assert se == pytest.approx({v: math.sqrt(x) / 5 for v, x in var.items()})


@pytest.mark.parametrize("beta3, within", [([100.0, 120.0], True), ([104.0, 106.0], False)])
def test_table1_verdict_says_when_a_gap_is_within_the_noise(tmp_path, beta3, within):
    results = tmp_path / "results"
    folder = results / "table1"
    fake_random(results, "A-v0", [0.0])
    scores = {v: [50.0, 52.0] for v in run.SUITES["table1"].variants} | {
        "clip0.2": [100.0, 100.0],
        "no-clip": [10.0, 12.0],
        "beta3": beta3,
    }
    for variant, values in scores.items():
        for seed, value in enumerate(values, start=1):
            fake_run(folder, "A-v0", variant, seed, value)
    line = next(
        line for line in report.report(folder, results=results).splitlines() if line.startswith("**The paper's order")
    )
    best = statistics.mean(scores["beta3"])  # beta3 leads, by one seed, and sets the scale
    d = (best - 100.0) / best
    e = statistics.stdev([x / best for x in beta3]) / math.sqrt(
        2
    )  # the gap's error is beta3's: clip 0.2's two seeds agree
    assert f"beta3 is (1.00), ahead by {d:.2f} ± {e:.2f}" + (" (within 2 standard errors);" if within else ";") in line
    assert (
        " ± is the standard error over seeds" in line
        and ("a gap within twice it is one these seeds cannot settle" in line) == within
    )
    assert f"| beta3 | 1.00 ± {e:.2f} | 2 |" in report.report(folder, results=results)


def test_report_uses_only_envs_every_variant_ran(tmp_path):
    results = tmp_path / "results"
    folder = results / "table1"
    for env in ("A-v0", "B-v0"):
        fake_random(results, env, [0.0])
        fake_run(folder, env, "clip0.2", 1, 10.0)
    fake_run(folder, "A-v0", "kl0.01", 1, 20.0)
    norm, envs, _ = report.normalized_scores(report.load_runs(folder), {"A-v0": 0.0, "B-v0": 0.0})
    assert envs == ["A-v0"]
    assert norm == {"clip0.2": (0.5, 1), "kl0.01": (1.0, 1)}


def test_learning_curve_is_the_trailing_100_episode_mean():
    rows = [(10 * (i + 1), float(i), 1) for i in range(250)]
    grid = [5, 10, 995, 1000, 2500, 3000]
    got = report.curve(rows, grid)
    for step, value in zip(grid, got, strict=True):
        finished = [r for s, r, _ in rows if s <= step][-100:]
        if finished:
            assert value == pytest.approx(sum(finished) / len(finished))
        else:
            assert math.isnan(value)


def test_best_window_finds_a_peak_the_score_misses():
    # 300 episodes, episode i ending at step 10 * i: returns of 0, but 10 for episodes 51 to 200. The score is 0.
    rows = [(10 * i, 10.0 if 50 < i <= 200 else 0.0, 1) for i in range(1, 301)]
    assert report.best_window(rows) == (10.0, 1_500)  # the first window of 100 tens: episodes 51 to 150
    assert report.best_window(rows[:40]) == (
        statistics.mean(r[1] for r in rows[:40]),
        400,
    )  # fewer than 100: all of them


def test_quick_start_promises_what_the_default_hopper_runs_did(tmp_path):
    folder = tmp_path / "mujoco"
    assert "no benchmark run" in report.quickstart_block(tmp_path)
    folder.mkdir()
    fake_run(folder, "Hopper-v5", "clip0.2", 1, 3000.0)
    fake_run(folder, "Hopper-v5", "clip0.2", 2, 1000.0)
    fake_run(folder, "Walker2d-v5", "clip0.2", 1, 9999.0)  # another env and another setting do not count
    fake_run(folder, "Hopper-v5", "const-lr", 1, 5000.0)
    line = report.quickstart_block(tmp_path).splitlines()[1]
    assert "took 1–1 min per run" in line and "1,000–3,000 over the last 100 episodes (2 seeds" in line, line


def test_beta_section_reads_each_runs_kl_target_from_its_command(tmp_path):
    """d_targ comes from the run's command (or the script's default), not from the variant's name; a fixed beta is
    left out. The score at 90% of the steps is the mean of the last 100 episodes finished by then."""

    def kl_run(variant, flags, kls):
        steps = 2048 * len(kls)  # 40,960: the 90% mark is step 36,864, when 184 of the 204 episodes have finished
        episodes = [(200 * i, 10.0 if 200 * i <= 0.9 * steps else 0.0, 10) for i in range(1, 205)]
        header = [
            ("command", f"python ppo_kl_penalty.py --env-id Hopper-v5 --seed 1 {flags}".strip()),
            ("global_step", steps),
        ]
        write_csv(tmp_path / f"Hopper-v5__{variant}__seed1.csv", header, episodes)
        (tmp_path / "beta").mkdir(exist_ok=True)
        with open(tmp_path / "beta" / f"Hopper-v5__{variant}__seed1.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["global_step", "beta", "kl"])
            writer.writerows((2048 * (i + 1), 0.5**i, kl) for i, kl in enumerate(kls))

    kl_run("kl0.01", "", [0.02] * 17 + [0.001] * 3)  # the default d_targ, 0.01: the last 3 updates are below 0.01 / 1.5
    kl_run("kl0.01-const-lr", "--no-anneal-lr", [0.001] * 19 + [0.012])  # ends above 0.01 / 1.5
    kl_run("wide", "--kl-target 0.03", [0.015] * 20)  # above 0.01 / 1.5 but below 0.03 / 1.5: all 20 count
    kl_run("beta3", "--init-beta 3 --no-adaptive-beta", [0.001] * 20)
    rows = [line for line in report.beta_section(tmp_path) if line.startswith("| Hopper-v5")]
    early, end = f"{statistics.median(0.5**i for i in range(18)):.3g}", f"{0.5**19:.3g}"
    # At 90% of the steps the last 100 episodes all scored 10; at the end, the last 20 of them scored 0.
    assert rows == [
        f"| Hopper-v5 | kl0.01 | 1 | {early} | {end} | 100% | 3 | 10.00 | 8.00 |",
        f"| Hopper-v5 | kl0.01-const-lr | 1 | {early} | {end} | 50% | 0 | 10.00 | 8.00 |",
        f"| Hopper-v5 | wide | 1 | {early} | {end} | 100% | 20 | 10.00 | 8.00 |",
    ]


def test_updates_section_averages_each_tenth_of_a_run_then_the_seeds(tmp_path):
    (tmp_path / "updates").mkdir()
    for seed, shift in ((1, 0.0), (2, 2.0)):  # 20 updates each: every statistic of update i is i + shift
        fake_run(tmp_path, "Hopper-v5", "clip0.2", seed, 100.0 * seed)
        rows = [[2048 * (i + 1)] + [i + shift] * len(UPDATE_STATS) for i in range(20)]
        write = "\n".join(",".join(map(str, row)) for row in rows)
        (tmp_path / "updates" / f"Hopper-v5__clip0.2__seed{seed}.csv").write_text(
            ",".join(("global_step", *UPDATE_STATS)) + "\n" + write + "\n"
        )
    lines = report.updates_section(tmp_path, ["clip0.2"])
    row = next(line for line in lines if line.startswith("| Hopper-v5 | clip0.2 (2) | explained_variance |"))
    cells = [float(c) for c in row.strip("|").split("|")[3:]]
    # tenth k holds updates 2k and 2k + 1: their mean is 2k + 0.5 for seed 1 and 2k + 2.5 for seed 2
    assert cells == [2 * k + 1.5 for k in range(10)]
    row = next(line for line in lines if line.startswith("| Hopper-v5 | clip0.2 (2) | return |"))
    assert row.endswith("| 150.0 |"), "at the end, the mean over the seeds of their last 100 episodes: (100 + 200) / 2"
    assert report.updates_section(tmp_path / "none", ["clip0.2"]) == []


def test_reference_figures_have_a_source_each():
    reference = report.load_reference()
    assert len(reference) >= 30
    assert all(source.strip() for _, _, source in reference.values())
    assert {s for (c, _, s) in reference if c == "paper_table1"} == set(run.SUITES["table1"].variants)


def test_cost_of_table1_counts_the_runs_not_done(tmp_path):
    results = tmp_path / "results"
    fake_run(results / "mujoco", "Hopper-v5", "clip0.2", 1, 100.0)  # one run of 60 s sets the cost per run
    assert "132 runs, about 2 CPU-hours, of which 132 runs are not done yet (2 CPU-hours)." in report.cost_block(
        results
    )
    jobs = run.make_grid("table1", envs=report.TABLE1_ENVS, results_root=results)
    for job in jobs[1:]:
        fake_run(job.csv.parent, job.env_id, job.variant, job.seed, 1.0)
    assert "of which 1 run is not done yet (0 CPU-hours)." in report.cost_block(results)
    fake_run(jobs[0].csv.parent, jobs[0].env_id, jobs[0].variant, jobs[0].seed, 1.0)
    assert report.cost_block(results).count("all of them done.") == 1


@pytest.mark.parametrize("path,full", [("README.md", False), ("benchmarks/README.md", True)])
def test_readme_results_block_is_generated_from_the_committed_csvs(path, full):
    """The READMEs' Results blocks are what report.py makes from the CSVs in benchmarks/results."""
    readme = (ROOT / path).read_text()
    start, end = readme.index(report.README_START), readme.index(report.README_END) + len(report.README_END)
    assert readme[start:end] == report.readme_block(full=full), "run python benchmarks/report.py"
    if full:  # the cost of Table 1 on a cluster, from the runs' wall times
        start, end = readme.index(report.COST_START), readme.index(report.COST_END) + len(report.COST_END)
        assert readme[start:end] == report.cost_block(), "run python benchmarks/report.py"
    else:  # the quick start's time and score, from the mujoco suite's Hopper runs
        start, end = readme.index(report.QUICK_START), readme.index(report.QUICK_END) + len(report.QUICK_END)
        assert readme[start:end] == report.quickstart_block(), "run python benchmarks/report.py"
        start, end = readme.index(report.RLHF_START), readme.index(report.RLHF_END) + len(report.RLHF_END)
        assert readme[start:end] == report.rlhf_block(), "run python benchmarks/report.py"
    for folder in report.suite_folders():
        assert (folder / "report.md").exists()
        if report.suite_name(folder) == "figure3":  # one figure, a panel per task
            assert (folder / "curves" / "figure3.png").exists()
            continue
        for env in {r.env_id for r in report.load_runs(folder)}:
            assert (folder / "curves" / f"{env}.png").exists(), (folder, env)


def test_throughput_replaces_only_its_own_section(tmp_path):
    import throughput

    path = tmp_path / "throughput.md"
    throughput.write_section(path, "mujoco", "## mujoco\n\n| a | 1 |\n")
    throughput.write_section(path, "atari", "## atari\n\n| b | 2 |\n")
    throughput.write_section(path, "mujoco", "## mujoco\n\n| a | 3 |\n")
    text = path.read_text()
    assert text.startswith("# Throughput") and "| a | 3 |" in text and "| a | 1 |" not in text
    assert "| b | 2 |" in text and text.index("## mujoco") < text.index("## atari")
    assert text.count("<!-- suite: mujoco -->") == 1


def test_the_rlhf_suite_keeps_its_series_and_samples_and_reports_them(tmp_path):
    rlhf = run.load_script("ppo_rlhf.py")
    job = run.make_grid("rlhf", ["beta0.05"], seeds=[1], results_root=tmp_path / "results", runs_root=tmp_path)[0]
    assert "--total-episodes 12800" in " ".join(job.command()) and "--env-id" not in job.command()
    # A tiny run in the job's folder, as if the runner had made it, with the log the runner keeps.
    tiny = dict(d_model=16, n_layer=1, n_head=2, response_length=16, sft_steps=60, sft_learning_rate=0.01, rm_pairs=128)
    tiny |= dict(rm_epochs=1, rm_batch_size=32, total_episodes=64, batch_size=16, minibatch_size=8, torch_threads=1)
    rlhf.train(rlhf.Args(**tiny, run_dir=str(job.run_dir)))
    (job.run_dir / "log.txt").write_text(
        "stage 3, PPO: iteration 4/4\n  score +1.00 | gold  +2 | the film was good <eos>\n"
    )
    run.finish(job)
    series = (job.results_dir / "rlhf" / f"{job.name}.csv").read_text().splitlines()
    assert series[0] == "global_step," + ",".join(RLHF_STATS) and len(series) == 1 + 4
    best = ["# wall_time_s: 60", ",".join(report.BEST_OF_N), "1,0,0.1,1.5,1,0,0,0.9", "4,0.636,0.9,3.25,0.5,0.5,0,nan"]
    (job.results_dir / "best_of_n").mkdir()
    (job.results_dir / "best_of_n" / "seed1.csv").write_text("\n".join(best) + "\n")
    text = report.report(job.results_dir)
    assert "| beta0.05 | " in text and "the film was good" in text and "| beta0.05 | 1 | " in text
    assert "## Best-of-N from pi_SFT (seeds 1)" in text and "1.0 min in all" in text
    assert "| 4 | 0.64 (1) | 0.90 (1) | 3.25 (1) | 0.50 (1) | 0.50 (1) | 0.00 (1) | – |" in text
    assert (job.results_dir / "curves" / "reviews.png").exists()


def test_the_readmes_rlhf_block_finds_gold_falling_while_the_score_holds(tmp_path):
    """rlhf_block counts a seed as over-optimized when its gold score ends more than 10% below its peak while the KL
    grows past its value there and the RM score ends at least as high (Gao et al. 2022), and no other; gives the
    controller's final KL beside its target, and the default runs' wall time; names each fall's hack by the larger of
    the spam and garbled shares at the end; and gives best-of-N's last point."""
    folder = tmp_path / "rlhf"
    rise = [i / 99 for i in range(100)]  # 0 to 1 over 100 iterations
    fall = [1 - r for r in rise]
    falls_late = [min(r, 1.2 - r) for r in rise]  # peaks at 0.6 and ends at 0.2
    dips = [min(r, 0.8) - 0.25 * max(0.0, r - 0.8) for r in rise]  # flat at 0.8, then 5% below it at the end
    shapes = {  # (RM score, gold, KL) of each run
        ("beta0", 1): (rise, falls_late, rise),  # over-optimized
        ("beta0", 2): (rise, rise, rise),  # gold kept rising
        ("beta0", 3): (falls_late, falls_late, rise),  # gold fell with the score
        ("beta0", 4): (rise, falls_late, fall),  # gold fell as the KL fell: the controller pulling back, not this
        ("beta0", 5): (rise, dips, rise),  # gold fell, but by less than 10%
        ("beta0", 6): (rise, falls_late, rise),  # over-optimized, onto garbled text
        ("adaptive", 1): (rise, rise, [2.1] * 100),
        ("adaptive", 2): (rise, rise, [2.2] * 100),
        ("beta0.05", 1): (rise, rise, rise),
    }
    for (variant, seed), (score, gold, kl) in shapes.items():
        fake_run(folder, "reviews", variant, seed, 1.0, steps=12_800)
        rows = []
        for i in range(100):
            stats = {"score": score[i], "gold_score": gold[i], "kl": kl[i], "kl_coef": 0.1 * seed}
            stats |= {"spam": rise[i] if seed == 1 else 0.0, "garbled": rise[i] / 2 if seed == 6 else 0.0}
            rows.append([(i + 1) * 128] + [stats.get(name, 0.5) for name in RLHF_STATS])
        write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
    (folder / "best_of_n").mkdir()
    best = ["# commit: abc", ",".join(report.BEST_OF_N), "1,0,0.1,1.5,1,0,0,0.9", "4,0.636,0.9,3.25,1,0,0,0.8"]
    (folder / "best_of_n" / "seed1.csv").write_text("\n".join(best) + "\n")
    block = report.rlhf_block(tmp_path)
    # the last tenth: the mean of rise over iterations 90 to 99, 0.95, and half of it
    assert "beta0 2 of 6 (seed 1: gold 0.6 to 0.2 as KL grew 0.6 to 1.0; spam 0.95; seed 6: gold" in block
    assert "as KL grew 0.6 to 1.0; garbled 0.48)" in block and report.BLIND_SPOT in block
    assert (
        "reached gold 3.25 at N = 4 (KL 0.64 nats, analytic; 1.50 at N = 1), with the reward models of seeds 1."
        in block
    )
    assert "adaptive 0 of 2" in block and "beta0.05 0 of 1" in block
    assert "held the KL over the last tenth of training at 2.15 ± 0.07 nats, for a target of 2" in block
    assert "took 1.0–1.0 min for all three stages, with torch's threads on test machine (1 run;" in block
    assert block.startswith(report.RLHF_START) and block.endswith(report.RLHF_END)
    # Tenths count from the end, so that the last is the last tenth of the iterations, as report.md's table takes it.
    series = np.arange(25.0)[:, None].repeat(1 + len(RLHF_STATS), axis=1)
    assert report.tenths(series, "score")[-1] == (23 + 24) / 2


def test_the_committed_figure3_report_is_what_report_py_makes_of_the_csvs(tmp_path):
    """benchmarks/results/figure3/report.md is generated: stale after a CSV lands until report.py runs again."""
    folder = report.RESULTS / "figure3"
    if not any(report.run_files(folder)):
        pytest.skip("no figure3 run is committed yet")
    copy = tmp_path / "figure3"
    copy.mkdir()
    for _, _, _, path in report.run_files(folder):
        (copy / path.name).write_bytes(path.read_bytes())
    assert (folder / "report.md").read_text() == report.figure3_markdown(copy), "run python benchmarks/report.py"


def test_figure3_counts_tasks_where_ppo_leads_trails_or_ties_each_peer(tmp_path):
    results = tmp_path / "results"
    for seed, noise in [(1, -1.0), (2, 0.0), (3, 1.0)]:
        fake_run(results / "mujoco", "Hopper-v5", "clip0.2", seed, 1000 + 10 * noise)
        fake_run(results / "mujoco", "Swimmer-v5", "clip0.2", seed, 50 + 10 * noise)
        fake_run(results / "mujoco", "Reacher-v5", "clip0.2", seed, -5 + noise)
        fake_run(results / "figure3", "Hopper-v5", "a2c", seed, 500 + 10 * noise)  # PPO ahead, far beyond 2 SE
        fake_run(results / "figure3", "Swimmer-v5", "a2c", seed, 100 + 10 * noise)  # PPO behind
        fake_run(results / "figure3", "Reacher-v5", "a2c", seed, -5.5 + noise)  # within: 0.5 apart, SE 0.8
    fake_run(results / "figure3", "Hopper-v5", "trpo", 1, 900)  # one seed: not comparable
    text = report.figure3_markdown(results / "figure3", results)
    line = next(line for line in text.splitlines() if line.startswith("**Over the last 100 episodes"))
    assert "against A2C (SB3), PPO is ahead on 1 (Hopper); behind on 1 (Swimmer); within 2 standard errors on 1" in line
    assert "against TRPO (sb3-contrib), PPO is not comparable yet on 3 (Hopper, Reacher, Swimmer)" in line
    assert "| Hopper-v5 | A2C (SB3) | 500.0 ± 10.0 (3) |" in text
    assert (results / "figure3" / "curves" / "figure3.png").exists()
    short = report.figure3_verdict(report.figure3_runs(results / "figure3", results), names=False)  # the README's
    assert short == (
        "over the last 100 episodes of 3 tasks, against A2C (SB3), PPO is ahead on 1, behind on 1, within 2 standard"
        " errors on 1; against TRPO (sb3-contrib), PPO is not comparable yet on 3."
    )


def test_sb3_mujoco_reads_the_rl_zoos_entry_for_the_task():
    pytest.importorskip("rl_zoo3")
    sb3 = run.load_script("benchmarks/sb3_mujoco.py")
    params, source = sb3.hyperparameters("trpo", "HalfCheetah-v5")
    assert source == "rl_zoo3 hyperparams/trpo.yml, entry HalfCheetah-v4" and params["normalize"] is True
    assert params["target_kl"] == 0.04 and params["n_envs"] == 2  # the task's own entry, over the shared defaults
    params, source = sb3.hyperparameters("a2c", "Reacher-v5")
    assert source.endswith("entry default (the Zoo has no entry for this task: SB3's defaults)")
    assert "normalize" not in params and params["policy"] == "MlpPolicy"


def test_humanoid_report_has_both_metrics_the_published_figures_and_the_video(tmp_path):
    folder = tmp_path / "results" / "humanoid"
    fake_run(folder, "Humanoid-v5", "table4", 1, 1000.0)
    fake_run(folder, "Humanoid-v5", "table4", 2, 3000.0)
    (folder / "video").mkdir()
    (folder / "video" / "Humanoid-v5__table4__seed1.mp4").write_bytes(b"")
    text = report.report(folder, results=tmp_path / "results")
    # last 100: 1,000 and 3,000; all training: (50 x -10,000 + 100 x score) / 150 = -2,666.7 and -1,333.3
    assert "| Humanoid-v5 | table4 | 100,000 | 2,000 ± 1,414 (2) | -2,000 ± 943 (2) |" in text
    assert "- CleanRL 1M (-v4; 1 env, Table 3's settings): 716.1 ± 49.1" in text
    assert "[video/Humanoid-v5__table4__seed1.mp4](video/Humanoid-v5__table4__seed1.mp4)" in text
    assert (folder / "curves" / "Humanoid-v5.png").exists()


def test_film_records_the_runs_policy_and_a_frame_of_it(tmp_path, tiny_run):
    import film
    import imageio.v3 as iio

    (job,) = run.make_grid("mujoco", envs=["Hopper"], seeds=[1], runs_root=tmp_path / "runs")
    job.run_dir.mkdir(parents=True)
    with pytest.raises(ValueError, match="has no checkpoint"):
        film.film(job, tmp_path / "video")
    torch.save(torch.load(tiny_run("ppo_continuous.py")[0] / "checkpoint.pt", weights_only=True), job.checkpoint)
    video, line = film.film(job, tmp_path / "video")
    assert video == tmp_path / "video" / "Hopper-v5__clip0.2__seed1.mp4" and line.startswith("eval Hopper-v5 step ")
    frame = iio.imread(video.with_suffix(".png"))
    assert frame.ndim == 3 and frame.std() > 0, "a frame of the film, not a blank"
    assert not list(job.run_dir.glob("videos-eval")), "the run's own folder is left as it was"


def test_throughput_humanoid_case_measures_ours_sb3_and_the_envs_with_table4(capsys):
    import throughput

    flags = throughput.SUITES["humanoid"]["flags"]
    assert "--num-envs 32 --num-steps 512 --update-epochs 15 --minibatch-size 4096" in flags
    # Table 4 on a tiny rollout (the case's flags come after the suite's): 3 iterations of 32 x 8 steps
    sps, first = throughput.measure_ours(
        "ppo_continuous.py --num-steps 8 --minibatch-size 128", "Humanoid-v5", 768, flags
    )
    assert sps > 0 and first > 0
    throughput.run_worker("env", "Humanoid-v5", 64, "humanoid")  # the 32 envs of ppo_continuous.py, alone
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["sps"] > 0
    pytest.importorskip("stable_baselines3")  # benchmarks/requirements.txt; CI installs only ray from it
    tiny = dict(n_envs=32, n_steps=8, batch_size=128, n_epochs=1)
    sps, first = throughput.measure_sb3_ppo_mujoco("Humanoid-v5", 768, threads=1, **tiny)
    assert sps > 0 and first > 0


def test_best_of_n_keeps_the_rm_favourite_of_n_with_its_analytic_kl(tmp_path):
    import best_of_n

    assert best_of_n.analytic_kl(1) == 0 and best_of_n.analytic_kl(4) == pytest.approx(math.log(4) - 0.75)
    rlhf_tiny = (
        "--d-model 16 --n-layer 1 --n-head 2 --response-length 16 --sft-steps 60 --sft-learning-rate 0.01"
        " --rm-pairs 128 --rm-epochs 1 --rm-batch-size 32 --total-episodes 16 --batch-size 16 --minibatch-size 8"
    ).split()
    cmd = [sys.executable, str(ROOT / "ppo_rlhf.py"), *rlhf_tiny, "--torch-threads", "1", "--run-dir", "run"]
    subprocess.run(cmd, cwd=tmp_path, check=True, capture_output=True, timeout=300)
    rows = best_of_n.best_of_n(tmp_path / "run", prompts=16, ns=[1, 2, 8])
    assert [row[0] for row in rows] == [1, 2, 8] and [row[1] for row in rows] == [
        best_of_n.analytic_kl(n) for n in (1, 2, 8)
    ]
    scores = [row[2] for row in rows]
    assert scores[0] <= scores[1] <= scores[2], "the best of more responses (nested: the first N) scores no lower"
    assert all(row[4] + row[5] + row[6] == pytest.approx(1.0) for row in rows), "each kept response has one form"
    assert all(math.isnan(row[7]) or 0 <= row[7] <= 1 for row in rows), "the RM's accuracy on the kept responses"
