"""ppo_rlhf.py after a learner pastes it into a project and changes it: a new flag whose default is 0, a flag typed with
--resume, a checkpoint written before a field was renamed, a renamed copy of the file; and the names a reader follows
from each call site to its definition. Each check fails on the script as it was before these traps were removed."""

import ast
import dataclasses
import importlib.util
import subprocess
import sys

import pytest
import torch
from conftest import ONE_THREAD, ROOT, TINY, call_main, load_script, roll_back, run_cli, script_at

SCRIPT = "ppo_rlhf.py"
rlhf = load_script(SCRIPT)


def test_a_new_float_flag_at_zero_is_accepted_unless_a_range_is_declared(tmp_path, monkeypatch):
    @dataclasses.dataclass
    class WithAuxLoss(rlhf.Args):
        aux_coef: float = 0.0  # a learner's new coefficient, off by default

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(rlhf, "Args", WithAuxLoss)  # load_checkpoint and check_args see the learner's Args
    rlhf.check_args(WithAuxLoss())
    rlhf.check_args(WithAuxLoss(aux_coef=-2.5))
    with pytest.raises(ValueError, match="--aux-coef must be a finite number"):
        rlhf.check_args(WithAuxLoss(aux_coef=float("nan")))
    monkeypatch.setitem(rlhf.RANGES, "aux_coef", (0, 1))  # a declared range is checked
    with pytest.raises(ValueError, match=r"--aux-coef must be in \[0, 1\]"):
        rlhf.check_args(WithAuxLoss(aux_coef=-2.5))
    monkeypatch.setattr(rlhf, "POSITIVE", [*rlhf.POSITIVE, "aux_coef"])  # and so is a declared positive one
    with pytest.raises(ValueError, match="--aux-coef must be positive"):
        rlhf.check_args(WithAuxLoss(aux_coef=0.0))


def a_checkpoint(path, module=rlhf, **saved):
    """A stage-3 checkpoint of a run with these hyperparameters, as save_checkpoint writes one, with its networks' fresh
    weights (main() checks their shapes; train(), which these tests replace, would read the rest)."""
    args = module.Args(**{"d_model": 16, "n_layer": 1, "n_head": 2, "seed": 5, "learning_rate": 3e-4, **saved})
    networks = {"reference": module.new_model(args, "cpu").state_dict()}
    networks["reward_model"] = networks["reference"]
    module.save_checkpoint(str(path), "ppo", args, iteration=1, global_step=64, **networks)
    return args


def test_a_hyperparameter_typed_with_resume_is_refused_and_a_runtime_flag_applied(tmp_path, monkeypatch, capsys):
    saved = a_checkpoint(tmp_path / "checkpoint.pt")
    resume = ["--resume", tmp_path / "checkpoint.pt"]
    for typed in (["--learning-rate", "0.123"], ["--seed", "1"]):  # --seed 1 is Args' default, not the run's 5
        assert call_main(rlhf, [*resume, *typed], monkeypatch) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and f"{typed[0]} {typed[1]}" in lines[0] and "resumed run keeps" in lines[0], lines
    # The checkpoint's own value typed again changes nothing; a runtime flag reaches train(); the rest is the run's.
    args = call_main(
        rlhf, [*resume, "--learning-rate", saved.learning_rate, "--save-every", 7, "--device", "cpu"], monkeypatch
    )
    assert (args.save_every, args.device, args.learning_rate, args.seed, args.d_model) == (7, "cpu", 3e-4, 5, 16)
    assert args.run_dir == str(tmp_path) and args.resume == str(tmp_path / "checkpoint.pt")


def test_a_checkpoint_with_a_field_args_no_longer_has_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    a_checkpoint(tmp_path / "checkpoint.pt")
    checkpoint = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    checkpoint["args"]["aux_coef"] = 0.5  # written by a copy that had this flag
    torch.save(checkpoint, tmp_path / "renamed-field.pt")
    assert call_main(rlhf, ["--resume", tmp_path / "renamed-field.pt"], monkeypatch) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "error:" in lines[0] and "aux_coef" in lines[0], lines
    # A field that an older checkpoint lacks takes its default.
    del checkpoint["args"]["aux_coef"], checkpoint["args"]["uwo_coef"]
    torch.save(checkpoint, tmp_path / "older.pt")
    args = call_main(rlhf, ["--resume", tmp_path / "older.pt"], monkeypatch)
    assert args.uwo_coef == rlhf.Args().uwo_coef and args.seed == 5


