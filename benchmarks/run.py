"""Run a benchmark suite: a grid of (script, variant, env, seed) training runs that never loses work.

    python benchmarks/run.py mujoco                     # the paper's 7 tasks, 1M steps, 3 seeds
    python benchmarks/run.py table1 --variants no-clip clip0.2 kl0.01 --envs Hopper Swimmer
    python benchmarks/run.py table1 --list              # print the grid and what is done, run nothing
    python benchmarks/run.py table1 --backend ray --ray-address HEAD:6379   # each run a Ray task, on a cluster

Each run is its own process (`python ppo_*.py ... --torch-threads 1 --run-dir ...`), up to
--workers at a time. A finished run becomes one CSV, benchmarks/results/<suite>/<env>__<variant>__seed<N>.csv:
a header of '# key: value' lines (the command, commit, package versions, machine, wall time), then
one row per episode. Run the same command again and it skips every run that has its CSV, resumes
every unfinished run from its checkpoint in benchmarks/runs/ (the scripts save one every
--save-every iterations, and on SIGTERM or Ctrl-C), and starts the rest. So a suite can be built
up over several sessions, and an interrupted sweep loses at most one save interval per run. Each
process a run takes is a line of its attempts.txt (when, commit, seconds, exit); the CSV's wall time
is their sum. A runner killed outright still has its attempt logged, up to its last status line.

A run with the same script, flags, env, seed and budget as a finished run of another suite is
not run twice: its CSV is copied (table1's clip0.2 row is the mujoco suite).
"""

from __future__ import annotations

import argparse
import io
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import load_script  # noqa: E402
from results import RESULTS, commit, copy_run, machine, read_run, score, versions, write_run  # noqa: E402
from suites import SUITES  # noqa: E402

# The packages whose versions every run's CSV records; a script adds its own as RESULTS_PACKAGES.
PACKAGES = ("torch", "numpy", "gymnasium", "mujoco", "ale-py")


@dataclass
class Job:
    suite: str
    variant: str
    script: str
    flags: list[str]
    env_id: str
    seed: int
    total_timesteps: int
    results_dir: Path
    runs_dir: Path
    progress: int = field(default=0, compare=False)
    env_flag: str | None = "--env-id"
    budget_flag: str = "--total-timesteps"
    ranks: int = 1  # processes of one run: more than 1 runs it under torchrun

    @property
    def launcher(self):
        """How the run's command starts: python, or torchrun with one process a rank on this machine."""
        return ["python"] if self.ranks == 1 else ["torchrun", "--standalone", f"--nproc-per-node={self.ranks}"]

    @property
    def name(self):
        return f"{self.env_id.split(':')[-1]}__{self.variant}__seed{self.seed}"  # a module:id, named by its id

    @property
    def csv(self):
        return self.results_dir / f"{self.name}.csv"

    @property
    def run_dir(self):
        return self.runs_dir / self.name

    @property
    def checkpoint(self):
        return self.run_dir / "checkpoint.pt"

    @property
    def identity(self):
        """What makes two runs the same run, wherever their results are kept: the same command on the same rules."""
        rules = SUITES[self.suite].rules
        return (self.script, tuple(self.flags), self.env_id, self.seed, self.total_timesteps, self.ranks, rules)

    def command(self, save_every=None):
        """The command that starts this run from scratch, relative to the repository root."""
        return [
            *self.launcher,
            self.script,
            *self.flags,
            *([self.env_flag, self.env_id] if self.env_flag else []),
            "--seed",
            str(self.seed),
            self.budget_flag,
            str(self.total_timesteps),
            "--torch-threads",
            "1",
            *(["--save-every", str(save_every)] if save_every else []),
            "--run-dir",
            str(_rel(self.run_dir)),
        ]


def _rel(path):
    path = Path(path).resolve()
    return path.relative_to(ROOT) if path.is_relative_to(ROOT) else path


