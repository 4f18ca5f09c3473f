"""The scripts paste into any project: one idea per line, citations one grep finds, main() owns the process and train()
changes nothing global, and each script stays within its budget."""

import ast
import io
import re
import signal
import sys
import tokenize

import pytest
import torch
from conftest import ROOT, TINY, load_script, scripts_with

# Assignments of a tuple of values to a tuple of names that are a true pair, as the paper writes them.
TRUE_PAIRS = {("T", "N")}


def packed_assignments(source):
    """The lines that bind several names to several unrelated values at once (`a, b = x, y`)."""
    packed = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Tuple):
            for target in node.targets:
                if isinstance(target, ast.Tuple):
                    names = tuple(ast.unparse(t) for t in target.elts)
                    if names not in TRUE_PAIRS:
                        packed.append(node.lineno)
    return packed


def test_the_packing_check_can_fail():
    assert packed_assignments("a, b = 1, 2\nT, N = 3, 4\nobs, info = env.reset()\nx = 1, 2\n") == [1]


@pytest.mark.parametrize("path", sorted(ROOT.glob("ppo_*.py")), ids=lambda p: p.name)
def test_one_name_per_assignment(path):
    assert packed_assignments(path.read_text()) == []


@pytest.mark.parametrize(
    "path", sorted([*ROOT.glob("*.py"), *ROOT.glob("tests/*.py"), *ROOT.glob("benchmarks/*.py")]), ids=lambda p: p.name
)
def test_the_formatter_owns_every_line(path):
    text = path.read_text()
    marker = "fmt: " + "skip"  # spelled apart, so that this file passes its own check
    assert marker not in text and "fmt: " + "off" not in text
    assert max(map(len, text.splitlines()), default=0) <= 120


@pytest.mark.parametrize("path", sorted(ROOT.glob("ppo_*.py")), ids=lambda p: p.name)
def test_every_equation_is_cited_as_eq_n(path):
    # "eq. (9)", so that one grep finds them all: not "eq. 9", "Eq 9", "equation 9" or "eqs. 11-12".
    loose = re.findall(r"(?i)\b(?:eqs?\.?\s*\d|equations?\s*\(?\d|eqs\.\s*\()", path.read_text())
    assert loose == []


def failing_envs(*args, **kwargs):
    raise RuntimeError("the envs failed to start")


# The scripts that step gymnasium or ale-py envs; ppo_rlhf.py's own tests check the same of its train().
ENV_SCRIPTS = scripts_with("make_envs")


def process_state():
    return {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}, torch.get_num_threads()


@pytest.mark.parametrize("script", ENV_SCRIPTS)
def test_train_changes_nothing_global_when_it_raises(script, tmp_path, monkeypatch):
    module = load_script(script)
    monkeypatch.setattr(module, "make_envs", failing_envs)
    before = process_state()
    args = module.Args(env_id=TINY[script]["env_id"], torch_threads=before[1] + 1, run_dir=str(tmp_path / "run"))
    with pytest.raises(RuntimeError, match="the envs failed to start"):
        module.train(args)
    assert process_state() == before


def tiny_args(module, script, tmp_path):
    flags = dict(zip(TINY[script]["tiny"][::2], TINY[script]["tiny"][1::2], strict=True))
    fields = {name[2:].replace("-", "_"): value for name, value in flags.items()}
    defaults = module.Args()
    fields = {name: type(getattr(defaults, name))(value) for name, value in fields.items()}
    return module.Args(env_id=TINY[script]["env_id"], **fields, torch_threads=1, run_dir=str(tmp_path / "run"))


@pytest.mark.parametrize("script", ENV_SCRIPTS)
def test_the_stop_flag_ends_the_run_with_a_checkpoint_and_an_exception(script, tmp_path, monkeypatch):
    # main()'s signal handler sets the flag during an iteration: train() saves, then raises Stopped, never SystemExit.
    module = load_script(script)
    real_compute_gae = module.compute_gae
    stop = []

    def interrupted(*args, **kwargs):
        stop.append(signal.SIGINT)
        return real_compute_gae(*args, **kwargs)

    monkeypatch.setattr(module, "compute_gae", interrupted)
    before = process_state()
    with pytest.raises(module.Stopped, match="--resume"):
        module.train(tiny_args(module, script, tmp_path), stop)
    assert torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)["iteration"] == 1
    assert process_state() == before