def renamed_copy(tmp_path, change=("", "")):
    """A copy of the script as my_rlhf.py, imported, with the text change[0] replaced by change[1]."""
    path = tmp_path / "my_rlhf.py"
    path.write_text((ROOT / SCRIPT).read_text().replace(*change))
    spec = importlib.util.spec_from_file_location("my_rlhf", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["my_rlhf"] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


def test_a_renamed_copy_resumes_its_own_and_this_files_checkpoints_and_refuses_another_scripts(tmp_path, monkeypatch):
    copy = renamed_copy(tmp_path)
    a_checkpoint(tmp_path / "by-the-script.pt")
    a_checkpoint(tmp_path / "by-the-copy.pt", copy, seed=6)
    assert copy.load_checkpoint(str(tmp_path / "by-the-script.pt"), copy.Args())[1].seed == 5
    assert copy.load_checkpoint(str(tmp_path / "by-the-copy.pt"), copy.Args())[1].seed == 6
    assert rlhf.load_checkpoint(str(tmp_path / "by-the-copy.pt"), rlhf.Args())[1].seed == 6
    assert call_main(copy, ["--resume", tmp_path / "by-the-script.pt"], monkeypatch).seed == 5
    torch.save({"format": "ppo-checkpoint-v1", "script": "ppo_continuous.py", "args": {}}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a checkpoint written by ppo_rlhf.py"):
        copy.load_checkpoint(str(tmp_path / "foreign.pt"), copy.Args())


def test_a_copy_with_another_network_refuses_the_scripts_checkpoints_in_one_line(tmp_path, monkeypatch, capsys):
    copy = renamed_copy(tmp_path, ("4 * d_model, 0.0", "2 * d_model, 0.0"))  # each block's MLP twice as wide, not 4x
    assert (tmp_path / "my_rlhf.py").read_text() != (ROOT / SCRIPT).read_text()
    saved = a_checkpoint(tmp_path / "checkpoint.pt")
    rlhf.save_checkpoint(str(tmp_path / "sft.pt"), "sft", saved, model=rlhf.new_model(saved, "cpu").state_dict())
    first = "blocks.layers.0.linear1.weight [64, 16] where this script's has blocks.layers.0.linear1.weight [32, 16]"
    network = ["--d-model", 16, "--n-layer", 1, "--n-head", 2]
    for argv in (["--resume", tmp_path / "checkpoint.pt"], ["--sft-checkpoint", tmp_path / "sft.pt", *network]):
        assert call_main(copy, [*argv, "--run-dir", tmp_path / "new"], monkeypatch) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and f"holds another network: {first}" in lines[0], lines
        assert call_main(rlhf, [*argv, "--run-dir", tmp_path / "new"], monkeypatch).d_model == 16  # the script's own
    assert not (tmp_path / "new").exists()


OLD = "45c9356"  # a commit before checkpoints were checked against the networks that read them


def test_a_checkpoint_written_at_the_earlier_commit_resumes(tmp_path):
    old = script_at(OLD, SCRIPT, tmp_path / "old")
    run = [sys.executable, str(old), *TINY[SCRIPT]["tiny"], "--run-dir", str(tmp_path / "run")]
    proc = subprocess.run([*run, *ONE_THREAD], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    path = tmp_path / "run" / "checkpoint.pt"
    checkpoint = roll_back(path)
    proc = run_cli(SCRIPT, "--resume", path, cwd=tmp_path)
    assert f"at step {checkpoint['global_step']:,} (iteration {checkpoint['iteration']})" in proc.stdout, proc.stdout
    assert torch.load(path, weights_only=True)["iteration"] == checkpoint["iteration"] + 1


def aliases(source):
    """Names bound to a function rather than defined: `f = g`, `f = g if c else h`, `f = torch.compile(g)`; a call
    through one names no def that a reader can find."""
    tree = ast.parse(source)
    functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}

    def is_function(value):
        if isinstance(value, ast.IfExp):
            return is_function(value.body) or is_function(value.orelse)
        if isinstance(value, ast.Call) and ast.unparse(value.func) == "torch.compile":
            return True
        return isinstance(value, ast.Name) and value.id in functions

    return [ast.unparse(node) for node in ast.walk(tree) if isinstance(node, ast.Assign) and is_function(node.value)]


def test_the_alias_check_can_fail():
    source = "def f(): ...\ndef g(): ...\nx = f\ny = f if c else g\nz = torch.compile(g)\nw = f()\n"
    assert aliases(source) == ["x = f", "y = f if c else g", "z = torch.compile(g)"]


def test_every_call_site_names_the_function_it_runs():
    assert aliases((ROOT / SCRIPT).read_text()) == []


def test_no_function_takes_a_value_that_it_also_reads_from_args():
    """A function that takes x and reads args.x too has two sources for one value, which a changed call can split."""
    doubled = []
    for node in ast.walk(ast.parse((ROOT / SCRIPT).read_text())):
        if isinstance(node, ast.FunctionDef) and "args" in (params := [a.arg for a in node.args.args]):
            read = {n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute) and ast.unparse(n.value) == "args"}
            doubled += [f"{node.name}({name})" for name in set(params) & read]
    assert doubled == []


def test_each_successor_is_a_function_of_its_own_after_ppos_update_loop():
    """The lesson first: PPO's path ends with train_ppo's update loop; each successor is then found by its name."""
    source = (ROOT / SCRIPT).read_text()
    names = [node.name for node in ast.parse(source).body if isinstance(node, ast.FunctionDef | ast.ClassDef)]
    successors = ["grpo_advantages", "dr_grpo_advantages", "rloo_advantages", "dpo_update", "ipo_loss", "kto_loss"]
    assert all(names.index(name) > names.index("train_ppo") for name in [*successors, "Ensemble"])
    assert source.index("\n# MACHINERY") > max(source.index(f"\ndef {name}(") for name in successors)
    machinery = ["Stopped", "Diverged", "report", "Log", "response_stats", "save_checkpoint", "check_args", "main"]
    assert all(names.index(name) > names.index("Ensemble") for name in machinery)
