"""Every benchmark suite in one place: what runs (the grid of run.py) and the constants its report needs (report.py).
A new suite is an entry in SUITES, whose `report` names its module in benchmarks/reports/.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field

# The paper's 7 MuJoCo tasks (§6.1 used gym's -v1), in today's -v5, except InvertedDoublePendulum: its -v5 pays no
# healthy reward on the step that falls, unlike the paper's -v1, and -v4 keeps -v1's reward (the shortfalls suite
# measured the difference; benchmarks/README.md).
MUJOCO = [
    "HalfCheetah-v5",
    "Hopper-v5",
    "InvertedDoublePendulum-v4",
    "InvertedPendulum-v5",
    "Reacher-v5",
    "Swimmer-v5",
    "Walker2d-v5",
]

# KTO's weights for a tenth of the desirable responses: lambda_D 10, lambda_U 1.
KTO_TENTH = ["--kto-weights", "10", "1"]

# The paper's Table 4 (§6.3), as flags of ppo_continuous.py: what is not here is Table 3's (the script's defaults).
TABLE4 = shlex.split(
    "--num-envs 32 --num-steps 512 --update-epochs 15 --minibatch-size 4096"
    " --anneal-logstd -0.7 -1.6 --no-anneal-lr --lr-target-kl 0.01"
)
# Table 4's 128 actors, which the paper gave its flagrun tasks.
TABLE4_128 = [("128" if flag == "32" else flag) for flag in TABLE4]
# The paper's three humanoid tasks with Roboschool's rules on MuJoCo, loaded by gymnasium's module:id form.
ROBOSCHOOL = [
    f"roboschool_humanoid:{task}-v0" for task in ("HumanoidForward", "HumanoidFlagrun", "HumanoidFlagrunHarder")
]


@dataclass
class Suite:
    variants: dict[str, tuple[str, list[str]]]  # name -> (script, flags)
    envs: list[str]
    seeds: list[int]
    total_timesteps: int
    about: str = ""
    only: dict[str, tuple[list[str], list[int]]] = field(
        default_factory=dict
    )  # variant -> the envs and seeds it runs on
    env_flag: str | None = "--env-id"  # how the script takes the env; None: the "env" is only the runs' label
    budget_flag: str = "--total-timesteps"  # how the script takes the budget
    report: str = "mujoco"  # the module of benchmarks/reports/ that writes its report.md and README lines
    ranks: dict[str, int] = field(default_factory=dict)  # variant -> torchrun's processes for one run (else 1)
    in_readme: bool = False  # whether README.md's Results block summarizes it (at its own budget)
    rules: str = ""  # the envs' rules, when a module of ours defines them: runs on other rules are not the same runs
    keep_checkpoints: dict[str, int] = field(default_factory=dict)  # label -> step: run.py keeps checkpoint_<label>.pt
    budgets: dict[str, int] = field(default_factory=dict)  # variant -> its own total_timesteps, in the suite's folder

    def budget(self, variant):
        """The variant's own budget, else the suite's."""
        return self.budgets.get(variant, self.total_timesteps)


SUITES = {
    "mujoco": Suite(
        {"clip0.2": ("ppo_continuous.py", [])},
        MUJOCO,
        [1, 2, 3],
        1_000_000,
        "ppo_continuous.py defaults (the paper's Table 3, clip 0.2)",
        in_readme=True,
    ),
    # Table 1: every row keeps the other hyperparameters at ppo_continuous.py's defaults. The KL rows
    # start at beta = 1, as the paper's did. "No clipping or penalty" is the KL script with beta 0.
    "table1": Suite(
        {
            "no-clip": ("ppo_kl_penalty.py", ["--init-beta", "0", "--no-adaptive-beta"]),
            "clip0.1": ("ppo_continuous.py", ["--clip-coef", "0.1"]),
            "clip0.2": ("ppo_continuous.py", []),
            "clip0.3": ("ppo_continuous.py", ["--clip-coef", "0.3"]),
            "kl0.003": ("ppo_kl_penalty.py", ["--kl-target", "0.003"]),
            "kl0.01": ("ppo_kl_penalty.py", []),
            "kl0.03": ("ppo_kl_penalty.py", ["--kl-target", "0.03"]),
            "beta0.3": ("ppo_kl_penalty.py", ["--init-beta", "0.3", "--no-adaptive-beta"]),
            "beta1": ("ppo_kl_penalty.py", ["--init-beta", "1", "--no-adaptive-beta"]),
            "beta3": ("ppo_kl_penalty.py", ["--init-beta", "3", "--no-adaptive-beta"]),
            "beta10": ("ppo_kl_penalty.py", ["--init-beta", "10", "--no-adaptive-beta"]),
        },
        MUJOCO,
        [1, 2, 3],
        1_000_000,
        "the paper's Table 1 rows; everything else at the scripts' defaults",
        report="table1",
        in_readme=True,
    ),
    # Does the collapse of beta at the end of the adaptive-KL runs matter? The same row with the lr held constant.
    "beta_collapse": Suite(
        {"kl0.01": ("ppo_kl_penalty.py", []), "kl0.01-const-lr": ("ppo_kl_penalty.py", ["--no-anneal-lr"])},
        ["Hopper-v5"],
        [1, 2, 3],
        1_000_000,
        "adaptive KL d_targ 0.01, with and without lr annealing",
    ),
    # Why InvertedDoublePendulum-v5 and Swimmer fall short of the paper: three hypotheses against the default. The env's
    # version (the default on IDP-v4, the paper's -v1 task), lr annealing (on both), and the discount (on Swimmer).
    "shortfalls": Suite(
        {
            "clip0.2": ("ppo_continuous.py", []),
            "const-lr": ("ppo_continuous.py", ["--no-anneal-lr"]),
            "gamma0.999": ("ppo_continuous.py", ["--gamma", "0.999"]),
        },
        ["InvertedDoublePendulum-v5", "Swimmer-v5", "InvertedDoublePendulum-v4"],
        [1, 2, 3],
        1_000_000,
        "ppo_continuous.py defaults (also on IDP-v4), without lr annealing, and with gamma 0.999 on Swimmer",
        only={
            "const-lr": (["InvertedDoublePendulum-v5", "Swimmer-v5"], [1, 2, 3]),
            "gamma0.999": (["Swimmer-v5"], [1, 2, 3]),
        },
    ),
    # The paper trained Atari for 10M agent steps (40M frames); here 1M, a tenth. The peer at the same budget is
    # SB3's PPO with the RL Zoo's Atari hyperparameters, on the two games where we trail it. vf0.5 is the
    # arm V: the value term weighed as the paper's code (baselines pposgd_simple, da99706) weighed it. e4 is
    # arm E: 4 epochs per update, as CleanRL, ppo2 and the RL Zoo use, where Table 5 says 3. novclip is arm C: L^VF
    # unclipped, as eq. (9) writes it and SB3 computes it, on Pong, which has no lives. zoo has all three of the RL
    # Zoo's settings that differ from ours: if it trails SB3 too, the gap is not in the hyperparameters.
    "atari": Suite(
        {
            "ppo": ("ppo_atari.py", ["--compile"]),
            "vf0.5": ("ppo_atari.py", ["--compile", "--vf-coef", "0.5"]),
            "e4": ("ppo_atari.py", ["--compile", "--update-epochs", "4"]),
            "novclip": ("ppo_atari.py", ["--compile", "--no-clip-vloss"]),
            "zoo": ("ppo_atari.py", ["--compile", "--update-epochs", "4", "--vf-coef", "0.5", "--no-clip-vloss"]),
            "sb3": ("benchmarks/sb3_atari.py", []),
        },
        ["PongNoFrameskip-v4", "BreakoutNoFrameskip-v4", "BeamRiderNoFrameskip-v4"],
        [1, 2, 3],
        1_000_000,
        "ppo_atari.py defaults (the paper's Table 5) with --compile, alpha annealed over the budget; the same with"
        " --vf-coef 0.5, with --update-epochs 4, with --no-clip-vloss, and with all three; SB3's PPO (RL Zoo) too",
        only={
            "vf0.5": (["PongNoFrameskip-v4", "BreakoutNoFrameskip-v4"], [1, 2, 3]),
            "e4": (["PongNoFrameskip-v4", "BreakoutNoFrameskip-v4"], [1, 2, 3]),
            "novclip": (["PongNoFrameskip-v4"], [1, 2, 3]),
            "zoo": (["PongNoFrameskip-v4", "BreakoutNoFrameskip-v4"], [1, 2, 3]),
            "sb3": (["PongNoFrameskip-v4", "BreakoutNoFrameskip-v4"], [1, 2, 3]),
        },
        report="atari",
        in_readme=True,
    ),
    # RLHF: beta of the KL penalty to pi_SFT fixed at 0 (no leash), 0.01, 0.05 (the default) and
    # 0.2, or adapted by Ziegler et al.'s controller toward 2 nats from 0.05; the three group baselines in place of the
    # critic and GAE (GRPO, Dr. GRPO, RLOO) at beta 0.05; and DPO at the beta of Rafailov et al.'s experiments, 0.1,
    # and at 0.5 (on seed 4, DPO's KL grew past 20 nats at beta 0.05 and settled near 6 at 0.5); and IPO,
    # DPO's pairs with Azar et al.'s bounded squared loss, at DPO's 0.1.
    # Best-of-N from pi_SFT, which trains nothing, is benchmarks/best_of_n.py on each seed's stages 1 and 2.
    # "reviews" is the script's own language, not an env; the budget is in responses. Each run trains its own stages 1
    # and 2, which depend only on the seed.
    "rlhf": Suite(
        {
            "beta0": ("ppo_rlhf.py", ["--kl-coef", "0"]),
            "beta0.01": ("ppo_rlhf.py", ["--kl-coef", "0.01"]),
            "beta0.05": ("ppo_rlhf.py", []),
            "beta0.2": ("ppo_rlhf.py", ["--kl-coef", "0.2"]),
            "adaptive": ("ppo_rlhf.py", ["--adaptive-kl"]),
            "grpo": ("ppo_rlhf.py", ["--advantage", "grpo"]),
            "dr-grpo": ("ppo_rlhf.py", ["--advantage", "dr-grpo"]),
            "rloo": ("ppo_rlhf.py", ["--advantage", "rloo"]),
            "dpo0.1": ("ppo_rlhf.py", ["--dpo", "--kl-coef", "0.1"]),
            "dpo0.5": ("ppo_rlhf.py", ["--dpo", "--kl-coef", "0.5"]),
            "ipo0.1": ("ppo_rlhf.py", ["--dpo", "--ipo", "--kl-coef", "0.1"]),
            # KTO at beta 0.1, DPO's; and with a tenth of the desirable responses, weighted 10 so that
            # lambda_D n_D / (lambda_U n_U) stays 1, in the range [1, 4/3] its paper recommends for imbalanced data
            "kto0.1": ("ppo_rlhf.py", ["--kto", "--kl-coef", "0.1"]),
            "kto0.1-tenth": ("ppo_rlhf.py", ["--kto", "--kl-coef", "0.1", "--kto-desirable-share", "0.1"] + KTO_TENTH),
            # Process supervision: a reward model fitted to each clause's gold on the outcome RM's responses, its
            # scores at the clauses' closing tokens, at the default beta, beside beta0.05 (the outcome RM)
            "process": ("ppo_rlhf.py", ["--reward", "process"]),
        },
        ["reviews"],
        [1, 2, 3],
        12_800,
        "ppo_rlhf.py with beta 0, 0.01, 0.05 (its default) and 0.2, the adaptive controller toward 2 nats, GRPO's,"
        " Dr. GRPO's and RLOO's advantages at beta 0.05, DPO at beta 0.1 and 0.5, IPO and KTO at 0.1, and a process"
        " reward model at 0.05",
        env_flag=None,
        budget_flag="--total-episodes",
        report="rlhf",
    ),
    # Over-optimization as Gao et al. 2022 (arXiv:2210.10760) measured it: runs long enough to pass the gold
    # peak, at beta 0 and at the default 0.05, and beta 0 with reward models from 1,024, 4,096 (the default) and 16,384
    # pairs. The length, 8 times the rlhf suite's, is that of pilot runs on seed 4, outside the reported seeds (their
    # results and what they showed: rlhf-long_102400/, and this suite's report).
    # Best-of-N from each seed's pi_SFT and each reward model is benchmarks/best_of_n.py on the runs' stages 1 and 2.
    "rlhf-long": Suite(
        {
            "beta0": ("ppo_rlhf.py", ["--kl-coef", "0"]),
            "beta0.05": ("ppo_rlhf.py", []),
            "rm1024-beta0": ("ppo_rlhf.py", ["--rm-pairs", "1024", "--kl-coef", "0"]),
            "rm16384-beta0": ("ppo_rlhf.py", ["--rm-pairs", "16384", "--kl-coef", "0"]),
            # Process supervision at beta 0, beside beta0: does a reward per clause over-optimize, and onto what?
            "process-beta0": ("ppo_rlhf.py", ["--reward", "process", "--kl-coef", "0"]),
            # Reward-model ensembles (Coste et al. 2023): 4 RMs on the default 4,096 pairs, at beta 0. The mean, and
            # the worst case (min) or the uncertainty-weighted mean (uwo), whichever peaked higher in gold over windows
            # of 20 iterations in a pilot of seed 4 at half the length (rlhf-long_51200/); seeds 1-3. Each member
            # draws its data order and its score head from a seed of its own, as Coste et al.'s do. The -same-head
            # runs are the ablation: members that differ only in their data order (the pilot's members were these).
            # Their CSVs' command lines do not show --rm-same-head: they ran before the flag, when it was the only way.
            "ens4-mean": ("ppo_rlhf.py", ["--rm-ensemble", "4", "--kl-coef", "0"]),
            "ens4-min": ("ppo_rlhf.py", ["--rm-ensemble", "4", "--rm-ensemble-agg", "min", "--kl-coef", "0"]),
            "ens4-mean-same-head": ("ppo_rlhf.py", ["--rm-ensemble", "4", "--rm-same-head", "--kl-coef", "0"]),
            "ens4-min-same-head": (
                "ppo_rlhf.py",
                ["--rm-ensemble", "4", "--rm-ensemble-agg", "min", "--rm-same-head", "--kl-coef", "0"],
            ),
            "ens4-uwo-same-head": (
                "ppo_rlhf.py",
                ["--rm-ensemble", "4", "--rm-ensemble-agg", "uwo", "--rm-same-head", "--kl-coef", "0"],
            ),
            # A reward model that keeps learning on the policy's own text (iterated online RLHF), at beta 0: every 8
            # iterations, pairs of the policy's responses to 64 prompts labelled by gold, for the outcome RM and for
            # the process RM. Stage 2's 4,096 comparisons and 200 refreshes of 64 come to 16,896, about
            # rm16384-beta0's 16,384: the two compare at about equal labels.
            "refresh8-beta0": ("ppo_rlhf.py", ["--rm-refresh", "8", "--kl-coef", "0"]),
            "process-refresh8-beta0": ("ppo_rlhf.py", ["--reward", "process", "--rm-refresh", "8", "--kl-coef", "0"]),
        },
        ["reviews"],
        [1, 2, 3],
        102_400,
        "ppo_rlhf.py past the gold peak: beta 0 and 0.05, beta 0 with reward models from 1,024 and 16,384 pairs, and"
        " with ensembles of 4 (their mean, their minimum), with a process reward model, and with the outcome and the"
        " process reward models refreshed on the policy's text every 8 iterations",
        env_flag=None,
        budget_flag="--total-episodes",
        report="overoptimization",
        # the pilot chose min by the rule above (rlhf-long_51200/report.md has both peaks); uwo ran only there
        only={"ens4-uwo-same-head": (["reviews"], [4])},
    ),
    # The paper's Figure 3: the algorithms PPO was compared with, on the mujoco suite's tasks and budget.
    # A2C is Stable-Baselines3's, TRPO sb3-contrib's, each with the RL Zoo's hyperparameters for the task (SB3's
    # defaults where the Zoo has none; benchmarks/sb3_mujoco.py). PPO's curves are the mujoco suite's runs.
    "figure3": Suite(
        {
            "a2c": ("benchmarks/sb3_mujoco.py", ["--algo", "a2c"]),
            "trpo": ("benchmarks/sb3_mujoco.py", ["--algo", "trpo"]),
        },
        MUJOCO,
        [1, 2, 3],
        1_000_000,
        "SB3's A2C and sb3-contrib's TRPO with the RL Zoo's hyperparameters, beside the mujoco suite's PPO",
        report="figure3",
    ),
    # The paper's §6.3 humanoid showcase: Table 4 on Humanoid-v5, the maintained stand-in for
    # RoboschoolHumanoid. 32 actors, T 512, 15 epochs, minibatch 4,096, gamma 0.99, lambda 0.95 (the defaults), the log
    # std annealed from -0.7 to -1.6, and the step size adapted to a KL target the paper does not give (0.01).
    # table4-2ranks: the same run in 2 processes under torchrun, each stepping 16 of the 32 actors, as the
    # paper's own code ran its actors over MPI; seeds 1-3.
    "humanoid": Suite(
        {"table4": ("ppo_continuous.py", TABLE4), "table4-2ranks": ("ppo_continuous.py", TABLE4)},
        ["Humanoid-v5"],
        [1, 2, 3],
        10_010_624,  # 611 batches of 32 x 512: the first whole batch past 10M steps
        "ppo_continuous.py with the paper's Table 4 (32 actors, T 512, 15 epochs, minibatch 4,096, log std annealed"
        " from -0.7 to -1.6, lr adapted toward KL 0.01)",
        only={"table4-2ranks": (["Humanoid-v5"], [1, 2, 3])},
        ranks={"table4-2ranks": 2},
        report="humanoid",
        in_readme=True,
    ),
    # Figure 4's three tasks, each run in 2 processes under torchrun: the forward walk with Table 4's 32
    # actors, the flagrun tasks with its 128. 50M steps (the figure's flagrun axes reach 100M) for seed 1 of the flagrun
    # tasks; the 10M pilots and seeds 2-3 run at --total-timesteps 10027008 (results/roboschool_10027k/).
    "roboschool": Suite(
        {"table4": ("ppo_continuous.py", TABLE4), "table4-128": ("ppo_continuous.py", TABLE4_128)},
        ROBOSCHOOL,
        [1, 2, 3],
        50_003_968,  # 763 batches of 128 x 512: the first whole batch past 50M steps
        "ppo_continuous.py with Table 4 in 2 processes on roboschool_humanoid.py's tasks (128 actors for flagrun), on"
        " the earlier rules: gymnasium's body, its springs and dampers, and the torso origin's height",
        only={"table4": (ROBOSCHOOL[:1], [1, 2, 3]), "table4-128": (ROBOSCHOOL[1:], [1, 2, 3])},
        ranks={"table4": 2, "table4-128": 2},
        report="roboschool",
    ),
    # The same tasks on Roboschool's body as its Bullet read the file: no joint springs, links that never touch their
    # ancestors, the height and the position that Roboschool's rules read. 100M steps, the budget of Figure 4's
    # flagrun axes, for seed 1 of the flagrun tasks; the 10M pilots at --total-timesteps 10027008 sit beside the
    # earlier rules' pilots.
    "roboschool-body": Suite(
        {"table4": ("ppo_continuous.py", TABLE4), "table4-128": ("ppo_continuous.py", TABLE4_128)},
        ROBOSCHOOL,
        [1, 2, 3],
        100_007_936,  # 1,526 batches of 128 x 512: the first whole batch past 100M steps
        "ppo_continuous.py with Table 4 in 2 processes on roboschool_humanoid.py's tasks (128 actors for flagrun), on"
        " Roboschool's body",
        only={"table4": (ROBOSCHOOL[:1], [1, 2, 3]), "table4-128": (ROBOSCHOOL[1:], [1, 2, 3])},
        ranks={"table4": 2, "table4-128": 2},
        report="roboschool",
        rules="Roboschool's body",
        keep_checkpoints={"50M": 50_003_968},  # the first checkpoint past the earlier rules' budget, for the measures
    ),
    # The same tasks on the body measured against Bullet (benchmarks/bullet_body.py): no dampers and no armature,
    # Bullet's masses, centres and inertias, the shoulders' and elbows' long axes emulated, stiffer joint limits, on
    # which Roboschool's own agent gets up (benchmarks/zoo_agent.py). 100M steps for the flagrun tasks, 50M for the
    # forward walk, seed 1 first.
    "roboschool-bullet": Suite(
        {"table4": ("ppo_continuous.py", TABLE4), "table4-128": ("ppo_continuous.py", TABLE4_128)},
        ROBOSCHOOL,
        [1, 2, 3],
        100_007_936,  # 1,526 batches of 128 x 512: the first whole batch past 100M steps
        "ppo_continuous.py with Table 4 in 2 processes on roboschool_humanoid.py's tasks (128 actors for flagrun), on"
        " the body measured against Bullet",
        only={"table4": (ROBOSCHOOL[:1], [1, 2, 3]), "table4-128": (ROBOSCHOOL[1:], [1, 2, 3])},
        ranks={"table4": 2, "table4-128": 2},
        report="roboschool",
        rules="the body measured against Bullet",
        in_readme=True,
        keep_checkpoints={"50M": 50_003_968},
        budgets={"table4": 50_003_968},  # 3,052 batches of 32 x 512: the forward walk's, as in the earlier rules' suite
    ),
}


# The published per-env figures each kind of suite shows: (column in the data file, heading, setting).
COLUMNS = {
    "mujoco": [
        ("paper_fig3", "paper, Fig. 3 (approx.)", "clip0.2"),
        ("cleanrl_1M", "CleanRL 1M (-v4)", "clip0.2"),
        ("baselines_ppo2_1M", "baselines ppo2 1M", "clip0.2"),
    ],
    "table1": [
        ("paper_fig3", "paper, Fig. 3 (approx.; clip 0.2)", "clip0.2"),
        ("cleanrl_1M", "CleanRL 1M (-v4; clip 0.2)", "clip0.2"),
    ],
    "humanoid": [
        ("cleanrl_1M", "CleanRL 1M (-v4; 1 env, Table 3's settings)", "clip0.2"),
        ("samplefactory_humanoid", "Sample Factory APPO (-v4; its trained agent)", "appo"),
    ],
    "roboschool": [("paper_fig4", "paper, Fig. 4 (Roboschool, read from the plot near 100M steps)", "table4-128")],
    "atari": [
        ("paper_table6", "paper, Table 6: last 100 at 10M steps (10x our budget)", "default"),
        ("cleanrl_atari_10M", "CleanRL: last 100 at 10M steps (10x our budget)", "default"),
    ],
}
# What each Atari variant is, for the table's headings.
ATARI_NAMES = {
    "ppo": "ours",
    "vf0.5": "ours, --vf-coef 0.5",
    "e4": "ours, --update-epochs 4",
    "novclip": "ours, --no-clip-vloss",
    "zoo": "ours with the RL Zoo's hyperparameters (--update-epochs 4 --vf-coef 0.5 --no-clip-vloss)",
    "sb3": "SB3 PPO (RL Zoo)",
    "default": "ours at 13a1a4a (L^VF halved, before the paper's c1 = 1 and fixed value clip)",
}


# The paper's Figure 3: PPO is the mujoco suite's default runs, the peers are the figure3 suite's.
FIGURE3_NAMES = {"ppo": "PPO (ours)", "a2c": "A2C (SB3)", "trpo": "TRPO (sb3-contrib)"}
FIGURE3_MISSING = (
    "Not reproduced: the paper's Figure 3 also has CEM, vanilla policy gradient with an adaptive step size, and A2C"
    " with a trust region. No maintained library we can install has them, and benchmarks/reference_figures.csv has"
    " no figures for them: the paper gives its curves as plots only."
)


# The README's Atari block: ours at the defaults, ours with the three settings in which the RL Zoo's differ from
# ours, and SB3's PPO with the RL Zoo's settings.
README_ATARI_VARIANTS = ("ppo", "zoo", "sb3")


# The envs of our Table 1: four of the paper's seven, for compute.
TABLE1_ENVS = ["HalfCheetah-v5", "Hopper-v5", "InvertedPendulum-v5", "Reacher-v5"]
