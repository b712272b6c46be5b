"""Every example in the README runs as written.

Each line of the README's ```bash / ```sh blocks is run in a fresh shell, in a scratch folder that
sees the repository's data/ and examples/ (so outputs land in the scratch folder), with the
project's `jaxland` and `python` first on PATH. Commands run in order, so a later example may use
an earlier one's output (`predict` reads what `fit` wrote). Each ```python block runs in its own
interpreter, because `import jaxland` changes global JAX state. They share the test session's
compilation cache (tests/conftest.py): a landing an earlier test compiled is read back, not
compiled again (the sizes in the README's examples match some tests' for that reason); results
are the same either way.

Two commands are not run literally:
- `make test` is skipped: it runs this test suite, which would recurse.
- `make demo` would (re)install the virtual environment; its recipe from the Makefile is run
  instead, with `$(VENV)/bin/` pointing at the interpreter running these tests.
"""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BIN = Path(sys.executable).parent
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def blocks(text: str, languages: tuple[str, ...]) -> list[str]:
    return [body for lang, body in FENCE.findall(text) if lang in languages]


def commands(block: str) -> list[str]:
    """The commands of a shell block: comment-only and blank lines dropped, backslash
    continuations joined."""
    out, pending = [], ""
    for line in block.splitlines():
        line = pending + line
        if line.rstrip().endswith("\\"):
            pending = line.rstrip()[:-1] + " "
            continue
        pending = ""
        if line.strip() and not line.lstrip().startswith("#"):
            out.append(line.strip())
    return out


def make_recipe(target: str) -> list[str]:
    """The recipe lines of a Makefile target, with $(VENV)/bin/ resolved to this interpreter's
    bin folder."""
    lines = (ROOT / "Makefile").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if re.match(rf"^{target}\s*:", line))
    recipe = []
    for line in lines[start + 1:]:
        if not line.startswith("\t"):
            break
        recipe.append(line.strip().replace("$(VENV)/bin/", f"{BIN}/"))
    return recipe


def shell_examples() -> list[str]:
    return [c for b in blocks(README.read_text(), ("bash", "sh", "shell")) for c in commands(b)]


def to_run(command: str) -> list[str]:
    """What running ``command`` as written means here (see the module docstring)."""
    words = shlex.split(command, comments=True)
    if words[:2] == ["make", "test"]:
        return []  # the suite itself: running it here would recurse
    if words[:1] == ["make"]:
        return [c for target in words[1:] for c in make_recipe(target)]
    return [command]


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    """A working folder that sees the repository's inputs; outputs stay inside it."""
    work = tmp_path_factory.mktemp("readme")
    for name in ("data", "examples", "benchmarks"):
        (work / name).symlink_to(ROOT / name)
    return work


def _env():
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
               MPLBACKEND="Agg")
    env.pop("XLA_FLAGS", None)  # as a user's shell would have it
    return env


def test_readme_has_the_two_commands_and_examples():
    examples = shell_examples()
    assert "make demo" in " ".join(examples) and "make test" in " ".join(examples)
    assert any(c.startswith("jaxland simulate") for c in examples)
    assert blocks(README.read_text(), ("python",))


def test_readme_is_short():
    assert len(README.read_text().splitlines()) <= 250


def test_make_demo_is_jaxland_simulate():
    assert make_recipe("demo") == [f"{BIN}/jaxland simulate --out out/paper-drop"]


def test_shell_examples_run_as_written(scratch):
    ran = []
    for example in shell_examples():
        for command in to_run(example):
            proc = subprocess.run(["bash", "-c", command], cwd=scratch, env=_env(),
                                  capture_output=True, text=True, timeout=600)
            assert proc.returncode == 0, (
                f"README example failed (exit {proc.returncode}): {example}\n"
                f"ran: {command}\n{proc.stdout[-1500:]}\n{proc.stderr[-3000:]}")
            ran.append(command)
    assert ran
    demo = scratch / "out" / "paper-drop"
    assert {"trajectory.csv", "summary.json", "vehicle.toml"} <= {p.name for p in
                                                                   demo.iterdir()}


def test_python_examples_run_as_written(scratch):
    for i, block in enumerate(blocks(README.read_text(), ("python",))):
        proc = subprocess.run([sys.executable, "-c", block], cwd=scratch, env=_env(),
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"README python block {i} failed:\n{proc.stderr[-3000:]}"