def results_folder(suite, total_timesteps, variant=None):
    """results/<suite>/ at the suite's own budget (or the variant's own, in budgets); results/<suite>_<budget>/ else."""
    if total_timesteps == SUITES[suite].budget(variant):
        return suite
    return f"{suite}_{total_timesteps // 1000}k" if total_timesteps % 1000 == 0 else f"{suite}_{total_timesteps}"


def resolve_env(name, known):
    """'Hopper' or 'Hopper-v5' -> 'Hopper-v5' from the suite's list; any other id is taken as given."""
    ids = {env: env.split(":")[-1] for env in known}  # a module:id by its id alone, too
    matches = [env for env, id in ids.items() if name in (env, id, id.split("-v")[0], id.split("NoFrameskip")[0])]
    return matches[0] if matches else name


def make_grid(suite, variants=None, envs=None, seeds=None, total_timesteps=None, results_root=None, runs_root=None):
    """The suite's jobs, or the subset asked for. Raises ValueError on an unknown suite or variant."""
    if suite not in SUITES:
        raise ValueError(f"unknown suite {suite!r}; the suites are {', '.join(SUITES)}")
    spec = SUITES[suite]
    for variant in variants or []:
        if variant not in spec.variants:
            raise ValueError(f"suite {suite} has no variant {variant!r}; its variants are {', '.join(spec.variants)}")
    results_root, runs_root = Path(results_root or RESULTS), Path(runs_root or ROOT / "benchmarks" / "runs")

    def budget(variant):  # a variant's budget, and the folders of its results and its runs
        total = total_timesteps or spec.budget(variant)
        folder = results_folder(suite, total, variant)
        return total, results_root / folder, runs_root / folder

    return [
        Job(
            suite,
            variant,
            *spec.variants[variant],
            resolve_env(env, spec.envs),
            seed,
            *budget(variant),
            env_flag=spec.env_flag,
            budget_flag=spec.budget_flag,
            ranks=spec.ranks.get(variant, 1),
        )
        for variant in (variants or spec.variants)
        for env in (envs or spec.envs)
        for seed in (seeds or spec.seeds)
        if variant not in spec.only
        or (resolve_env(env, spec.envs) in spec.only[variant][0] and seed in spec.only[variant][1])
    ]


def check_grid(jobs):
    """Parse every distinct command with its script's own parser and argument checks, so that an
    unknown env or a flag the script lacks stops the sweep before any run starts."""
    import tyro

    seen = set()
    for job in jobs:
        key = (job.script, tuple(job.flags), job.env_id)
        if key in seen:
            continue
        seen.add(key)
        module = load_script(job.script)
        # Without --run-dir: a run's folder is the runner's, which resumes what it holds.
        argv = job.command()[len(job.launcher) + 1 : -2]
        try:
            args = tyro.cli(module.Args, args=argv, console_outputs=False)
        except SystemExit:
            raise ValueError(
                f"{job.script} does not accept the flags {shlex.join(job.flags)} (variant {job.variant})"
            ) from None
        try:
            module.check_args(args)
        except ValueError as e:
            raise ValueError(f"{job.script} rejects {job.name}: {e}") from None


def find_equivalent(job, results_root):
    """A finished CSV of the same run in another suite's results, if there is one."""
    for suite in SUITES:
        for other in make_grid(suite, total_timesteps=job.total_timesteps, results_root=results_root):
            if other.identity == job.identity and other.csv != job.csv and other.csv.exists():
                return other.csv
    return None


def commit_of(script):
    """The commit the script is at, marked when the script differs from it."""
    return commit([script], " (script modified)")


def attempt_line(started, commit, elapsed, returncode, resumed):
    return (
        f"{time.strftime('%Y-%m-%dT%H:%M:%S', time.gmtime(started))}\t{commit}\t{elapsed:.0f}\t{returncode}"
        f"\t{'resume' if resumed else 'start'}\n"
    )


def log_attempt(job, started, commit, elapsed, returncode, resumed):
    """One line per process a run took: when, at which commit, how long, and how it ended."""
    with open(job.run_dir / "attempts.txt", "a") as f:
        f.write(attempt_line(started, commit, elapsed, returncode, resumed))
    (job.run_dir / "attempt.txt").unlink(missing_ok=True)


