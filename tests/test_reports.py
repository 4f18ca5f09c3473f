"""benchmarks/report.py and benchmarks/reports/: each suite's report and the README blocks, on hand-made CSVs, and the
arithmetic of the paper's (Table 1's normalized score, its verdict, the differences and their standard errors)."""

import csv
import math
import statistics
import subprocess
import sys
import types

import numpy as np
import pytest
from conftest import ROOT, fake_random, fake_run, load_script

sys.path.insert(0, str(ROOT / "benchmarks"))
import report  # noqa: E402

from reports import base, figure3, mujoco, rlhf, rlhf_series, table1, training  # noqa: E402
from results import (  # noqa: E402
    BEST_OF_N,
    RESULTS,
    RLHF_STATS,
    UPDATE_STATS,
    load_reference,
    load_runs,
    random_score,
    run_files,
    write_csv,
    write_series,
)
from run import check_grid, make_grid  # noqa: E402
from suites import SUITES, TABLE1_ENVS, Suite  # noqa: E402


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
    runs = load_runs(folder)
    assert sorted(r.score for r in runs) == [5.0, 10.0, 10.0, 20.0, 30.0]
    random = {"A-v0": random_score("A-v0", results), "B-v0": random_score("B-v0", results)}
    assert random == {"A-v0": 0.0, "B-v0": -10.0}

    norm, envs, best = table1.normalized_scores(runs, random)
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
    default = "ours at 13a1a4a (L^VF halved, before the paper's c1 = 1 and fixed value clip)"
    assert f"| A-v0 | {default} | 30.00 (1) | – | – | fewer than 2 seeds a side |" in text
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
    assert "| A-v0 | ours, --vf-coef 0.5 |" not in short and "13a1a4a" not in short
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
    scores = {v: 50.0 for v in SUITES["table1"].variants} | {
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
    runs, random = load_runs(folder), {"A-v0": 0.0, "B-v0": -15.0}
    norm, envs, best = table1.normalized_scores(runs, random)
    assert envs == ["A-v0"] and sorted(table1.standard_errors(runs, random, envs, best)) == [
        "clip0.2",
        "no-clip",
    ]  # kl0.01: one run
    runs = [r for r in runs if r.variant != "kl0.01"]
    norm, envs, best = table1.normalized_scores(runs, random)
    se = table1.standard_errors(runs, random, envs, best)
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
    scores = {v: [50.0, 52.0] for v in SUITES["table1"].variants} | {
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
    norm, envs, _ = table1.normalized_scores(load_runs(folder), {"A-v0": 0.0, "B-v0": 0.0})
    assert envs == ["A-v0"]
    assert norm == {"clip0.2": (0.5, 1), "kl0.01": (1.0, 1)}


def test_learning_curve_is_the_trailing_100_episode_mean():
    rows = [(10 * (i + 1), float(i), 1) for i in range(250)]
    grid = [5, 10, 995, 1000, 2500, 3000]
    got = base.curve(rows, grid)
    for step, value in zip(grid, got, strict=True):
        finished = [r for s, r, _ in rows if s <= step][-100:]
        if finished:
            assert value == pytest.approx(sum(finished) / len(finished))
        else:
            assert math.isnan(value)


def test_best_window_finds_a_peak_the_score_misses():
    # 300 episodes, episode i ending at step 10 * i: returns of 0, but 10 for episodes 51 to 200. The score is 0.
    rows = [(10 * i, 10.0 if 50 < i <= 200 else 0.0, 1) for i in range(1, 301)]
    assert base.best_window(rows) == (10.0, 1_500)  # the first window of 100 tens: episodes 51 to 150
    assert base.best_window(rows[:40]) == (
        statistics.mean(r[1] for r in rows[:40]),
        400,
    )  # fewer than 100: all of them


def test_quick_start_promises_what_the_default_hopper_runs_did(tmp_path):
    folder = tmp_path / "mujoco"
    assert "no benchmark run" in mujoco.quickstart_block(tmp_path)
    folder.mkdir()
    fake_run(folder, "Hopper-v5", "clip0.2", 1, 3000.0)
    fake_run(folder, "Hopper-v5", "clip0.2", 2, 1000.0)
    fake_run(folder, "Walker2d-v5", "clip0.2", 1, 9999.0)  # another env and another setting do not count
    fake_run(folder, "Hopper-v5", "const-lr", 1, 5000.0)
    line = mujoco.quickstart_block(tmp_path).splitlines()[1]
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
    rows = [line for line in training.beta_section(tmp_path) if line.startswith("| Hopper-v5")]
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
    lines = training.updates_section(tmp_path, ["clip0.2"])
    row = next(line for line in lines if line.startswith("| Hopper-v5 | clip0.2 (2) | explained_variance |"))
    cells = [float(c) for c in row.strip("|").split("|")[3:]]
    # tenth k holds updates 2k and 2k + 1: their mean is 2k + 0.5 for seed 1 and 2k + 2.5 for seed 2
    assert cells == [2 * k + 1.5 for k in range(10)]
    row = next(line for line in lines if line.startswith("| Hopper-v5 | clip0.2 (2) | return |"))
    assert row.endswith("| 150.0 |"), "at the end, the mean over the seeds of their last 100 episodes: (100 + 200) / 2"
    assert training.updates_section(tmp_path / "none", ["clip0.2"]) == []


def test_every_committed_run_csv_names_its_own_variant_and_seed():
    """A run's CSV header says which arm ran: a reader, or a tool that groups runs by the header's variant, must not
    mix two arms. A CSV renamed to another variant (the ensembles whose members shared one head were renamed
    -same-head when seeded heads became the default) must say so in its header too."""
    from results import read_csv

    runs = [(variant, seed, path) for p in RESULTS.iterdir() if p.is_dir() for _, variant, seed, path in run_files(p)]
    assert len(runs) > 100
    for variant, seed, path in runs:
        header, _ = read_csv(path)
        assert header.get("variant", variant) == variant, (path, header["variant"])
        assert int(header.get("seed", seed)) == seed, (path, header["seed"])


def test_reference_figures_have_a_source_each():
    reference = load_reference()
    assert len(reference) >= 30
    assert all(source.strip() for _, _, source in reference.values())
    assert {s for (c, _, s) in reference if c == "paper_table1"} == set(SUITES["table1"].variants)


def test_cost_of_table1_counts_the_runs_not_done(tmp_path):
    results = tmp_path / "results"
    fake_run(results / "mujoco", "Hopper-v5", "clip0.2", 1, 100.0)  # one run of 60 s sets the cost per run
    assert "132 runs, about 2 CPU-hours, of which 132 runs are not done yet (2 CPU-hours)." in table1.cost_block(
        results
    )
    jobs = make_grid("table1", envs=TABLE1_ENVS, results_root=results)
    for job in jobs[1:]:
        fake_run(job.csv.parent, job.env_id, job.variant, job.seed, 1.0)
    assert "of which 1 run is not done yet (0 CPU-hours)." in table1.cost_block(results)
    fake_run(jobs[0].csv.parent, jobs[0].env_id, jobs[0].variant, jobs[0].seed, 1.0)
    assert table1.cost_block(results).count("all of them done.") == 1


@pytest.mark.parametrize("path,full", [("README.md", False), ("benchmarks/README.md", True)])
def test_readme_results_block_is_generated_from_the_committed_csvs(path, full):
    """The READMEs' Results blocks are what report.py makes from the CSVs in benchmarks/results."""
    readme = (ROOT / path).read_text()
    start, end = readme.index(report.README_START), readme.index(report.README_END) + len(report.README_END)
    assert readme[start:end] == report.readme_block(full=full), "run python benchmarks/report.py"
    if full:  # the cost of Table 1 on a cluster, from the runs' wall times, and the RLHF suite's findings
        start, end = readme.index(table1.COST_START), readme.index(table1.COST_END) + len(table1.COST_END)
        assert readme[start:end] == table1.cost_block(), "run python benchmarks/report.py"
        start, end = readme.index(rlhf.RLHF_START), readme.index(rlhf.RLHF_END) + len(rlhf.RLHF_END)
        assert readme[start:end] == rlhf.rlhf_block(), "run python benchmarks/report.py"
    else:  # the quick start's time and score, from the mujoco suite's Hopper runs
        start, end = readme.index(mujoco.QUICK_START), readme.index(mujoco.QUICK_END) + len(mujoco.QUICK_END)
        assert readme[start:end] == mujoco.quickstart_block(), "run python benchmarks/report.py"
    for folder in report.suite_folders():
        assert (folder / "report.md").exists()
        if base.suite_name(folder) == "figure3":  # one figure, a panel per task
            assert (folder / "curves" / "figure3.png").exists()
            continue
        if base.suite_name(folder).startswith("rlhf"):  # a panel per seed; the arms' means are the rlhf-long figure
            assert (folder / "curves" / "seeds.png").exists()
            continue
        for env in {r.env_id for r in load_runs(folder)}:
            assert (folder / "curves" / f"{env}.png").exists(), (folder, env)


def test_the_rlhf_report_gives_ktos_reference_point_from_its_series(tmp_path):
    """A --kto run's kto/ series (z0, and the mismatched pairs' mean implied reward that it clamps) becomes its row of
    the report's section on KTO's reference point: z0's range, how many iterations had z0 > 0, and the mean reward
    over the first and last tenth with its range. A run without the series has no row."""
    folder = tmp_path / "rlhf"
    for variant in ("kto0.1", "dpo0.1"):
        fake_run(folder, "reviews", variant, 1, 1.0, steps=12_800, meta=[("rm_held_out_accuracy", "0.9")])
        rows = [[(i + 1) * 128] + [0.5 + i / 100 for _ in RLHF_STATS] for i in range(100)]
        write_series(folder / "rlhf" / f"reviews__{variant}__seed1.csv", RLHF_STATS, rows)
    mismatched = [-i / 100 for i in range(100)]  # 0 to -0.99: z0 is 0 throughout but where a minibatch was above 0
    z0 = [0.02 if i in (3, 7) else 0.0 for i in range(100)]
    rows = [[(i + 1) * 128, z0[i], mismatched[i]] for i in range(100)]
    write_series(folder / "kto" / "reviews__kto0.1__seed1.csv", ("kto_z0", "kto_mismatched_reward"), rows)
    text = report.report(folder, results=tmp_path)
    assert "## KTO's reference point" in text
    # first tenth: the mean of 0 ... -0.09; last tenth: of -0.90 ... -0.99
    assert "| kto0.1 | 1 | 0.0000, 0.0200 | 2 of 100 | -0.045, -0.945, -0.990, 0.000 |" in text
    assert "| dpo0.1 | 1 | 0.0000" not in text


def test_the_readmes_rlhf_block_finds_gold_falling_while_the_score_holds(tmp_path):
    """rlhf_block counts a seed as over-optimized when its gold score rose to its peak and fell from it, each past the
    noise between tenths and by at least rlhf_series.MIN_FALL, while neither the KL nor the RM score fell past their
    noise (Gao et al. 2022), and no other: not a fall within the noise between tenths, nor one from the first tenth,
    nor one with the score or the KL falling too; gives the
    controller's final KL beside its target, and the default runs' wall time; names each fall's hack by the larger of
    the spam and garbled shares at the end; and gives best-of-N's last point."""
    folder = tmp_path / "rlhf"
    rise = [i / 99 for i in range(100)]  # 0 to 1 over 100 iterations
    fall = [1 - r for r in rise]
    falls_late = [min(r, 1.2 - r) for r in rise]  # peaks at 0.6 and ends at 0.2
    gold_falls = [10 * g for g in falls_late]  # peaks at 6 and ends at 2: a fall of gold points
    # gold_falls with each tenth 3 above or below by turns: noise between tenths several times the fall
    noisy = [g + 3 * (-1) ** (i // 10) for i, g in enumerate(gold_falls)]
    shapes = {  # (RM score, gold, KL) of each run
        ("beta0", 1): (rise, gold_falls, rise),  # over-optimized
        ("beta0", 2): (rise, rise, rise),  # gold kept rising
        ("beta0", 3): (falls_late, gold_falls, rise),  # gold fell with the score
        ("beta0", 4): (rise, gold_falls, fall),  # gold fell as the KL fell: the controller pulling back, not this
        ("beta0", 5): (rise, noisy, rise),  # gold fell, but by less than the noise between its tenths
        ("beta0", 7): (rise, [10 * f for f in fall], rise),  # gold fell from the first tenth: it never rose
        ("beta0", 6): (rise, gold_falls, rise),  # over-optimized, onto garbled text
        ("dpo0.1", 1): (falls_late, gold_falls, rise),  # as beta0's seed 3; but DPO never sees the RM: over-optimized
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
    best = ["# commit: abc", ",".join(BEST_OF_N), "1,0,0.1,1.5,1,0,0,0.9", "4,0.636,0.9,3.25,1,0,0,0.8"]
    (folder / "best_of_n" / "seed1.csv").write_text("\n".join(best) + "\n")
    block = rlhf.rlhf_block(tmp_path)
    # the last tenth: the mean of rise over iterations 90 to 99, 0.95, and half of it
    assert "beta0 2 of 7 (seed 1: gold " in block and "; spam 0.95; seed 6: gold " in block
    assert "; garbled 0.48)" in block and rlhf.BLIND_SPOT in block
    assert (
        "reached gold 3.25 at N = 4 (KL at most 0.64 nats; 1.50 at N = 1), with the reward models of seeds 1." in block
    )
    assert "adaptive 0 of 2" in block and "beta0.05 0 of 1" in block
    assert "dpo0.1 1 of 1 (seed 1: gold " in block and "; spam 0.95). A seed is over-optimized where" in block
    assert "held the KL over the last tenth of training at 2.15 ± 0.07 nats, for a target of 2" in block
    assert "took 1.0–1.0 min for all three stages, with torch's threads on test machine (1 run;" in block
    assert block.startswith(rlhf.RLHF_START) and block.endswith(rlhf.RLHF_END)
    # Tenths count from the end, so that the last is the last tenth of the iterations, as report.md's table takes it.
    series = np.arange(25.0)[:, None].repeat(1 + len(RLHF_STATS), axis=1)
    assert rlhf_series.tenths(series, "score")[-1] == (23 + 24) / 2


def test_the_committed_figure3_report_is_what_report_py_makes_of_the_csvs(tmp_path):
    """benchmarks/results/figure3/report.md is generated: stale after a CSV lands until report.py runs again."""
    folder = RESULTS / "figure3"
    if not any(run_files(folder)):
        pytest.skip("no figure3 run is committed yet")
    copy = tmp_path / "figure3"
    copy.mkdir()
    for _, _, _, path in run_files(folder):
        (copy / path.name).write_bytes(path.read_bytes())
    assert (folder / "report.md").read_text() == figure3.figure3_markdown(copy), "run python benchmarks/report.py"


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
    text = figure3.figure3_markdown(results / "figure3", results)
    line = next(line for line in text.splitlines() if line.startswith("**Over the last 100 episodes"))
    assert "against A2C (SB3), PPO is ahead on 1 (Hopper); behind on 1 (Swimmer); within 2 standard errors on 1" in line
    assert "against TRPO (sb3-contrib), PPO is not comparable yet on 3 (Hopper, Reacher, Swimmer)" in line
    assert "| Hopper-v5 | A2C (SB3) | 500.0 ± 10.0 (3) |" in text
    assert (results / "figure3" / "curves" / "figure3.png").exists()
    short = figure3.figure3_verdict(figure3.figure3_runs(results / "figure3", results), names=False)  # the README's
    assert short == (
        "over the last 100 episodes of 3 tasks, against A2C (SB3), PPO is ahead on 1, behind on 1, within 2 standard"
        " errors on 1; against TRPO (sb3-contrib), PPO is not comparable yet on 3."
    )


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


def test_roboschool_report_and_readme_give_scores_beside_figure_4_and_what_the_policies_do(tmp_path):
    """The report's scores beside Figure 4's end points and its measures table; README.md's line of words
    with the flags reached and the get-ups, over the runs' episodes."""
    import roboschool_measures

    results = tmp_path / "results"
    folder = results / "roboschool-bullet"  # the suite that README.md summarizes
    fake_run(folder, "HumanoidFlagrunHarder-v0", "table4-128", 1, 1000.0)
    fake_run(folder, "HumanoidFlagrunHarder-v0", "table4-128", 2, 3000.0)
    zero = dict.fromkeys(roboschool_measures.FIELDS, 0)
    for seed, episodes in [(1, [dict(flags=1, falls=2, getups=1, getup_steps=40)]), (2, [dict(started_down=1)] * 3)]:
        rows = [zero | {"seed": i + 1, "length": 100, "getup_steps": ""} | e for i, e in enumerate(episodes)]
        roboschool_measures.write(folder / "measures" / f"HumanoidFlagrunHarder-v0__table4-128__seed{seed}.csv", rows)
    # Flagrun: a fall ends its episode, so it has falls and no get-ups (3 of these 4 episodes fell, one of them twice
    # in the counts, as a dip below 0.8 m and back above Flagrun's 0.78 m end would count)
    fake_run(folder, "HumanoidFlagrun-v0", "table4-128", 1, 2000.0)
    episodes = [dict(flags=2, falls=1), dict(flags=1), dict(falls=2), dict(flags=3, falls=1)]
    rows = [zero | {"seed": i + 1, "length": 100, "getup_steps": ""} | e for i, e in enumerate(episodes)]
    roboschool_measures.write(folder / "measures" / "HumanoidFlagrun-v0__table4-128__seed1.csv", rows)
    # the forward walk: no flags and no cubes, so neither is counted (0 would read as none reached, none thrown)
    fake_run(folder, "HumanoidForward-v0", "table4", 1, 4000.0)
    rows = [
        zero | {"seed": i + 1, "length": 100, "getup_steps": "", "speed_to_flag": 3} | e
        for i, e in enumerate([dict(falls=1), dict()])
    ]
    roboschool_measures.write(folder / "measures" / "HumanoidForward-v0__table4__seed1.csv", rows)
    text = report.report(folder, results=results)
    # last 100: 1,000 and 3,000; all training: (50 x -10,000 + 100 x score) / 150 = -2,666.7 and -1,333.3
    row = "| HumanoidFlagrunHarder-v0 | table4-128 | 100,000 | 2,000 ± 1,414 (2) | -2,000 ± 943 (2) | 1 min, 1 min |"
    assert row + " 3,000 |" in text
    assert "| HumanoidFlagrunHarder-v0, table4-128, seed1 | 100 | 1.00 | 0.00 | 2.00 (0.00) | 1 (2) | 40 |" in text
    assert "| HumanoidFlagrunHarder-v0, table4-128, seed2 | 100 | 0.00 | 0.00 | 0.00 (0.00) | 0 (3) | – |" in text
    assert "| HumanoidFlagrun-v0, table4-128, seed1 | 100 | 1.50 | 0.00 | 1.00 (–) | – | – |" in text
    assert "| HumanoidForward-v0, table4, seed1 | 100 | – | 3.00 | 0.50 (–) | – | – |" in text
    # README.md, a line of words: over 4 episodes, 1 flag; 1 get-up of 2 falls and 3 starts on the ground
    short = report.readme_block(results=results)
    assert (
        "**`roboschool-bullet`: 4 runs (seeds 1, 2; 100,000 steps each)** ([report](roboschool-bullet/report.md)):"
        " HumanoidFlagrun-v0 (table4-128) 2,000 over the last 100 episodes (1 seed; Figure 4: about 2,500 near 100M),"
        " 1.50 flags reached an episode, fell in 3 of 4 episodes; HumanoidFlagrunHarder-v0 (table4-128) 2,000 ± 1,414"
        " over the last 100 episodes (2 seeds; Figure 4: about 3,000 near 100M), 0.25 flags reached an episode, got up"
        " 1 of 5 times down; HumanoidForward-v0 (table4) 4,000 over the last 100 episodes (1 seed), fell in 1 of 2"
        " episodes." in short
    )


def test_roboschool_body_report_sets_each_run_beside_the_same_run_on_the_earlier_rules(tmp_path):
    """A roboschool-body folder's report has each run's score, flags and get-ups beside the same command and seed in
    the earlier rules' folder at the same budget; runs with no counterpart there get no row."""
    import roboschool_measures

    results = tmp_path / "results"
    body, earlier = results / "roboschool-body_100000", results / "roboschool_100000"
    fake_run(body, "HumanoidFlagrunHarder-v0", "table4-128", 1, 1500.0)
    fake_run(body, "HumanoidFlagrun-v0", "table4-128", 2, 700.0)  # no counterpart: no row
    fake_run(earlier, "HumanoidFlagrunHarder-v0", "table4-128", 1, 900.0)
    zero = dict.fromkeys(roboschool_measures.FIELDS, 0) | {"length": 100, "getup_steps": ""}
    name = "HumanoidFlagrunHarder-v0__table4-128__seed1.csv"
    roboschool_measures.write(body / "measures" / name, [zero | dict(seed=1, flags=3, falls=1, getups=1)])
    roboschool_measures.write(earlier / "measures" / name, [zero | dict(seed=1, flags=1, started_down=1)] * 2)
    (body / "video").mkdir()
    film = "frames,body_span_median,body_span_p5,flag_near,flag_seen,cube_flying,cube_seen\n300,0.314,0.2,120,119,9,7\n"
    (body / "video" / "HumanoidFlagrunHarder-v0__table4-128__seed1.csv").write_text(film)
    text = report.report(body, results=results)
    film_row = "| HumanoidFlagrunHarder-v0, table4-128, seed1"
    assert film_row + " | 300 | 0.31 (0.20) | 119 of 120 | 7 of 9 |" in text
    assert "## Roboschool's body against the earlier rules" in text
    assert "in `benchmarks/results/roboschool_100000`" in text
    # earlier: 2 episodes of 1 flag, each started down and never got up; body: 3 flags, 1 get-up of 1 fall
    assert (
        "| HumanoidFlagrunHarder-v0 | table4-128 | 1 | 100,000 | 900.0 | 1,500 | 1.00 | 3.00 | 0 (2) | 1 (1) |" in text
    )
    section = text.split("against the earlier rules", 1)[1].split("\n\n", 3)[2]  # the table
    assert section.count("\n| Humanoid") == 1
    assert "against the earlier rules" not in report.report(earlier, results=results)


def test_the_measured_bodys_report_names_the_body_it_is_set_beside(tmp_path):
    """The body measured against Bullet is set beside Roboschool's body as first settled (roboschool-body), not beside
    the earlier rules: its section's heading, its words and its columns name those two bodies."""
    import roboschool_measures

    results = tmp_path / "results"
    bullet, body = results / "roboschool-bullet_100000", results / "roboschool-body_100000"
    fake_run(bullet, "HumanoidFlagrunHarder-v0", "table4-128", 1, 1700.0)
    fake_run(body, "HumanoidFlagrunHarder-v0", "table4-128", 1, 364.0)
    zero = dict.fromkeys(roboschool_measures.FIELDS, 0) | {"length": 100, "getup_steps": ""}
    name = "HumanoidFlagrunHarder-v0__table4-128__seed1.csv"
    roboschool_measures.write(bullet / "measures" / name, [zero | dict(seed=1, falls=2, getups=2)])
    roboschool_measures.write(body / "measures" / name, [zero | dict(seed=1, falls=1)])
    text = report.report(bullet, results=results)
    assert "against the earlier rules" not in text and "gymnasium's body" not in text
    section = text.split("## The body measured against Bullet beside Roboschool's body as first settled", 1)[1]
    words, table = section.split("\n\n", 3)[1:3]
    assert words.startswith("The same seed and settings on Roboschool's body as first settled from its sources (")
    assert "in `benchmarks/results/roboschool-body_100000`" in words
    assert table.splitlines()[0].startswith("| env | setting | seed | steps | Roboschool's body: last 100 | measured")
    assert table.splitlines()[2:] == [
        "| HumanoidFlagrunHarder-v0 | table4-128 | 1 | 100,000 | 364.0 | 1,700 | 0.00 | 0.00 | 0 (1) | 2 (2) |"
    ]


def test_a_long_runs_report_sets_its_midway_checkpoint_beside_its_end(tmp_path):
    """The 100M runs are measured at the checkpoint run.py kept past 50M as well: the report's table gives, for each,
    the score as it stood at that checkpoint's step and the measures of both checkpoints; README's line adds them."""
    import roboschool_measures

    from reports import roboschool
    from results import load_runs

    folder, earlier = tmp_path / "results" / "roboschool-body", tmp_path / "results" / "roboschool"
    fake_run(folder, "HumanoidFlagrunHarder-v0", "table4-128", 1, 1500.0)
    fake_run(earlier, "HumanoidFlagrunHarder-v0", "table4-128", 1, 900.0, steps=50_000)  # the earlier rules, shorter
    fake_run(folder, "HumanoidFlagrun-v0", "table4-128", 1, 700.0)  # measured at its end only: no midway row
    zero = dict.fromkeys(roboschool_measures.FIELDS, 0) | {"length": 100, "getup_steps": ""}
    for name in ["HumanoidFlagrunHarder-v0__table4-128__seed1.csv", "HumanoidFlagrun-v0__table4-128__seed1.csv"]:
        roboschool_measures.write(folder / "measures" / name, [zero | dict(seed=1, flags=3, falls=1, getups=1)])
    midway = [zero | dict(seed=1, flags=2, falls=1, step=50_500), zero | dict(seed=2, step=50_500)]
    roboschool_measures.write(folder / "measures" / "50M" / "HumanoidFlagrunHarder-v0__table4-128__seed1.csv", midway)
    text = report.report(folder, results=tmp_path / "results")
    table = text.split("## At 50M steps and at the end", 1)[1].split("\n\n", 3)[2]
    # By step 50,500 the first 75 of the 150 episodes had ended (one every 666.7 steps): the 50 of -10,000, then
    # 13 of 1,499 and 12 of 1,501, a mean of -6,166.7; at the end, the last 100 average 1,500.
    run = "| HumanoidFlagrunHarder-v0, table4-128, seed1 |"
    assert table.splitlines()[2:] == [
        run + " 50,500 | -6,167 | 100 | 1.00 | 0.00 | 0.50 (0.00) | 0 (1) | – |",
        run + " 100,000 | 1,500 | 100 | 3.00 | 0.00 | 1.00 (0.00) | 1 (1) | – |",
    ]
    # Beside the earlier rules' 50,000 steps, this run at the checkpoint kept just past them: its score and measures.
    rules = text.split("## Roboschool's body against the earlier rules", 1)[1].split("\n\n", 3)[2]
    assert rules.splitlines()[2:] == [
        "| HumanoidFlagrunHarder-v0 | table4-128 | 1 | 50,000 | 900.0 | -6,167 (at 50,500) | – | 1.00 | – | 0 (1) |"
    ]
    line = roboschool.summary(folder, load_runs(folder), {}, tmp_path / "results")
    assert "got up 1 of 1 times down (at 50M: -6,167, 1.00 flags, got up 0 of 1 times down)" in line


def test_the_readmes_example_suite_is_one_entry_and_one_module(tmp_path, monkeypatch):
    """benchmarks/README.md's "Adding a suite": its entry of SUITES and its module of reports/ are all that run.py and
    report.py need to run the suite and write its report and README lines."""
    section = (ROOT / "benchmarks" / "README.md").read_text().split("## Adding a suite", 1)[1].split("\n## ", 1)[0]
    entry, code = [block.split("```", 1)[0] for block in section.split("```python\n")[1:]]
    monkeypatch.setitem(SUITES, "stepsize", eval("{" + entry + "}", {"Suite": Suite})["stepsize"])
    module = types.ModuleType("reports.stepsize")
    exec(code, module.__dict__)
    monkeypatch.setitem(sys.modules, "reports.stepsize", module)
    jobs = make_grid("stepsize")
    check_grid(jobs)
    assert sorted((job.variant, job.seed) for job in jobs) == [(v, s) for v in ("lr1e-3", "lr3e-4") for s in (1, 2, 3)]
    results = tmp_path / "results"
    for seed in (1, 2, 3):
        fake_run(results / "stepsize", "Hopper-v5", "lr3e-4", seed, 1000.0 + seed)
        fake_run(results / "stepsize", "Hopper-v5", "lr1e-3", seed, 2000.0 + seed)
    text = report.report(results / "stepsize", reference={}, results=results)
    # By hand: each side's scores are n + 1, 2, 3 (std 1); the gap is 1,000 with a standard error of sqrt(1/3 + 1/3).
    assert "| Hopper-v5 | lr1e-3 | 2,002 ± 1 (3) | **+1,000.0 ± 0.8** | – |" in text
    assert "| env | ours: lr3e-4 (n) | ours: lr1e-3 (n) | random policy |" in text, "the entry's order: default first"
    assert (results / "stepsize" / "curves" / "Hopper-v5.png").exists()
    assert "### `stepsize`: 6 runs (seeds 1, 2, 3; 100,000 steps each)" in report.readme_block(
        results=results, reference={}, full=True
    )


@pytest.mark.parametrize("form", ["bon", "rl"])
def test_gaos_forms_are_fitted_back_from_points_of_known_alpha_and_beta(form):
    """fit_gao recovers alpha and beta from points on R(d) = d (alpha - beta d) or d (alpha - beta
    log d), with noise, and its peak is where a fine grid of the true curve peaks."""
    import numpy as np

    alpha, beta = (3.0, 0.8) if form == "bon" else (1.2, 0.9)
    d = np.linspace(0.05, 6.0, 40)
    curve = {"bon": lambda x: x * (alpha - beta * x), "rl": lambda x: x * (alpha - beta * np.log(x))}[form]
    noisy = curve(d) + np.random.default_rng(0).normal(0, 0.02, d.size)
    fitted_alpha, fitted_beta, peak, at_peak = rlhf_series.fit_gao(d, noisy, form)
    assert fitted_alpha == pytest.approx(alpha, abs=0.03) and fitted_beta == pytest.approx(beta, abs=0.03)
    grid = np.linspace(0.01, 20.0, 200_001)
    exact_alpha, exact_beta, exact_peak, exact_at_peak = rlhf_series.fit_gao(d, curve(d), form)
    assert exact_peak == pytest.approx(grid[np.argmax(curve(grid))], abs=1e-3)
    assert exact_at_peak == pytest.approx(curve(grid).max(), rel=1e-6)
    assert peak == pytest.approx(exact_peak, rel=0.1) and at_peak == pytest.approx(exact_at_peak, rel=0.1)
    rising = rlhf_series.fit_gao(d, d * 2.0, form)  # no fall in the data: no peak to report
    assert rising[3] == float("inf") or rising[2] > d.max() * 5


def fake_best_of_n(results, pairs, alpha, beta, g0):
    """Best-of-N's 7 points (N = 1 ... 64) for seeds 1-3 of a reward model of `pairs`, on Gao et al.'s form."""
    from reports import overoptimization as over

    where = over.best_of_n_folder(results, pairs) / "best_of_n"
    where.mkdir(parents=True, exist_ok=True)
    for seed in (1, 2, 3):
        lines = ["# wall_time_s: 60", ",".join(BEST_OF_N)]
        for n in (1, 2, 4, 8, 16, 32, 64):
            kl = math.log(n) - (n - 1) / n
            lines.append(f"{n},{kl},0.5,{g0 + over.curve('bon', alpha, beta, math.sqrt(kl))},1,0,0,0.9")
        (where / f"seed{seed}.csv").write_text("\n".join(lines) + "\n")


def committed_gold_noise():
    """The gold's noise in the committed rlhf-long runs, over the report's windows of 20 iterations: each run's noise
    between windows (rlhf_series.between_window_noise of its window means) and the std of its iterations within a
    window (the median over its windows), by (variant, seed)."""
    from results import read_rlhf_series

    between, within = {}, {}
    for key, run in read_rlhf_series(RESULTS / "rlhf-long").items():
        means, errors = rlhf_series.tenths(run, "gold_score", spread=True, width=20)
        between[key] = rlhf_series.between_window_noise(means)
        within[key] = float(np.median(errors) * np.sqrt(20))
    return between, within


def synthetic_runs(gold, between, within, count, seed):
    """`count` runs of 1,600 iterations, rlhf-long's 80 windows of 20: gold is the curve `gold` (one value an
    iteration) plus an offset per window and noise per iteration, sized so that the window means scatter `between`
    around the curve and the iterations `within` around their window's mean. The KL and the RM score rise steadily
    (with noise), so that only gold decides a verdict."""
    rng = np.random.default_rng(seed)
    n, width = 1600, 20
    offset = math.sqrt(max(between**2 - within**2 / width, 0.0))
    runs = {}
    for i in range(count):
        columns = np.full((n, 1 + len(RLHF_STATS)), 0.0)
        columns[:, 0] = np.arange(1, n + 1) * 64
        noisy = gold + np.repeat(rng.normal(0, offset, n // width), width) + rng.normal(0, within, n)
        columns[:, 1 + RLHF_STATS.index("gold_score")] = noisy
        columns[:, 1 + RLHF_STATS.index("kl")] = np.linspace(2.0, 12.0, n) + rng.normal(0, 0.3, n)
        columns[:, 1 + RLHF_STATS.index("score")] = np.linspace(1.0, 2.0, n) + rng.normal(0, 0.05, n)
        runs["beta0", i] = columns
    return runs


def one_window_runs(golds, kl, score):
    """Runs of one iteration a window, for rlhf_series.judge(run, 1): gold each row of `golds`, and the KL and the RM
    score of each run from kl(i) and score(i)."""
    runs = {}
    for i, gold in enumerate(golds):
        columns = np.zeros((len(gold), 1 + len(RLHF_STATS)))
        columns[:, 1 + RLHF_STATS.index("gold_score")] = gold
        columns[:, 1 + RLHF_STATS.index("kl")] = kl(i)
        columns[:, 1 + RLHF_STATS.index("score")] = score(i)
        runs["beta0", i] = columns
    return runs


@pytest.mark.parametrize(
    "noise,windows,bound", [("gaussian", 80, 0.02), ("gaussian", 10, 0.02), ("t4", 80, 0.05), ("t4", 10, 0.05)]
)
def test_the_fall_rule_calls_few_flat_curves_a_fall(noise, windows, bound):
    """On flat curves of pure noise, of rlhf-long's 80 windows and of the rlhf suite's 10 tenths, the fall alone passes
    in under 2% of Gaussian curves and under 5% of curves with t's heavy tails (4 degrees of freedom): the bounds
    rlhf_series.Z was fixed on, before the runs were judged. No minimum fall: the rule's noise alone decides."""
    rng = np.random.default_rng(windows)
    golds = rng.standard_normal((4000, windows)) if noise == "gaussian" else rng.standard_t(4, (4000, windows))
    runs = one_window_runs(golds, lambda i: np.arange(windows), lambda i: np.arange(windows))
    fell = [rlhf_series.verdict_of(rlhf_series.judge(run, 1, min_fall=0.0))[1]["fell"] for run in runs.values()]
    assert np.mean(fell) < bound, np.mean(fell)


@pytest.mark.parametrize("windows", [80, 10])
def test_the_fall_rule_calls_a_step_collapse_whose_residuals_the_previous_rule_counted_as_noise(windows):
    """A collapse as the runs show it: gold rises from its first window (by 3 to 6 points over tenths, as process
    supervision's rlhf runs; by 1 to 5 over rlhf-long's windows, as the 1,024-pair RM's) to a plateau at 8.5 with
    heavy-tailed noise, then drops in one window to the penalty, -6, and stays there; the KL jumps and the RM score
    holds. The rule calls at least 99% of 500 such curves, wherever the drop falls; the previous rule, whose noise
    counted the drop's two residuals, fewer than half."""
    rng = np.random.default_rng(windows)
    golds, drops = [], []
    for _ in range(500):
        drops.append(int(rng.integers(4, windows - 2)))  # after a plateau of 3 windows, and before the last 3
        gold = np.where(np.arange(windows) < drops[-1], 8.5, -6.0) + 0.1 * rng.standard_t(4, windows)
        gold[0] -= rng.uniform(3.0, 6.0) if windows == 10 else rng.uniform(1.0, 5.0)
        golds.append(gold)
    kl = lambda i: np.linspace(2, 20, windows) + 10 * (np.arange(windows) >= drops[i])  # noqa: E731
    runs = one_window_runs(golds, kl, lambda i: np.linspace(1, 2, windows))
    called = len(rlhf_series.falls(runs, width=1)) / len(runs)
    previous = len(rlhf_series.falls(runs, width=1, rule=rlhf_series.PREVIOUS)) / len(runs)
    assert called >= 0.99 and previous < 0.5, (called, previous)


def test_a_refreshed_reward_model_whose_score_fell_with_the_gold_does_not_hide_the_fall():
    """The RM score must hold for a fall to be over-optimization, but a refreshed reward model's score at the end is a
    later model's than at the peak: one that learned to score the fallen text low would otherwise hide the fall its
    earlier self led to. The same curves are a fall for refresh8-beta0 and not for beta0, whose one RM scored both."""
    windows = 80
    gold = np.where(np.arange(windows) < 40, 8.0, -6.0)
    gold[:5] = [2.0, 4.0, 6.0, 7.0, 7.5]  # the rise
    score = np.where(np.arange(windows) < 40, 10.0, 3.0)  # the refreshed model scores the fallen text low
    (run,) = one_window_runs([gold], lambda i: np.linspace(2, 20, windows), lambda i: score).values()
    fell = rlhf_series.falls({("refresh8-beta0", 1): run, ("beta0", 1): run}, width=1)
    assert set(fell) == {("refresh8-beta0", 1)}, fell
    assert rlhf_series.refreshed("process-refresh8-beta0") and not rlhf_series.refreshed("process-beta0")


def test_the_fall_rule_still_calls_a_fall_of_the_size_seen_at_beta_0():
    """The committed beta-0 runs (4,096 pairs) fall from their peak to their end by some amount each, read as the
    rule reads them; the median of the three is the size of fall seen at beta 0. Drawn 200 times on a curve that rises
    to a plateau and then falls by that much, with that run's own noise between and within windows, the rule calls at
    least 95% of them over-optimized."""
    from results import read_rlhf_series

    between, within = committed_gold_noise()
    series = read_rlhf_series(RESULTS / "rlhf-long")
    drops = {}
    for key in [k for k in series if k[0] == "beta0"]:
        _, peak, last = rlhf_series.judge(series[key], 20)["values"]["gold_score"]
        drops[key] = peak - last
    key = sorted(drops, key=drops.get)[len(drops) // 2]  # the seed of the median fall
    drop = drops[key]
    t = np.arange(1600) / 1600
    gold = 2.0 + 6.0 * np.minimum(t / 0.4, 1.0) - drop * np.clip((t - 0.6) / 0.2, 0.0, 1.0)  # rise, plateau, fall
    runs = synthetic_runs(gold, between[key], within[key], 200, seed=1)
    called = len(rlhf_series.falls(runs, width=20)) / len(runs)
    assert drop > 0 and called >= 0.95, (key, drop, between[key], called)


def test_the_overoptimization_report_fits_gaos_forms_and_answers_the_claims_from_them(tmp_path):
    """On runs drawn from Gao et al.'s RL form with known alpha and beta per reward model size, and best-of-N
    points from its own form, the rlhf-long report fits both back per size, counts the beta-0 runs that pass their
    peak as over-optimized, and answers (a) a weaker RM peaks earlier and lower, (b) runs that stop early on the same
    curve lie on it, and (c) PPO lies below best-of-N, from those numbers; and draws its figure."""
    from reports import overoptimization as over

    assert over.DEFAULT_PAIRS == load_script("ppo_rlhf.py").Args().rm_pairs
    folder, g0 = tmp_path / "rlhf-long", 1.0
    rl = {1024: (1.5, 1.0), 4096: (2.0, 1.0), 16384: (2.2, 0.9)}  # d* = e^(alpha / beta - 1): 1.65, 2.72, 4.2
    bon = {1024: (2.0, 0.5), 4096: (3.0, 0.5), 16384: (3.5, 0.5)}
    noise = np.random.default_rng(0)
    for variant in [
        v for v in SUITES["rlhf-long"].variants if over.measures.one_outcome_rm(v)
    ]:  # ensembles, process: theirs
        # the beta-0 runs go on to d = 6; the penalized ones stop at d = 2, on the same grid of d (so that a bin of d
        # holds the same d in both, and only the noise tells them apart)
        d = np.linspace(0.05, 6.0, 400)
        d = d if over.beta_of(variant) == 0 else d[d <= 2.0]
        pairs = over.rm_pairs(variant)
        for seed in (1, 2, 3):
            fake_run(folder, "reviews", variant, seed, 1.0, steps=102_400)
            gold = g0 + over.curve("rl", *rl[pairs], d) + noise.normal(0, 0.05, d.size)
            rows = []
            for i in range(d.size):
                stats = {"score": i / 399, "gold_score": gold[i], "kl": d[i] ** 2, "spam": 0.0, "garbled": 0.0}
                rows.append([(i + 1) * 256] + [stats.get(name, 0.5) for name in RLHF_STATS])
            write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
    for pairs, (alpha, beta) in bon.items():
        fake_best_of_n(tmp_path, pairs, alpha, beta, g0)
    text = report.report(folder, results=tmp_path)

    def fitted(pairs, form):
        row = next(line for line in text.splitlines() if line.startswith(f"| {pairs:,} |") and over.FORMS[form] in line)
        return [float(c.split("±")[0]) for c in row.split("|")[4:6]]

    for pairs in rl:
        assert fitted(pairs, "rl") == pytest.approx(rl[pairs], abs=0.05)
        assert fitted(pairs, "bon") == pytest.approx(bon[pairs], abs=0.01)
    # the beta-0 runs of 1,024 and 4,096 pairs pass their peak (d* 1.65, 2.72) and fall from it by 3.4 and 1.5 by d = 6;
    # those of 16,384 pass theirs (4.2) but fall 0.3, under the minimum fall
    counts = {row.split("|")[1].strip(): row.split("|")[-2].strip() for row in text.splitlines() if " of 3 |" in row}
    assert counts == {"beta0": "3 of 3", "beta0.05": "0 of 3", "rm1024-beta0": "3 of 3", "rm16384-beta0": "0 of 3"}
    assert "The 1,024-pair RM's runs peak lower than the 16,384-pair RM's" in text and ") and earlier (their" in text
    assert "also visited, lies within 2 standard errors of that run's (" in text
    assert "against that run's fitted curve, within 2 standard errors of it (" in text
    assert "4,096 pairs, β = 0: below best-of-N (" in text and "4,096 pairs, β = 0.05: below best-of-N (" in text
    assert (folder / "curves" / "panels.png").exists() and (folder / "curves" / "seeds.png").exists()
    summary = "\n".join(over.summary_lines(folder, tmp_path))  # the README's, beside the rlhf suite's block
    assert "12 runs of 102,400 responses, seeds 1, 2, 3, β = 0 with reward models from 1,024, 4,096, 16,384" in summary
    current = text.split("## What the change of rule moved")[0]  # after it, the claims under the previous rule
    assert all(line in summary for line in current.splitlines() if line.startswith("- **("))


def test_the_overoptimization_report_answers_whether_an_ensemble_peaks_later_and_higher_and_herds(tmp_path):
    """Single-RM runs drawn from Gao et al.'s RL form with d* 2.72, and 4-RM ensemble runs from one with
    d* 4.06, higher, each past its peak: (d) the ensemble peaks later and higher than the same seed's single RM; (e)
    where every member's score keeps rising as gold falls, each fallen run herds, and the members' disagreement,
    tripled by the gold peak, rose first; with one member that turns down after the peak, that run does not herd."""
    from reports import overoptimization as over

    folder = tmp_path / "rlhf-long"
    arms = {"beta0": (2.0, 1.0, 4.5), "ens4-mean": (2.4, 1.0, 8.0)}  # alpha, beta, the last d: past the minimum fall
    for variant, (alpha, beta, d_end) in arms.items():
        for seed in (1, 2, 3):
            fake_run(folder, "reviews", variant, seed, 1.0, steps=102_400)
            d = np.linspace(0.05, d_end, 200)
            gold = 1.0 + over.curve("rl", alpha, beta, d)
            rows = []
            for i in range(200):
                stats = {"score": i / 199, "gold_score": gold[i], "kl": d[i] ** 2, "spam": 0.0, "garbled": 0.0}
                rows.append([(i + 1) * 512] + [stats.get(name, 0.5) for name in RLHF_STATS])
            write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
            if variant == "ens4-mean":
                peak = int(np.argmax(gold))
                spread = 0.1 + 0.2 * np.minimum(np.arange(200), peak) / peak  # 0.1 at first, 0.3 by the gold peak
                members = [np.arange(200) / 199 + k / 10 for k in range(4)]
                if seed == 3:  # one member turns down after the gold peak
                    members[0] = np.where(np.arange(200) > peak, 2 * members[0][peak] - members[0], members[0])
                rows = [[(i + 1) * 512, spread[i], *(m[i] for m in members)] for i in range(200)]
                columns = ("rm_disagreement", *(f"rm_member{k}" for k in range(4)))
                write_series(folder / "ensemble" / f"reviews__{variant}__seed{seed}.csv", columns, rows)
    text = report.report(folder, results=tmp_path)

    def peak(alpha, beta, d_end):  # the 3 windows of 20 iterations of highest mean gold: gain over the first, d
        d = np.linspace(0.05, d_end, 200)
        gold = (1.0 + over.curve("rl", alpha, beta, d)).reshape(10, 20).mean(1)
        kl = (d**2).reshape(10, 20).mean(1)
        i = int(np.argmax([gold[j : j + 3].mean() for j in range(8)]))
        return gold[i : i + 3].mean() - (1.0 + over.curve("rl", alpha, beta, d[0])), np.sqrt(kl[i : i + 3].mean())

    (single_gain, single_d), (gain, d_peak) = peak(*arms["beta0"]), peak(*arms["ens4-mean"])
    d = next(line for line in text.splitlines() if line.startswith("- **(d)"))  # the current rule's, then the previous
    assert f"`ens4-mean` peaks at gold gain {gain:.2f} ± 0.00 at d {d_peak:.2f} ± 0.00" in d
    assert f"its peak gain is above it ({gain - single_gain:+.2f} ± 0.00, mean ± standard error over 3 seeds)" in d
    assert f"its peak's d above its ({d_peak - single_d:+.2f} ± 0.00" in d and gain > single_gain
    e = next(line for line in text.splitlines() if line.startswith("- **(e)"))
    assert "Of 3 ensemble runs, 3 fell (the current rule); in 2 of them every member rated the fallen text" in e
    assert "and in 3 the disagreement at the gold peak was more than twice that of the first window" in e
    assert "ens4-mean seed 3: gold " in e and "; 3 of 4 members rated the end at least as high" in e
    assert "| ens4-mean | 4,096 × 4 |" in text


def test_the_overoptimization_report_sets_members_with_heads_of_their_own_against_members_with_one_head(tmp_path):
    """(d) for both kinds of member: each ensemble arm's disagreement before PPO (its first rollout's, the first row of
    its ensemble series), and the seeded heads' peak against the same seed's -same-head run's, here higher and later
    (Gao et al.'s RL form with a larger alpha)."""
    from reports import overoptimization as over

    folder = tmp_path / "rlhf-long"
    arms = {"beta0": (2.0, 0.0), "ens4-mean": (2.4, 0.4), "ens4-mean-same-head": (2.2, 0.2)}  # alpha, first spread
    d = np.linspace(0.05, 8.0, 200)
    for variant, (alpha, spread) in arms.items():
        for seed in (1, 2, 3):
            fake_run(folder, "reviews", variant, seed, 1.0, steps=102_400)
            gold = 1.0 + over.curve("rl", alpha, 1.0, d)
            stats = [{"score": i / 199, "gold_score": gold[i], "kl": d[i] ** 2} for i in range(200)]
            rows = [[(i + 1) * 512] + [s.get(name, 0.0) for name in RLHF_STATS] for i, s in enumerate(stats)]
            write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
            if variant != "beta0":
                rows = [[(i + 1) * 512, spread + seed / 100, *(i / 199 + k / 10 for k in range(4))] for i in range(200)]
                columns = ("rm_disagreement", *(f"rm_member{k}" for k in range(4)))
                write_series(folder / "ensemble" / f"reviews__{variant}__seed{seed}.csv", columns, rows)
    text = report.report(folder, results=tmp_path)

    def peak(alpha):  # the 3 windows of 20 iterations of highest mean gold: gain over the first iteration, and d
        gold = (1.0 + over.curve("rl", alpha, 1.0, d)).reshape(10, 20).mean(1)
        i = int(np.argmax([gold[j : j + 3].mean() for j in range(8)]))
        kl = (d**2).reshape(10, 20).mean(1)
        return gold[i : i + 3].mean() - (1.0 + over.curve("rl", alpha, 1.0, d[0])), np.sqrt(kl[i : i + 3].mean())

    (gain, d_peak), (same_gain, same_d) = peak(2.4), peak(2.2)
    line = next(line for line in text.splitlines() if line.startswith("- **(d)"))
    assert "by `ens4-mean` 0.42 ± 0.01, `ens4-mean-same-head` 0.22 ± 0.01." in line
    assert gain - same_gain > 0.1 and d_peak > same_d
    assert (
        "Members with heads of their own (`ens4-mean`) against the same seed's members with one head"
        f" (`ens4-mean-same-head`): the peak gain is above theirs ({gain - same_gain:+.2f} ± 0.00" in line
    )
    assert f"and its d above theirs ({d_peak - same_d:+.2f} ± 0.00" in line


def test_the_overoptimization_report_answers_credit_assignment_and_the_fall_of_process_supervision(tmp_path):
    """(f): each suite's process arm against its outcome arm over the first 40 iterations, seed by seed (here the
    process arm's gold is 1 higher there in every seed), and the first window of the earliest fall (the process arm's
    at beta 0, after those iterations); (g): the process arm at beta 0 rises and falls onto spam while
    its RM's score keeps rising, so it fell, and its peak against beta0's; and the labels from the runs' headers. The
    process arm is not one of the single-RM runs that Gao's forms are fitted to."""
    from reports import overoptimization as over

    long, short = tmp_path / "rlhf-long", tmp_path / "rlhf"
    rise = np.linspace(0, 1, 200)
    falls = np.minimum(rise, 1.2 - rise)  # peaks at 0.6, ends at 0.2
    shapes = {  # folder, variant: gold by iteration (an offset per seed), and whether spam takes over
        (long, "beta0"): (2 + 6 * rise, False),
        (long, "process-beta0"): (3 + 10 * falls, True),
        (short, "beta0.05"): (2 + rise, False),
        (short, "process"): (3 + rise, False),
    }
    for (folder, variant), (gold, spam) in shapes.items():
        for seed in (1, 2, 3):
            meta = [("rm_held_out_accuracy", "0.7" if variant.startswith("process") else "0.9")]
            if variant.startswith("process"):
                meta += [("rm_held_out_clause_accuracy", f"{0.8 + seed / 100}"), ("rm_clause_labels", 7000 + seed)]
                meta += [("rm_train_pairs", 3000 + seed)]
            steps = 102_400 if folder == long else 12_800
            fake_run(folder, "reviews", variant, seed, 1.0, steps=steps, meta=meta)
            rows = []
            for i in range(200):
                stats = {"score": rise[i], "gold_score": gold[i] + seed / 10, "kl": 1 + 20 * rise[i]}
                stats |= {"spam": rise[i] if spam else 0.0, "garbled": 0.0}
                rows.append([(i + 1) * steps // 200] + [stats.get(name, 0.5) for name in RLHF_STATS])
            write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
            if variant == "process-beta0":
                rows = [[(i + 1) * 512, 0.9 - 0.5 * rise[i]] for i in range(200)]
                write_series(long / "process" / f"reviews__{variant}__seed{seed}.csv", ("rm_clause_accuracy",), rows)
    text = report.report(long, results=tmp_path)
    f = next(line for line in text.splitlines() if line.startswith("- **(f)"))
    first = shapes[short, "process"][0][:40].mean() + 0.2  # the first 40 iterations; seeds add 0.1-0.3, 0.2 on average
    assert f"in `rlhf`, `process` reached gold {first:.2f} ± 0.06 and `beta0.05` {first - 1:.2f} ± 0.06 (seed 1:" in f
    assert f"seed 3: {first + 0.1:.2f} against {first - 0.9:.2f}); process minus outcome, seed by seed, is above" in f
    mine, theirs = (shapes[long, v][0][:40].mean() for v in ("process-beta0", "beta0"))
    assert f"in `rlhf-long`, `process-beta0` reached gold {mine + 0.2:.2f} ± 0.06 and `beta0` {theirs + 0.2:.2f}" in f
    # the process runs fall: the first window of 20 iterations after their peak (the 3 of highest mean) that is below
    # it by more than the minimum fall (their noise between windows is 0: straight lines)
    windows = (3 + 10 * falls).reshape(10, 20).mean(1)
    peak = int(np.argmax([windows[j : j + 3].mean() for j in range(8)]))
    first_fall = next(i for i in range(peak + 3, 10) if windows[i] < windows[peak : peak + 3].mean() - 0.5)
    assert f"begins at iteration {20 * first_fall + 1}: these iterations come before any fall." in f
    g = next(line for line in text.splitlines() if line.startswith("- **(g)"))
    assert "`process-beta0` peaks at gold gain" in g and "minus the same seed's `beta0`" in g
    for seed in (1, 2, 3):
        assert f"seed {seed} fell (rose yes, fell yes, kl held yes, score held yes): gold " in g
    windows = (3 + 10 * falls).reshape(10, 20).mean(1)
    peak = int(np.argmax([windows[j : j + 3].mean() for j in range(8)]))  # the 3 windows of 20 of highest gold

    def at(x, start, stop):  # the mean of x over windows start to stop
        return x[20 * start : 20 * stop].mean()

    assert f"with spam {at(rise, 9, 10):.2f} and garbled 0.00 at the end" in g
    assert f"its RM's score {at(rise, peak, peak + 3):.2f} at the peak, {at(rise, 7, 10):.2f} at the end" in g
    clauses = 0.9 - 0.5 * rise
    assert f"it rated {at(clauses, peak, peak + 3):.0%} of the policy's clauses as gold does at the peak," in g
    assert f" {at(clauses, 7, 10):.0%} at the end." in g
    labels = next(line for line in text.splitlines() if line.startswith("- **The labels each cost.**"))
    assert "7,002 ± 1" in labels and "6,002–6,006 responses of the 3,001–3,003 pairs" in labels
    assert "0.82 ± 0.01" in labels and "not at equal labelling effort" in labels
    fits = next(line for line in text.splitlines() if line.startswith("| 4,096 | "))
    assert fits.startswith("| 4,096 | 0.90 ± 0.00 |")  # the single outcome RMs' accuracy alone, not the process RMs'
    assert over.measures.one_outcome_rm("beta0") and not over.measures.one_outcome_rm("process-beta0")


def test_the_overoptimization_report_answers_whether_a_refreshed_reward_model_removes_the_fall(tmp_path):
    """(h): the refreshed arms beside the same reward models never refreshed, the leash and the ensembles. Here beta0
    falls in every seed and refresh8-beta0 only in seed 3: the refresh kept seeds 1 and 2 from falling, and ended
    higher in gold. The comparisons each arm drew come from its flags and the run's length (a refreshed outcome RM:
    stage 2's 4,096 and 200 refreshes of 64 prompts, about rm16384-beta0's 16,384); the labels each learned from, from
    the runs' headers (a process RM's in clauses). The refreshed arms are not among the single RMs Gao's forms fit."""
    from reports import overoptimization as over

    folder = tmp_path / "rlhf-long"
    rise = np.minimum(np.arange(200) / 60, 1.0)  # to 1 by iteration 60, then held
    collapse = np.where(np.arange(200) < 120, 2 + 6 * rise, -6.0)  # gold 8 until iteration 120, then the penalty
    holds = 2 + 6 * rise
    shapes = {
        "beta0": [collapse] * 3,
        "refresh8-beta0": [holds, holds, collapse],
        "process-beta0": [collapse] * 3,
        "process-refresh8-beta0": [holds] * 3,
        "beta0.05": [holds] * 3,
        "ens4-mean": [holds] * 3,
        "rm16384-beta0": [collapse, holds, holds],
    }
    for variant, golds in shapes.items():
        for seed, gold in enumerate(golds, 1):
            process = variant.startswith("process")
            meta = [("rm_clause_labels", 10_000 + seed), ("rm_held_out_clause_accuracy", 0.9)] * process
            meta += [("rm_train_pairs", 3_400 + seed)]
            if "refresh" in variant:
                meta.append(("rm_refresh_labels", (50_000 if process else 12_000) + seed))
            fake_run(folder, "reviews", variant, seed, 1.0, steps=102_400, meta=meta)
            stats = [{"score": i / 199, "gold_score": gold[i], "kl": 1 + i / 10} for i in range(200)]
            rows = [[(i + 1) * 512] + [stats[i].get(name, 0.0) for name in RLHF_STATS] for i in range(200)]
            write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
    text = report.report(folder, results=tmp_path)
    h = next(line for line in text.splitlines() if line.startswith("- **(h)"))
    assert (
        "`refresh8-beta0` fell in 1 of 3 seeds, `beta0` in 3; of those, the refresh kept 2 from falling (seed 1, 2)"
        in h
    )
    assert "its gold at the end is within 2 standard errors of the unrefreshed run (+9.33 ± 4.67" in h  # 14, 14, 0
    assert "`process-refresh8-beta0` fell in 0 of 3 seeds, `process-beta0` in 3; of those, the refresh kept 3" in h
    table = text.split("- **(h)")[1].split("## What the change of rule moved")[0].splitlines()
    rows = {line.split("|")[1].strip(): line.split("|")[2:-1] for line in table if line.startswith("| ")}
    refreshed = [c.strip() for c in rows["refresh8-beta0"]]
    assert refreshed[:5] == ["outcome, refreshed every 8 iterations", "0", "16,896", "15,404 ± 2", "1 of 3"]
    assert [c.strip() for c in rows["process-refresh8-beta0"]][2:5] == ["–", "60,004 ± 2", "0 of 3"]
    assert [c.strip() for c in rows["rm16384-beta0"]][2:5] == ["16,384", "3,402 ± 1", "1 of 3"]
    assert [c.strip() for c in rows["ens4-mean"]][:3] == ["outcome × 4", "0", "4,096"]
    assert [c.strip() for c in rows["beta0.05"]][1:3] == ["0.05", "4,096"]
    assert not over.measures.one_outcome_rm("refresh8-beta0") and over.measures.refresh_of("refresh8-beta0") == 8
    labels = next(line for line in text.splitlines() if line.startswith("- **The labels each cost.**"))
    assert "10,002 ± 1 clause labels (mean ± std over 3 reward models)" in labels  # a refreshed twin's RM counted once
    assert (folder / "curves" / "panels.png").exists()


def test_the_fits_of_a_reward_model_size_give_the_held_out_accuracy_of_the_single_reward_models_fitted(tmp_path):
    """Gao et al.'s forms are fitted to the beta-0 runs of one reward model: the row's held-out accuracy is theirs, not
    pooled with the ensembles' trained on the same number of pairs (4 reward models, another accuracy)."""
    from reports import overoptimization as over

    folder = tmp_path / "rlhf-long"
    d = np.linspace(0.05, 4.5, 100)
    gold = 1.0 + over.curve("rl", 2.0, 1.0, d)
    for variant, accuracy in (("beta0", "0.8500"), ("ens4-mean", "0.9900")):
        for seed in (1, 2, 3):
            fake_run(folder, "reviews", variant, seed, 1.0, 102_400, [("rm_held_out_accuracy", accuracy)])
            stats = [{"score": i / 99, "gold_score": gold[i], "kl": d[i] ** 2} for i in range(100)]
            rows = [[(i + 1) * 1024] + [stats[i].get(name, 0.0) for name in RLHF_STATS] for i in range(100)]
            write_series(folder / "rlhf" / f"reviews__{variant}__seed{seed}.csv", RLHF_STATS, rows)
            if variant == "ens4-mean":
                columns = ("rm_disagreement", *(f"rm_member{k}" for k in range(4)))
                rows = [[(i + 1) * 1024, 0.1, *(i / 99 + k / 10 for k in range(4))] for i in range(100)]
                write_series(folder / "ensemble" / f"reviews__{variant}__seed{seed}.csv", columns, rows)
    fake_best_of_n(tmp_path, 4096, 3.0, 0.5, 1.0)
    text = report.report(folder, results=tmp_path)
    fits = [line for line in text.splitlines() if line.startswith("| 4,096 | ")]
    assert len(fits) == 2 and all(line.startswith("| 4,096 | 0.85 ± 0.00 | ") for line in fits), fits


def test_a_clone_of_one_commit_regenerates_the_rlhf_report_and_block_unchanged(tmp_path):
    """What a run's RM accuracy measures is in its CSV (results.RM_ACCURACY), not asked of git: a clone made with
    --depth 1, as CI's default checkout on the big hosting services, has no history to ask, and regenerates the rlhf
    suite's report and the README's RLHF block as committed."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", "--depth", "1", f"file://{ROOT}", str(clone)], check=True)
    depth = subprocess.run(["git", "rev-list", "--count", "HEAD"], cwd=clone, capture_output=True, text=True)
    assert depth.stdout.strip() == "1"
    check = """if True:
        import sys
        from pathlib import Path
        sys.path.insert(0, "benchmarks")
        from reports import rlhf
        from results import load_runs
        readme = Path("benchmarks/README.md").read_text()
        start, end = readme.index(rlhf.RLHF_START), readme.index(rlhf.RLHF_END) + len(rlhf.RLHF_END)
        assert readme[start:end] == rlhf.rlhf_block(), "the README's RLHF block differs"
        folder = Path("benchmarks/results/rlhf")
        committed = (folder / "report.md").read_text()
        assert rlhf.rlhf_report(folder, load_runs(folder)) == committed, "the rlhf report differs"
    """
    proc = subprocess.run([sys.executable, "-c", check], cwd=clone, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.mark.parametrize("t,p", [(2.306, 0.05), (3.355, 0.01), (1.860, 0.10)])
def test_welchs_test_against_students_table(t, p):
    """Two samples of 5 with equal variance 2.5, their means t standard errors apart: Welch's degrees of freedom are
    2 (n - 1) = 8, and the two-sided p-value is the one a table of Student's t gives for df 8."""
    from reports.stats import welch

    base = [0.0, 1.0, 2.0, 3.0, 4.0]
    t_stat, df, p_value = welch([x + t for x in base], base)
    assert t_stat == pytest.approx(t) and df == pytest.approx(8.0)
    assert p_value == pytest.approx(p, abs=0.0005)
