"""The roboschool family: the paper's Figure 4, its three humanoid tasks with Roboschool's rules on MuJoCo
(roboschool_humanoid.py), beside the figure's rough end points, and what the trained policies do in units a reader
knows (benchmarks/roboschool_measures.py)."""

from __future__ import annotations

import csv
from pathlib import Path

from reports import scores
from reports.base import env_base, fmt, ordered_variants, suite_name
from reports.humanoid import score_cells
from reports.stats import group, mean_std
from suites import COLUMNS

ORDER = 2  # beside the humanoid suite
# A suite on a later body -> (the suite of the same runs on the body before it, whose results the report sets beside;
# the section's heading; what the earlier body was; the two bodies' short names, for the columns).
EARLIER = {
    "roboschool-body": (
        "roboschool",
        "Roboschool's body against the earlier rules",
        "the earlier rules (gymnasium's body, its joint springs and dampers, the height of MuJoCo's torso origin, the"
        " mean of 13 bodies)",
        ("earlier rules", "Roboschool's body", "earlier", "body"),
    ),
    "roboschool-bullet": (
        "roboschool-body",
        "The body measured against Bullet beside Roboschool's body as first settled",
        "Roboschool's body as first settled from its sources (a damper of 0.5 on every joint, unit joint axes with"
        " gymnasium's armature, the inertia of MuJoCo's geoms, MuJoCo's default joint limits and contacts)",
        ("Roboschool's body", "measured body", "Roboschool's", "measured"),
    ),
}
RULE = (
    "A run's score is the mean return of its last 100 episodes; a cell is the mean ± sample std over seeds, with the"
    " number of seeds in brackets. Rewards are Roboschool's (per step: +2 alive, progress toward the target in m/s,"
    " minus the motors' costs), not gymnasium's: compare them with Figure 4, not with Humanoid-v5."
)


def paper(env, variant, reference):
    """Figure 4's rough end point for the task, where one was read from the plot; else an empty string."""
    refs = [reference.get((column, env_base(env), variant)) for column, _, _ in COLUMNS["roboschool"]]
    return "; ".join(fmt(r[0]) for r in refs if r)


def run_name(run):
    """The name of a run's measures file: <env>__<variant>__seed<N>."""
    return f"{run.env_id}__{run.variant}__seed{run.seed}"


def flags(rows):
    """Flags reached an episode, over episodes' measures."""
    return sum(float(r["flags"]) for r in rows) / len(rows)


def got_up(rows):
    """(get-ups, times down) over episodes' measures: a time down is a fall or a start on the ground."""
    return sum(int(r["getups"]) for r in rows), sum(int(r["falls"]) + int(r["started_down"]) for r in rows)


def can_get_up(name):
    """Only FlagrunHarder's body can be down and go on; the other tasks end the episode when the torso falls."""
    return "FlagrunHarder" in name


def has_flags(name):
    """The flagrun tasks run to flags; the forward walk has one target far ahead, which it never reaches."""
    return "Flagrun" in name


def settings(folder, runs):
    """(env, variant, its runs), in the report's order."""
    by_env = group(runs)
    for env in sorted(by_env):
        for v in ordered_variants(suite_name(folder), runs):
            if v in by_env[env]:
                yield env, v, by_env[env][v]


def tables(folder, runs, reference, results, level="##"):
    """The scores beside Figure 4's, then the measures of the trained policies where they have been made."""
    lines = [
        "| env | setting | steps | last 100 (n) | all training (n) | wall time per run | paper, Fig. 4, near 100M"
        " (approx.) |",
        "|---|---|---|---|---|---|---|",
    ]
    for env, v, setting_runs in settings(folder, runs):
        lines.append("| " + " | ".join([env, v, *score_cells(setting_runs), paper(env, v, reference) or "–"]) + " |")
    return (
        lines
        + measures_table(folder, level)
        + midway_table(folder, runs, level)
        + film_table(folder, level)
        + rules_table(folder, runs, level)
    )


def summary(folder, runs, reference, results):
    """README.md's line of words: each task's score beside Figure 4's end point, and what its trained policy does (the
    report has the tables)."""
    measures = read_measures(folder)
    parts = []
    for env, v, setting_runs in settings(folder, runs):
        last = [r.score for r in setting_runs]
        seeds = f"{len(last)} seeds" if len(last) > 1 else "1 seed"
        figure = paper(env, v, reference)
        part = f"{env} ({v}) {fmt(*mean_std(last))} over the last 100 episodes ({seeds}"
        part += f"; Figure 4: about {figure} near 100M)" if figure else ")"
        rows = [row for r in setting_runs for row in measures.get(run_name(r), [])]
        if rows:
            if has_flags(env):
                part += f", {flags(rows):.2f} flags reached an episode"
            if can_get_up(env):
                getups, downs = got_up(rows)
                part += f", got up {getups} of {downs} times down"
            else:
                part += f", fell in {sum(int(row['falls']) > 0 for row in rows)} of {len(rows)} episodes"
        for label, kept in read_midway(folder).items():
            at = [r for r in setting_runs if run_name(r) in kept]
            if at:
                score = fmt(*mean_std([score_at(r, int(kept[run_name(r)][0]["step"])) for r in at]))
                rows = [row for r in at for row in kept[run_name(r)]]
                part += f" (at {label}: {score}" + (f", {flags(rows):.2f} flags" if has_flags(env) else "")
                if can_get_up(env):
                    part += ", got up {} of {} times down".format(*got_up(rows))
                part += ")"
        parts.append(part)
    return "; ".join(parts) + "."