def note_attempt(job, started, commit, resumed):
    """The attempt under way, rewritten with each status line: a runner killed outright (SIGKILL, or a machine
    that shuts down) cannot log it, and the next runner logs it from this file as 'killed'."""
    path = job.run_dir / "attempt.txt"
    path.with_suffix(".tmp").write_text(attempt_line(started, commit, time.time() - started, "running", resumed))
    path.with_suffix(".tmp").replace(path)


def recover_attempt(job):
    """Log the attempt a killed runner left in attempt.txt, up to its last status line."""
    path = job.run_dir / "attempt.txt"
    if path.exists():
        fields = path.read_text().rstrip("\n").split("\t")
        fields[3] = "killed"
        with open(job.run_dir / "attempts.txt", "a") as f:
            f.write("\t".join(fields) + "\n")
        path.unlink()


def read_attempts(job):
    path = job.run_dir / "attempts.txt"
    if not path.exists():
        return []
    return [line.rstrip("\n").split("\t") for line in path.read_text().splitlines() if line.strip()]


def finish(job):
    """Turn a finished run directory into its results folder's files (results.write_run); returns its score. What the
    run logged decides which series it has; a script may add packages (RESULTS_PACKAGES) and header lines
    (results_header(flags, env_id)) of its own."""
    logs = read_run(job.run_dir)
    attempts = read_attempts(job)
    commits = sorted({a[1] for a in attempts}) or ["unknown"]  # every attempt may have added steps
    wall = sum(float(a[2]) for a in attempts)
    script = load_script(job.script)
    header = [
        ("command", shlex.join(job.command())),
        ("suite", job.suite),
        ("variant", job.variant),
        ("script", job.script),
        ("env_id", job.env_id),
        ("seed", job.seed),
        ("global_step", logs.global_step),
        ("commit", ", ".join(commits)),
        ("machine", machine()),
        ("versions", versions((*PACKAGES, *getattr(script, "RESULTS_PACKAGES", ())))),
        *(script.results_header(job.flags, job.env_id) if hasattr(script, "results_header") else []),
        ("wall_time_s", f"{wall:.0f}"),
        ("attempts", len(attempts)),
    ]
    write_run(job.results_dir, job.name, header, logs)
    return score(logs.rows)


def running_elsewhere(job):
    """The pid of a live process that is training this run (say, left by a runner that was killed)."""
    try:
        pid = int((job.run_dir / "pid").read_text())
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except (OSError, ValueError):
        return None
    return pid if job.script in cmdline and str(job.run_dir.name) in cmdline else None


def last_step(job):
    """The latest step a running job printed, from its log (the scripts print one every 10 s or so). The tail read is
    long enough to reach past a failed attempt's traceback (two ranks' tracebacks under torchrun run to several KB)."""
    try:
        with open(job.run_dir / "log.txt", "rb") as f:
            f.seek(max(0, os.path.getsize(f.name) - 65536))
            tail = f.read().decode(errors="replace")
    except OSError:
        return 0
    # The last "step N/" (the gym scripts), or "iteration I/M" (ppo_rlhf.py's stage 3, I/M of the budget in steps)
    marks = re.findall(r"(step|iteration)\s+([\d,]+)/([\d,]+)", tail)
    if not marks:
        return 0
    kind, done, total = marks[-1][0], *(int(x.replace(",", "")) for x in marks[-1][1:])
    return done if kind == "step" else done * job.total_timesteps // total


def fmt_time(seconds):
    seconds = int(seconds)
    return (
        f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"
    )


def start_process(cmd, root, log, run_dir):
    """Start a run's command in a session of its own, logging to `log`, and note its pid in the run's folder."""
    python = [sys.executable, "-m", "torch.distributed.run"] if cmd[0] == "torchrun" else [sys.executable]
    proc = subprocess.Popen(
        [*python, *cmd[1:]],
        cwd=root,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"},
    )
    (Path(run_dir) / "pid").write_text(str(proc.pid))
    return proc


