"""Film a finished run's trained policy for its suite's report: one evaluation episode of the deterministic policy,
through the script's own --eval-checkpoint --capture-video (with the model's tracking camera), and a frame of it.

    python benchmarks/film.py humanoid                       # seed 1 of each of the suite's envs and variants
    python benchmarks/film.py humanoid --seed 2

The video and the frame go to benchmarks/results/<suite>/video/<env>__<variant>__seed<N>.mp4 and .png, where
report.py shows them; the episode's return is printed, as the script prints it.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from run import make_grid  # noqa: E402


def film(job, video_dir, frame_at=0.5):
    """Evaluate the run's checkpoint for one filmed episode; copy the video to video_dir and save the frame that is
    `frame_at` of the way through it. Returns (the video's path, the line the script printed)."""
    import imageio.v3 as iio

    if not job.checkpoint.exists():
        raise ValueError(f"{job.name} has no checkpoint at {job.checkpoint}: run the suite first")
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "run" / "checkpoint.pt"  # evaluation films into the checkpoint's folder: a copy's
        copy.parent.mkdir()
        shutil.copyfile(job.checkpoint, copy)
        cmd = [sys.executable, job.script, "--eval-checkpoint", str(copy), "--capture-video", "--eval-episodes", "1"]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800)
        if proc.returncode != 0:
            raise ValueError(f"{job.name}: evaluation failed:\n{proc.stderr[-2000:]}")
        (source,) = (copy.parent / "videos-eval").glob("*.mp4")
        video_dir.mkdir(parents=True, exist_ok=True)
        video = video_dir / f"{job.name}.mp4"
        shutil.copyfile(source, video)
    n_frames = sum(1 for _ in iio.imiter(video))  # streamed: the container does not say
    iio.imwrite(video.with_suffix(".png"), iio.imread(video, index=int(frame_at * (n_frames - 1))))
    return video, proc.stdout.strip().splitlines()[-1]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("suite")
    parser.add_argument("--seed", type=int, default=1, help="the seed whose run is filmed (default: 1)")
    args = parser.parse_args()
    try:
        jobs = make_grid(args.suite, seeds=[args.seed])
        for job in jobs:
            video, line = film(job, job.results_dir / "video")
            print(f"{video.relative_to(ROOT)}: {line}")
    except ValueError as e:
        sys.exit(f"film.py: error: {e}")


if __name__ == "__main__":
    main()
