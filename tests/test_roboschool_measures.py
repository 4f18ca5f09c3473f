"""benchmarks/roboschool_measures.py: the falls, knock-downs, get-ups, flags and speed toward the flag that the
roboschool report prints, counted on scripted episodes whose answers are worked out by hand below."""

import sys

import numpy as np
import pytest
from conftest import ROOT, fake_run

gym = pytest.importorskip("gymnasium")
sys.path.insert(0, str(ROOT / "benchmarks"))
import roboschool_measures as measures  # noqa: E402

DT = 0.0165  # seconds a step in roboschool_humanoid.py


class Scripted(gym.Env):
    """An env that plays back one episode: per step the torso's height, the cubes thrown so far, the distance to the
    flag, whether the flag moved, and the flags reached so far, with reward 1 a step; the episode ends with the list."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, start_z, steps):
        self.start_z, self.steps = start_z, steps

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([self.start_z - 0.8], np.float32), {}  # as the rules' state starts: the torso's height - 0.8

    def step(self, action):
        z, cubes, distance, moved, flags = self.steps[self.t]
        self.t += 1
        info = dict(torso_z=z, cubes_thrown=cubes, distance_to_target=distance, flag_moved=moved, flags_reached=flags)
        return np.zeros(1, np.float32), 1.0, self.t == len(self.steps), False, info


@pytest.fixture
def scripted(monkeypatch):
    """play() on a Scripted env made from (start_z, steps), in place of a checkpoint's env and policy."""

    def play(start_z, steps, episodes=1):
        env_id = f"ScriptedMeasures{len(steps)}-v0"
        gym.register(env_id, entry_point=lambda: Scripted(start_z, steps))
        monkeypatch.setattr(measures, "policy", lambda checkpoint: (env_id, lambda obs: np.zeros(1), 4096))
        try:
            return measures.play("unused.pt", episodes)
        finally:
            del gym.registry[env_id]

    return play


def test_falls_knockdowns_getups_and_the_speed_toward_the_flag(scripted):
    # 41 steps, standing at 1.2 m: a cube at step 2; down (0.5 m) at steps 3-4, a knock-down 1 step after the throw; up
    # at step 5, a get-up 2 steps after the fall; down again from step 40 on, 38 steps after the throw: a fall, not a
    # knock-down, and no get-up before the end. The flag is 10 m away and comes 0.1 m closer each step; it moves at step
    # 20 (to 12 m away, a step that counts no speed), and the run reaches 1 flag by the end.
    steps = []
    distance = 10.0
    for t in range(1, 42):
        z = 0.5 if t in (3, 4) or t >= 40 else 1.2
        distance = 12.0 if t == 20 else distance - 0.1
        steps.append((z, int(t >= 2), distance, t == 20, int(t >= 30)))
    (row,) = scripted(1.2, steps)
    assert row["falls"] == 2 and row["knockdowns"] == 1
    assert row["getups"] == 1 and row["getup_steps"] == 2
    assert row["started_down"] == 0 and row["cubes"] == 1 and row["flags"] == 1
    assert row["length"] == 41 and row["return"] == 41.0 and row["seed"] == 1
    assert row["step"] == 4096, "the checkpoint's step, which the report reads for a midway checkpoint"
    # Speeds are counted from step 2 on, but for step 20: 39 steps of 0.1 m each.
    assert row["speed_to_flag"] == pytest.approx(0.1 / DT)
    assert measures.DT == DT


def test_a_start_on_the_ground_counts_its_get_up_from_step_0_and_no_fall(scripted):
    steps = [(0.3, 0, 5.0, False, 0)] * 6 + [(1.0, 0, 5.0, False, 0)] * 4  # up at step 7
    rows = scripted(0.3, steps, episodes=2)
    assert [row["seed"] for row in rows] == [1, 2]
    for row in rows:
        assert row["started_down"] == 1 and row["falls"] == 0 and row["knockdowns"] == 0
        assert row["getups"] == 1 and row["getup_steps"] == 7 and row["speed_to_flag"] == 0.0


def test_a_fall_with_no_cube_thrown_is_no_knock_down_and_an_episode_with_no_get_up_has_no_get_up_time(scripted):
    steps = [(1.2, 0, 5.0, False, 0)] * 2 + [(0.5, 0, 5.0, False, 0)]
    (row,) = scripted(1.2, steps)
    assert row["falls"] == 1 and row["knockdowns"] == 0 and row["getups"] == 0 and row["getup_steps"] == ""
    assert "got up 0/1 times" in measures.summary([row])