def keep_checkpoints(job, seen):
    """Copy aside, as checkpoint_<label>.pt, the first checkpoint a run saves at or past each mark of its suite's
    keep_checkpoints short of its budget, so that a long run's policy midway can be measured later. `seen`: each save
    is read once."""
    marks = {job.run_dir / f"checkpoint_{k}.pt": v for k, v in SUITES[job.suite].keep_checkpoints.items()}
    todo = {path: mark for path, mark in marks.items() if mark < job.total_timesteps and not path.exists()}
    mtime = job.checkpoint.stat().st_mtime_ns if todo and job.checkpoint.exists() else None
    if mtime is not None and seen.get(job.name) != mtime:
        import torch

        seen[job.name], data = mtime, job.checkpoint.read_bytes()  # one read: the script replaces the file atomically
        step = torch.load(io.BytesIO(data), weights_only=True)["global_step"]
        for path in [path for path, mark in todo.items() if step >= mark]:
            path.with_suffix(".tmp").write_bytes(data)
            os.replace(path.with_suffix(".tmp"), path)


def launch_local(job, cmd, log):
    """Start a run as a subprocess of this runner."""
    return start_process(cmd, ROOT, log, job.run_dir)


def ray_run(cmd, root, log_path, run_dir):
    """A Ray task: run one training command on whichever node Ray picked, in the same repository path,
    logging to the run's folder, until it ends or the runner asks it to stop (a file, 'stop', in the
    run's folder: a Ray task cannot be sent SIGTERM, and its process must save its checkpoint)."""
    stop_file = Path(run_dir) / "stop"
    with open(log_path, "a") as log:
        proc = start_process(cmd, root, log, run_dir)
        while proc.poll() is None:
            if stop_file.exists():
                proc.terminate()  # the script saves its checkpoint and exits 130
                proc.wait()
            time.sleep(0.5)
    stop_file.unlink(missing_ok=True)
    return proc.returncode


class RayRun:
    """A run as a Ray task, with the part of Popen's interface that run_grid uses: poll() and terminate()."""

    def __init__(self, job, cmd, log):
        import ray

        log.close()  # the task writes the log itself, on its node
        self.job, self.returncode = job, None
        (job.run_dir / "stop").unlink(missing_ok=True)
        cuda = any(flag.startswith("cuda") for flag in job.flags)  # the run asks for a GPU with --device cuda
        task = ray.remote(num_cpus=job.ranks, num_gpus=job.ranks if cuda else 0, max_retries=0)(ray_run)
        self.ref = task.remote(cmd, str(ROOT), str(job.run_dir / "log.txt"), str(job.run_dir))

    def poll(self):
        import ray

        if self.returncode is None and ray.wait([self.ref], timeout=0)[0]:
            try:
                self.returncode = ray.get(self.ref)
            except Exception as e:  # the task itself failed (its node died, say): a failed run, by name
                print(f"{self.job.name}: its Ray task failed: {type(e).__name__}", flush=True)
                self.returncode = 1
        return self.returncode

    def terminate(self):
        (self.job.run_dir / "stop").write_text("")


def start_ray(address, workers):
    """Join the Ray cluster at `address`, or start a local Ray instance with `workers` CPUs. Raises
    ValueError, with one line, when the address does not answer."""
    import socket

    if address:
        host, _, port = address.removeprefix("ray://").rpartition(":")
        try:
            socket.create_connection((host, int(port)), timeout=5).close()
        except (OSError, ValueError):
            raise ValueError(
                f"no Ray cluster answers at --ray-address {address} (start one with `ray start --head`)"
            ) from None
    import ray

    ray.init(
        address=address or None,
        num_cpus=None if address else workers,
        include_dashboard=False,
        log_to_driver=False,
        configure_logging=False,
    )