@pytest.mark.parametrize("script", ENV_SCRIPTS)
def test_main_owns_the_process_and_turns_ctrl_c_into_the_stop_flag(script, tmp_path, monkeypatch):
    module = load_script(script)
    seen = {}

    def train(args, stop):  # Ctrl-C during a run of main()'s: it only sets the flag that train() reads
        signal.raise_signal(signal.SIGINT)
        seen["stop"] = list(stop)
        seen["threads"] = torch.get_num_threads()
        raise module.Stopped("saved")

    monkeypatch.setattr(module, "train", train)
    monkeypatch.setattr(module, "check_args", lambda args: None)
    monkeypatch.setattr(sys, "argv", [script, "--torch-threads", "3"])
    monkeypatch.chdir(tmp_path)  # main() names the run's folder under runs/ in the working directory
    before = process_state()
    try:
        with pytest.raises(SystemExit) as stopped:
            module.main()
    finally:
        for sig, handler in before[0].items():
            signal.signal(sig, handler)
        torch.set_num_threads(before[1])
    assert stopped.value.code == 130 and seen == {"stop": [signal.SIGINT], "threads": 3}


def test_train_has_no_process_settings_to_undo():
    # main() sets the process up once; no script carries machinery that changes it and must undo it.
    for script in ENV_SCRIPTS:
        source = (ROOT / script).read_text()
        train = ast.get_source_segment(
            source, next(n for n in ast.parse(source).body if getattr(n, "name", "") == "train")
        )
        assert "signal." not in train and "set_num_threads" not in train and "_inductor" not in train, script


# The budgets set when the scripts were rewritten for reading, after `ruff format`, comments included: lines, code
# characters (comments, docstrings and blank lines left out, leading spaces stripped) and the lines of train().
# ppo_rlhf.py has a line budget only. --track and the PEP 723 block moved each line budget by 15, and Table 4's flags
# ppo_continuous.py's by 25. The rollout buffer's fields, declared one a line, moved the train() budgets of
# ppo_continuous.py and ppo_atari.py by the 4 lines they added.
BUDGETS = {
    "ppo_continuous.py": {"lines": 590, "code_chars": 16_500, "train": 123},
    "ppo_atari.py": {"lines": 585, "code_chars": 17_500, "train": 124},
    "ppo_kl_penalty.py": {"lines": 615, "code_chars": 17_800, "train": 135},
    "ppo_rlhf.py": {"lines": 715},  # and PPO's successors, with the hack named, moved it by 80
}


def code_chars(source):
    """Characters of code: every line stripped, without its comment, docstring lines and blank lines left out."""
    docstrings = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.FunctionDef | ast.ClassDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                docstrings.update(range(first.lineno, first.end_lineno + 1))
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    comments = {t.start[0]: t.start[1] for t in tokens if t.type == tokenize.COMMENT}
    lines = source.splitlines()
    kept = [line[: comments.get(i, len(line))].strip() for i, line in enumerate(lines, 1) if i not in docstrings]
    return sum(len(line) for line in kept)


def weight(source):
    train = next((n for n in ast.parse(source).body if isinstance(n, ast.FunctionDef) and n.name == "train"), None)
    return {
        "lines": len(source.splitlines()),
        "code_chars": code_chars(source),
        "train": train.end_lineno - train.lineno + 1,
    }


def test_the_weight_can_fail():
    source = '"""Doc."""\n\n\ndef train(args):  # a comment\n    """Doc\n    string."""\n    return args  # why\n'
    assert weight(source) == {"lines": 7, "code_chars": len("def train(args):") + len("return args"), "train": 4}