def read_measures(folder, label=""):
    """{run name: [row, ...]} from <folder>/measures/*.csv (benchmarks/roboschool_measures.py), or from
    measures/<label>/, the checkpoints that run.py kept midway."""
    out = {}
    for path in sorted((Path(folder) / "measures" / label).glob("*.csv")):
        with open(path) as f:
            out[path.stem] = list(csv.DictReader(f))
    return out


def read_midway(folder):
    """{label: {run name: [row, ...]}} for each checkpoint kept midway (measures/<label>/), such as 50M."""
    labels = sorted(p.name for p in (Path(folder) / "measures").glob("*") if p.is_dir())
    return {label: read_measures(folder, label) for label in labels}


def score_at(run, step):
    """The run's score as it stood at `step`: the mean return of the last 100 episodes that ended by then."""
    from results import score

    return score([row for row in run.rows if row[0] <= step])


def measure_cells(name, rows):
    """A run's measures as cells: steps an episode, flags reached, speed toward the flag, falls (knock-downs), got up
    (times down) and the steps it took; means over episodes."""

    def mean(key):
        values = [float(r[key]) for r in rows if r[key] != ""]
        return sum(values) / len(values) if values else None

    getups, downs = got_up(rows)
    steps_up = mean("getup_steps")
    up = [f"{getups} ({downs})", f"{steps_up:.0f}" if steps_up is not None else "–"] if can_get_up(name) else ["–"] * 2
    flag = f"{mean('flags'):.2f}" if has_flags(name) else "–"
    knocks = f"{mean('knockdowns'):.2f}" if can_get_up(name) else "–"  # only FlagrunHarder throws cubes
    return [f"{mean('length'):,.0f}", flag, f"{mean('speed_to_flag'):.2f}", f"{mean('falls'):.2f} ({knocks})", *up]


