"""Each script carries its own dependencies (PEP 723 inline metadata), so that a copied file runs with `uv run`: the
block must pin what requirements.txt pins, and name every package the script imports."""

import ast
import importlib.metadata
import re
import sys
import tomllib

import pytest
from conftest import ROOT, SCRIPTS

# The regular expression of PEP 723's reference implementation.
BLOCK = re.compile(r"(?m)^# /// (?P<type>[a-zA-Z0-9-]+)$\s(?P<content>(^#(| .*)$\s)+)^# ///$")
# Modules that are not their distribution's name: torch.utils.tensorboard needs the tensorboard package.
NEEDS = {"torch.utils.tensorboard": "tensorboard"}


def script_metadata(source):
    """The TOML of the script's `# /// script` block; a ValueError if it has none, or more than one."""
    blocks = [m for m in BLOCK.finditer(source) if m.group("type") == "script"]
    if len(blocks) != 1:
        raise ValueError(f"{len(blocks)} script metadata blocks")
    content = "".join(line[2:] if line.startswith("# ") else line[1:] for line in blocks[0]["content"].splitlines(True))
    return tomllib.loads(content)


def name(requirement):
    """'gymnasium[mujoco]==1.4.0' -> 'gymnasium', as PEP 503 normalizes it."""
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9._-]+", requirement).group()).lower()


def pins(requirements_text):
    """{name: the whole pin} of a requirements file's lines."""
    lines = [line.split("#")[0].strip() for line in requirements_text.splitlines()]
    return {name(line): line for line in lines if line and not line.startswith("-")}


def disagreements(dependencies, requirements_text):
    """The script's dependencies that requirements.txt lacks or pins to another version (extras may differ: the Atari
    script needs gymnasium without MuJoCo)."""
    pinned = {key: re.sub(r"\[.*?\]", "", pin) for key, pin in pins(requirements_text).items()}
    return [dep for dep in dependencies if pinned.get(name(dep)) != re.sub(r"\[.*?\]", "", dep)]


def imported_distributions(source):
    """The distributions whose modules a script imports, anywhere in it (the standard library left out)."""
    modules = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            modules.add(node.module)
    by_module = importlib.metadata.packages_distributions()
    found = set()
    for module in modules:
        top = module.split(".")[0]
        if top in sys.stdlib_module_names:
            continue
        found |= {name(d) for d in by_module.get(top, [top])}
        found |= {NEEDS[m] for m in NEEDS if module == m}
    return found


@pytest.mark.parametrize("script", SCRIPTS)
def test_metadata_pins_what_requirements_pins(script):
    metadata = script_metadata((ROOT / script).read_text())
    assert metadata["requires-python"] == ">=3.11"
    assert disagreements(metadata["dependencies"], (ROOT / "requirements.txt").read_text()) == []


@pytest.mark.parametrize("script", SCRIPTS)
def test_metadata_names_every_package_the_script_imports(script):
    source = (ROOT / script).read_text()
    listed = {name(dep) for dep in script_metadata(source)["dependencies"]}
    assert imported_distributions(source) <= listed


def test_a_pin_changed_in_requirements_alone_is_caught():
    requirements = (ROOT / "requirements.txt").read_text()
    dependencies = script_metadata((ROOT / "ppo_continuous.py").read_text())["dependencies"]
    assert disagreements(dependencies, requirements) == []
    changed = requirements.replace("numpy==2.4.6", "numpy==2.4.7")
    assert disagreements(dependencies, changed) == ["numpy==2.4.6"]
    assert disagreements(dependencies, requirements.replace("tyro==", "# tyro==")) == ["tyro==1.0.17"]


def test_an_import_the_block_lacks_is_caught():
    source = (
        "# /// script\n# dependencies = []\n# ///\nimport numpy\nfrom torch.utils.tensorboard import SummaryWriter\n"
    )
    assert script_metadata(source) == {"dependencies": []}
    assert imported_distributions(source) == {"numpy", "torch", "tensorboard"}