def run_grid(jobs, workers, save_every=None, status_every=60.0, results_root=None, launch=launch_local):
    """Run what is not finished, `workers` at a time. Returns the number of runs that failed."""
    todo, done = [], 0
    for job in jobs:
        if job.csv.exists():
            done += 1
            continue
        source = find_equivalent(job, results_root)
        if source is not None:
            copy_run(source, job.results_dir, job.name)  # the CSV and the series that go with it
            print(f"{job.name}: the same run is finished in {_rel(source)}; copied", flush=True)
            done += 1
            continue
        todo.append(job)
    total = len(jobs)
    print(f"{done}/{total} runs finished, {len(todo)} to run on {workers} workers", flush=True)
    if not todo:
        return 0

    running, failed = {}, 0
    start = time.time()
    steps_at_start, seen = {}, {}
    signals = []  # the handler only notes the signal; the loop below stops the runs, once
    previous = {
        sig: signal.signal(sig, lambda signum, frame: signals.append(signum)) for sig in (signal.SIGTERM, signal.SIGINT)
    }
    stopping, last_status = False, 0.0
    try:
        while (todo and not signals) or running:
            if signals and not stopping:
                stopping = True
                print("stopping: each run saves its checkpoint", flush=True)
                for proc in running:  # each script saves its checkpoint on SIGTERM and exits
                    proc.terminate()
            while todo and len(running) < workers and not signals:
                job = todo.pop(0)
                if job.csv.exists():  # finished meanwhile by another runner
                    print(f"skip   {job.name}: another runner finished it", flush=True)
                    continue
                other = running_elsewhere(job)
                if other:
                    print(f"skip   {job.name}: another process (pid {other}) is running it", flush=True)
                    continue
                job.run_dir.mkdir(parents=True, exist_ok=True)
                recover_attempt(job)
                resumed = job.checkpoint.exists()
                cmd = job.command(save_every)
                if resumed:  # the run's own hyperparameters come back from its checkpoint
                    cmd = [
                        *job.launcher,
                        job.script,
                        "--resume",
                        str(_rel(job.checkpoint)),
                        "--torch-threads",
                        "1",
                        *(["--save-every", str(save_every)] if save_every else []),
                    ]
                log = open(job.run_dir / "log.txt", "a")
                log.write(f"$ {shlex.join(cmd)}\n")
                log.flush()
                # A session of its own: Ctrl-C in the terminal reaches only this runner, which then
                # stops each run exactly once, so that no second signal cuts a checkpoint save short.
                proc = launch(job, cmd, log)
                started, commit = time.time(), commit_of(job.script)
                running[proc] = (job, started, commit, resumed, log)
                note_attempt(job, started, commit, resumed)
                job.progress = steps_at_start[job.name] = last_step(job) if resumed else 0
                print(
                    f"{'resume' if resumed else 'start '} {job.name}"
                    + (f" at step {job.progress:,}" if resumed else ""),
                    flush=True,
                )
            time.sleep(0.2)
            for job, *_ in running.values():
                keep_checkpoints(job, seen)
            for proc in [p for p in running if p.poll() is not None]:
                job, started, commit, resumed, log = running.pop(proc)
                log.close()
                log_attempt(job, started, commit, time.time() - started, proc.returncode, resumed)
                if proc.returncode == 0:
                    try:
                        result = finish(job)
                    except Exception as e:  # say which run, and keep the others going
                        failed += 1
                        print(f"FAILED {job.name}: its results could not be read: {e!r}", flush=True)
                        continue
                    done += 1
                    job.progress = job.total_timesteps
                    print(f"done   {job.name}: score {result:.1f} ({done}/{total})", flush=True)
                elif stopping:
                    print(f"stopped {job.name}: its checkpoint is kept; run the same command to resume", flush=True)
                else:
                    failed += 1
                    print(
                        f"FAILED {job.name} (exit {proc.returncode}); see {_rel(job.run_dir / 'log.txt')}", flush=True
                    )
            if time.time() - last_status > status_every and running:
                last_status = time.time()
                for job, started, commit, resumed, _ in running.values():
                    job.progress = max(job.progress, last_step(job))
                    note_attempt(job, started, commit, resumed)
                print(status_line(jobs, done, total, running, todo, steps_at_start, start), flush=True)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return failed