# Not met yet; strict, so that each fails once it is met and its marker must go. The ceilings below keep the scripts
# from growing past what they reached in the meantime. The lines over the moved budgets, and the code characters,
# hold --track with its offline fallback and the W&B run that --resume continues (about 30 lines a script), and
# Table 4's flags in ppo_continuous.py, and then what each line below lists.
REACHED = {
    # and its redesign for reading: PPO's path first, each successor a function found by name, the logging in a class
    # under MACHINERY, and the traps of a pasted copy removed as in the gym scripts (59 lines)
    ("ppo_rlhf.py", "lines"): 1042,  # DPO, the hack's metrics; run dirs; IPO, one-prompt pairs;
    # KTO and reward-model ensembles (whose budget was 815); KTO's KL batch built from each minibatch, z0
    # logged, and the members' own heads with --rm-same-head, the ablation that reproduces the earlier runs (16);
    # process supervision (whose budget was 40): its labels, its reward model, its rewards at the clauses' ends,
    # its accuracy per clause held out and on the policy's text; --rm-refresh, a reward model that keeps learning on
    # the policy's text with an optimizer of its own, its labels counted, and the loss stage 2 and it share (34)
    # torchrun (the section MANY PROCESSES, the normalizers' merge, one record, the ranks' stops and faults),
    # run dirs made atomically and filming checked before the run; torch._dynamo imported before the group;
    # no line: a dash for the return before the first episode ends (2 characters) and, in the MuJoCo
    # scripts, a module:id whose module is not found refused in one line (15); --compile under torchrun refused in
    # one line (2 lines and 120 characters a script: the compiled graph held the group, and gloo's threads, to the exit)
    # a run folder named without an env id's module: prefix, whose colon breaks scp (15 characters a script, no line);
    # the envs made by the id's own vector env where it has one (6 lines and 250 characters a MuJoCo script)
    # the lesson before the machinery, and the traps of a pasted copy removed: a new flag is free until a range is
    # declared, a flag typed with --resume is applied or refused, a checkpoint with a field Args lost is refused, a
    # renamed copy reads its own checkpoints, any env that renders can be filmed, a rollout quantity is one line (the
    # lines held; about 500 characters a script)
    # a copy's own network, loss term and flags: a checkpoint of another network refused in one line (11 lines), the
    # runtime flags that --resume applies (1), video refused without its writer (2, Atari 3), the rollout buffer's
    # fields one a line (4), the keys of the stats that train() reads (1); ppo_rlhf.py 12 lines for the same
    ("ppo_continuous.py", "lines"): 781,
    ("ppo_continuous.py", "code_chars"): 25_382,
    ("ppo_atari.py", "lines"): 724,
    ("ppo_atari.py", "code_chars"): 23_701,
    ("ppo_kl_penalty.py", "lines"): 795,
    ("ppo_kl_penalty.py", "code_chars"): 25_739,
}
NOT_MET = set(REACHED)
CASES = [
    pytest.param(
        script,
        measure,
        marks=[pytest.mark.xfail(strict=True, reason="not met yet")] if (script, measure) in NOT_MET else [],
        id=f"{script}-{measure}",
    )
    for script in sorted(BUDGETS)
    for measure in BUDGETS[script]
]


@pytest.mark.parametrize("script,measure", CASES)
def test_scripts_stay_within_their_budgets(script, measure):
    if not (ROOT / script).exists():
        pytest.skip(f"no {script}")
    reached = weight((ROOT / script).read_text())[measure]
    assert reached <= BUDGETS[script][measure], f"{script}: {measure} {reached}, budget {BUDGETS[script][measure]}"


@pytest.mark.parametrize("script,measure", sorted(REACHED))
def test_no_script_grows_past_what_it_reached(script, measure):
    assert weight((ROOT / script).read_text())[measure] <= REACHED[script, measure]


@pytest.mark.parametrize("script", ["ppo_continuous.py", "ppo_atari.py", "ppo_kl_penalty.py"])
def test_the_update_ends_within_the_first_330_lines(script):
    """A reader reaches the end of the update's minibatch loop, in train(), by line 330: the lesson comes first."""
    train = next(n for n in ast.parse((ROOT / script).read_text()).body if getattr(n, "name", "") == "train")
    loops = [n for n in ast.walk(train) if isinstance(n, ast.For) and ast.unparse(n.target) == "mb_inds"]
    assert len(loops) == 1 and loops[0].end_lineno <= 330, [n.end_lineno for n in loops]


def test_every_file_in_benchmarks_stays_under_600_lines_and_the_report_modules_import_in_no_circle():
    """The benchmarks' code is read as much as it is run: no file of it passes 600 lines (the rlhf-long report is split
    by what it does: what it measures, its claims, its figure, its account of the rule change). And no report module
    imports, directly or through others, one that imports it back."""
    import ast

    folder = ROOT / "benchmarks"
    files = [p for p in folder.rglob("*.py") if not {"runs", "results"} & set(p.relative_to(folder).parts)]
    long = {str(p.relative_to(ROOT)): n for p in files if (n := len(p.read_text().splitlines())) >= 600}
    assert not long, long
    modules = {p.stem: p for p in (folder / "reports").glob("*.py")}
    imports = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("reports"):
                found |= {node.module.split(".")[1]} if "." in node.module else {a.name for a in node.names}
        imports[name] = found & set(modules)

    def reaches(start, goal, seen=()):
        return any(m == goal or (m not in seen and reaches(m, goal, (*seen, m))) for m in imports[start])

    assert not [name for name in modules if reaches(name, name)]