def test_a_checkpoint_kept_midway_is_measured_beside_the_last_into_a_folder_named_by_its_label(tmp_path, monkeypatch):
    """run.py keeps checkpoint_50M.pt in a 100M run's folder: the measures play it too, into measures/50M/, and the last
    checkpoint into measures/ as before."""
    (job,) = measures.make_grid(
        "roboschool-body", ["table4-128"], ["HumanoidFlagrun"], [1], None, tmp_path / "r", tmp_path
    )
    job.run_dir.mkdir(parents=True)
    for name in ["checkpoint.pt", "checkpoint_50M.pt"]:
        (job.run_dir / name).write_text(name)
    job.csv.parent.mkdir(parents=True)
    job.csv.write_text("finished")  # measured only once finished
    played = []

    def play(path, episodes):
        played.append(path.name)
        return [dict.fromkeys(measures.FIELDS, 0) | dict(seed=1, step=len(path.read_text()), getup_steps="")]

    monkeypatch.setattr(measures, "play", play)
    monkeypatch.setattr(measures, "make_grid", lambda suite, total_timesteps: [job])
    monkeypatch.setattr(sys, "argv", ["roboschool_measures.py", "--suite", "roboschool-body", "--episodes", "1"])
    measures.main()
    assert sorted(played) == ["checkpoint.pt", "checkpoint_50M.pt"]
    midway = (job.results_dir / "measures" / "50M" / f"{job.name}.csv").read_text().splitlines()
    last = (job.results_dir / "measures" / f"{job.name}.csv").read_text().splitlines()
    assert midway[1].endswith(f",{len('checkpoint_50M.pt')}") and last[1].endswith(f",{len('checkpoint.pt')}")


def test_film_films_the_checkpoint_kept_midway_into_a_folder_named_by_its_label_and_the_report_shows_both(
    tmp_path, monkeypatch
):
    """With --film, checkpoint_50M.pt is filmed into video/50M/ as the last checkpoint is into video/, each on its own
    measured episodes; the report's film table and its videos list the midway film just before the last."""
    import report

    (job,) = measures.make_grid(
        "roboschool-bullet", ["table4-128"], ["HumanoidFlagrunHarder"], [1], None, tmp_path / "r", tmp_path
    )
    job.run_dir.mkdir(parents=True)
    for name in ["checkpoint.pt", "checkpoint_50M.pt"]:
        (job.run_dir / name).write_text(name)
    fake_run(job.results_dir, "HumanoidFlagrunHarder-v0", "table4-128", 1, 1700.0)
    filmed = []

    def play(path, episodes):
        return [dict.fromkeys(measures.FIELDS, 0) | dict(seed=len(path.name), step=50_000, getup_steps="")]

    def film(path, rows, video):
        filmed.append((path.name, rows[0]["seed"], video.relative_to(job.results_dir).as_posix()))
        video.parent.mkdir(parents=True, exist_ok=True)
        video.write_bytes(b"")
        video.with_suffix(".png").write_bytes(b"")
        flag = "1,1" if path.name == "checkpoint.pt" else "2,1"  # flag within 8 m, and seen
        video.with_suffix(".csv").write_text(",".join(measures.FILM_FIELDS) + f"\n10,0.3,0.2,{flag},0,0\n")
        return rows[0]["seed"]

    monkeypatch.setattr(measures, "play", play)
    monkeypatch.setattr(measures, "film", film)
    monkeypatch.setattr(measures, "make_grid", lambda suite, total_timesteps: [job])
    monkeypatch.setattr(sys, "argv", ["roboschool_measures.py", "--suite", "roboschool-bullet", "--film"])
    measures.main()
    name = job.name
    assert filmed == [
        ("checkpoint_50M.pt", len("checkpoint_50M.pt"), f"video/50M/{name}.mp4"),
        ("checkpoint.pt", len("checkpoint.pt"), f"video/{name}.mp4"),
    ]
    text = report.report(job.results_dir, results=tmp_path / "r")
    row = "| HumanoidFlagrunHarder-v0, table4-128, seed1"
    films = text.split("## What the films show", 1)[1].split("\n\n", 3)[2].splitlines()[2:]
    assert films == [
        row + ", at 50M | 10 | 0.30 (0.20) | 1 of 2 | 0 of 0 |",
        row + " | 10 | 0.30 (0.20) | 1 of 1 | 0 of 0 |",
    ]
    videos = text.split("## The trained policy", 1)[1]
    assert videos.index(f"[video/50M/{name}.mp4](video/50M/{name}.mp4): {name.replace('__', ', ')}, at 50M") < (
        videos.index(f"[video/{name}.mp4](video/{name}.mp4)")
    )
    assert f"(video/50M/{name}.png)](video/50M/{name}.mp4)" in videos