def status_line(jobs, done, total, running, todo, steps_at_start, start):
    """Runs done/total and an ETA from the steps this sweep has made so far."""
    made = sum(job.progress - steps_at_start.get(job.name, 0) for job in jobs if job.name in steps_at_start)
    left = sum(job.total_timesteps - job.progress for job, *_ in running.values()) + sum(
        job.total_timesteps for job in todo
    )
    elapsed = time.time() - start
    eta = fmt_time(left / (made / elapsed)) if made > 0 else "?"
    now = ", ".join(f"{job.name} {job.progress / job.total_timesteps:.0%}" for job, *_ in running.values())
    return f"[{fmt_time(elapsed)}] {done}/{total} runs done | running: {now} | ETA {eta}"


def main():
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        epilog="suites: " + "; ".join(f"{k}: {v.about} (variants: {', '.join(v.variants)})" for k, v in SUITES.items()),
    )
    parser.add_argument("suite", help=f"one of: {', '.join(SUITES)}")
    parser.add_argument("--variants", nargs="+", help="a subset of the suite's variants (default: all)")
    parser.add_argument("--envs", nargs="+", help="a subset of envs, e.g. Hopper Swimmer (default: the suite's)")
    parser.add_argument("--seeds", nargs="+", type=int, help="default: the suite's (1 2 3 for the MuJoCo suites)")
    parser.add_argument(
        "--total-timesteps", type=int, help="another budget, for every run; its results go to results/<suite>_<budget>/"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count(),
        help="runs at once, each on one torch thread (default: the number of cores)",
    )
    parser.add_argument("--save-every", type=int, help="checkpoint every N iterations (default: the script's)")
    parser.add_argument("--results-dir", type=Path, help="default: benchmarks/results")
    parser.add_argument(
        "--runs-dir", type=Path, help="where run directories and checkpoints live (default: benchmarks/runs)"
    )
    parser.add_argument("--status-every", type=float, default=60.0, help="seconds between progress lines")
    parser.add_argument("--list", action="store_true", help="print the grid and what is finished, and run nothing")
    parser.add_argument(
        "--backend",
        choices=["local", "ray"],
        default="local",
        help="local: subprocesses of this runner; ray: one Ray task a run, on a local Ray instance or --ray-address",
    )
    parser.add_argument(
        "--ray-address", help="a Ray cluster to join, such as 10.0.0.1:6379 (default: start a local instance)"
    )
    args = parser.parse_args()
    try:
        if args.workers <= 0:
            raise ValueError(f"--workers must be positive, got {args.workers}")
        if args.total_timesteps is not None and args.total_timesteps <= 0:
            raise ValueError(f"--total-timesteps must be positive, got {args.total_timesteps}")
        jobs = make_grid(
            args.suite, args.variants, args.envs, args.seeds, args.total_timesteps, args.results_dir, args.runs_dir
        )
        check_grid(jobs)
    except ValueError as e:
        sys.exit(f"run.py: error: {e}")
    if args.list:
        for job in jobs:
            state = "finished" if job.csv.exists() else ("checkpoint" if job.checkpoint.exists() else "not started")
            print(f"{job.name:50s} {state:12s} {shlex.join(job.command())}")
        return
    if args.backend == "ray" and not all(job.csv.exists() for job in jobs):  # Ray starts only when there is a run to do
        try:
            start_ray(args.ray_address, args.workers)
        except ValueError as e:
            sys.exit(f"run.py: error: {e}")
    # On Ray, as many runs at once as the cluster has CPUs (a run asks for one); locally, --workers.
    workers = int(sys.modules["ray"].cluster_resources().get("CPU", 1)) if "ray" in sys.modules else args.workers
    launch = RayRun if args.backend == "ray" else launch_local
    failed = run_grid(jobs, workers, args.save_every, args.status_every, args.results_dir, launch)
    finished = sum(job.csv.exists() for job in jobs)
    print(f"{finished}/{len(jobs)} runs finished" + (f", {failed} failed" if failed else ""))
    if failed:
        sys.exit(1)
    if finished < len(jobs):
        sys.exit(130)


if __name__ == "__main__":
    main()
