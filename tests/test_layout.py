"""The scripts paste into any project: one idea per line, citations one grep finds, and train() leaves the process as
it found it, whether it returns or raises."""

import ast
import re
import signal

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


@pytest.mark.parametrize("script", ENV_SCRIPTS)
def test_train_restores_the_process_when_it_raises(script, tmp_path, monkeypatch):
    module = load_script(script)
    monkeypatch.setattr(module, "make_envs", failing_envs)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    threads = torch.get_num_threads()
    args = module.Args(env_id=TINY[script]["env_id"], torch_threads=threads + 1, run_dir=str(tmp_path / "run"))
    with pytest.raises(RuntimeError, match="the envs failed to start"):
        module.train(args)
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers
    assert torch.get_num_threads() == threads


@pytest.mark.parametrize("script", ENV_SCRIPTS)
def test_a_stop_is_an_exception_and_leaves_the_process_as_it_was(script, tmp_path, monkeypatch):
    # SIGINT during a run: train() saves, then raises the script's Stopped, never SystemExit; main() maps it to 130.
    module = load_script(script)
    real_compute_gae = module.compute_gae

    def interrupted(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)
        return real_compute_gae(*args, **kwargs)

    monkeypatch.setattr(module, "compute_gae", interrupted)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    threads = torch.get_num_threads()
    flags = dict(zip(TINY[script]["tiny"][::2], TINY[script]["tiny"][1::2], strict=True))
    fields = {name[2:].replace("-", "_"): value for name, value in flags.items()}
    defaults = module.Args()
    fields = {name: type(getattr(defaults, name))(value) for name, value in fields.items()}
    args = module.Args(env_id=TINY[script]["env_id"], **fields, torch_threads=1, run_dir=str(tmp_path / "run"))
    with pytest.raises(module.Stopped, match="--resume"):
        module.train(args)
    assert (tmp_path / "run" / "checkpoint.pt").exists()
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers
    assert torch.get_num_threads() == threads


@pytest.mark.parametrize("script", scripts_with("process_settings"))
def test_the_compile_setting_is_scoped_to_the_run(script):
    module = load_script(script)
    import torch._inductor.config as inductor

    before = inductor.fallback_random
    with module.process_settings(module.Args(compile=True)):
        assert inductor.fallback_random is True  # compiled code samples with torch's generator, as eager code does
    assert inductor.fallback_random == before
    with module.process_settings(module.Args(compile=False)):
        assert inductor.fallback_random == before