def measures_table(folder, level):
    measures = read_measures(folder)
    if not measures:
        return []
    lines = [
        "",
        f"{level} What the trained policies do",
        "",
        "Each run's last checkpoint, its deterministic policy (the Gaussian's mean), "
        f"{len(next(iter(measures.values())))} episodes (env seeds 1, 2, ...), by `benchmarks/roboschool_measures.py`."
        " Down means the torso below 0.8 m (FlagrunHarder's rule); a knock-down is a fall within 30 steps of a cube's"
        " throw; got up counts the times it rose from the ground (from a fall or a start lying down), and the steps it"
        " took on average, for FlagrunHarder (the other tasks end an episode when the body falls). Means over"
        " episodes.",
        "",
        "| run | steps an episode | flags reached an episode | speed toward the flag or target (m/s)"
        " | falls (knock-downs) an episode | got up (times down) | steps to get up |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, rows in measures.items():
        lines.append("| " + " | ".join([name.replace("__", ", "), *measure_cells(name, rows)]) + " |")
    return lines


def midway_table(folder, runs, level):
    """Each run at the checkpoint that run.py kept midway beside its end: the score as it stood at that checkpoint's
    step, and the measures of both checkpoints."""
    midway, last = read_midway(folder), read_measures(folder)
    lines = []
    for label, kept in midway.items():
        lines += [
            "",
            f"{level} At {label} steps and at the end",
            "",
            f"Each run at the checkpoint that `benchmarks/run.py` kept midway (the first saved at or past {label}"
            " steps), beside its last. Last 100 is the mean return of the last 100 episodes of training that had"
            " ended by the checkpoint's step; the rest are the measures above, of the same episodes.",
            "",
            "| run | steps | last 100 | steps an episode | flags reached an episode | speed toward the flag or target"
            " (m/s) | falls (knock-downs) an episode | got up (times down) | steps to get up |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for run in runs:
            name = run_name(run)
            if name not in kept:
                continue
            for rows, step in [
                (kept[name], int(kept[name][0]["step"])),
                (last.get(name), int(run.meta["global_step"])),
            ]:
                cells = [name.replace("__", ", "), f"{step:,}", fmt(score_at(run, step))]
                lines.append("| " + " | ".join(cells + (measure_cells(name, rows) if rows else ["–"] * 6)) + " |")
    return lines


def film_table(folder, level):
    """What each film's frames show (video/<run>.csv, by roboschool_measures.py --film, and video/<label>/<run>.csv of
    a checkpoint kept midway, just before it), where it says."""
    video = Path(folder) / "video"
    films = sorted([*video.glob("*.csv"), *video.glob("*/*.csv")], key=lambda path: (path.stem, path.parent == video))
    if not films:
        return []
    lines = [
        "",
        f"{level} What the films show",
        "",
        "Each frame of each film, by the camera's projection (a part hidden behind another still counts): the body's"
        " height in the frame (head to feet, as a share of the frame's), the flag in frame when it is within 8 m of"
        " the body, and the cube in frame while it flies.",
        "",
        "| film | frames | body's height in frame: median (5th percentile) | flag within 8 m: frames in frame"
        " | cube in flight: frames in frame |",
        "|---|---|---|---|---|",
    ]
    for path in films:
        with open(path) as f:
            (row,) = csv.DictReader(f)
        flag = f"{row['flag_seen']} of {row['flag_near']}"
        cube = f"{row['cube_seen']} of {row['cube_flying']}" if "FlagrunHarder" in path.stem else "–"
        span = f"{float(row['body_span_median']):.2f} ({float(row['body_span_p5']):.2f})"
        at = f", at {path.parent.name}" if path.parent != video else ""
        lines.append(f"| {path.stem.replace('__', ', ')}{at} | {row['frames']} | {span} | {flag} | {cube} |")
    return lines


def earlier_folder(folder):
    """The folder of the same runs on the earlier rules, at the same budget, or None."""
    name = suite_name(folder)
    if name not in EARLIER:
        return None
    other = Path(folder).parent / (EARLIER[name][0] + Path(folder).name.removeprefix(name))
    return other if other.is_dir() else None


def rules_table(folder, runs, level):
    """Each run beside the same seed and settings on the body before its own (EARLIER), at the earlier run's budget:
    the score and, where both were measured, flags reached an episode and, for FlagrunHarder, the get-ups. A longer run
    here is taken at the checkpoint that run.py kept at or just past that budget: its score then, and that checkpoint's
    measures."""
    from results import load_runs

    other = earlier_folder(folder)
    if other is None:
        return []
    earlier = {(r.env_id, r.variant, r.seed): r for r in load_runs(other)}
    _, heading, before_body, (then, now, then_short, now_short) = EARLIER[suite_name(folder)]
    measures, midway = (read_measures(folder), read_measures(other)), read_midway(folder)
    lines = [
        "",
        f"{level} {heading}",
        "",
        f"The same seed and settings on {before_body}, in `benchmarks/results/{other.name}`, at the earlier"
        " run's budget. A longer run here is taken at the checkpoint that run.py kept at or just past that step (its"
        " step in brackets): the mean return of its last 100 episodes that had ended by then, and that checkpoint's"
        " measures. Its log std, annealed over its own budget, was then at a different point of its schedule. Flags"
        " and get-ups are measured on each run's own rules.",
        "",
        f"| env | setting | seed | steps | {then}: last 100 | {now}: last 100 | {then_short}: flags an episode |"
        f" {now_short}: flags an episode | {then_short}: got up (times down) | {now_short}: got up (times down) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        before = earlier.get((run.env_id, run.variant, run.seed))
        steps = int(before.meta["global_step"]) if before else None
        if before is None or int(run.meta["global_step"]) < steps:
            continue
        name = run_name(run)
        score, rows = fmt(run.score), measures[0].get(name, [])
        if int(run.meta["global_step"]) > steps:  # at the checkpoint kept at or just past the earlier run's budget
            kept = [m[name] for m in midway.values() if name in m and int(m[name][0]["step"]) >= steps]
            rows = min(kept, key=lambda m: int(m[0]["step"])) if kept else []
            at = int(rows[0]["step"]) if rows else steps
            score = f"{fmt(score_at(run, at))} (at {at:,})"
        both = [measures[1].get(name, []), rows]
        flag_cells = [f"{flags(x):.2f}" if x and has_flags(name) else "–" for x in both]
        ups = ["{} ({})".format(*got_up(x)) if x and can_get_up(name) else "–" for x in both]
        cells = [run.env_id, run.variant, str(run.seed), f"{steps:,}", fmt(before.score), score, *flag_cells, *ups]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and its curves; returns the markdown."""
    return scores.write_report(folder, runs, reference, results, tables, RULE, COLUMNS["roboschool"])


def readme_lines(folder, results, reference, full):
    """The suite's lines in a README's Results block (scores.readme_lines)."""
    from results import load_runs

    return scores.readme_lines(folder, load_runs(folder), results, reference, full, tables, summary)
