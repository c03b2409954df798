"""README's blocks run verbatim, from a clone's root and from a folder outside it (issue 22, items 1 and 2).

The install, main-job, test and step-by-step blocks are read from README.md as written. The
step by step runs as a bash script twice: in a fresh clone's root right after its install block
(the clone's ``configs`` folder answers), and in a folder with none (the packaged configs answer
``configs/...``). The main job runs with the quick experiment in place of ``paper.yaml`` (same
command otherwise); the test block is run with ``--collect-only`` (running the suite from inside
the suite would recurse); the install block runs in a copy of the repository (slow: it builds
and installs).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_block(heading: str) -> str:
    """The first ```bash block after ``## heading`` in README.md."""
    text = (ROOT / "README.md").read_text()
    section = text.split(f"\n## {heading}\n", 1)[1]
    match = re.search(r"```bash\n(.*?)```", section, re.S)
    assert match, f"README: no bash block under '## {heading}'"
    return match.group(1)


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def _bash(script: str, cwd: Path, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-e", "-o", "pipefail", "-c", script], cwd=cwd, env=_env(), text=True,
                          capture_output=True, timeout=timeout)


@pytest.mark.parametrize("heading", ["Step by step", "The main job"])
def test_readme_commands_parse(heading):
    """Every microctl line of the block parses as written (``[--json]`` did not, item 1)."""
    from microctl.cli import build_parser

    parser = build_parser()
    lines = [ln for ln in readme_block(heading).splitlines() if ln.startswith("microctl ")]
    assert lines
    for line in lines:
        argv = shlex.split(line, comments=True)[1:]
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # pragma: no cover - the failure message
            pytest.fail(f"README line does not parse (exit {exc.code}): {line}")
        assert args.func


def test_readme_configs_resolve_outside_the_clone(tmp_path, monkeypatch):
    """Every ``configs/...`` path of README's blocks reads from a folder with no ``configs`` (item 2)."""
    from microctl.experiments.config import load_experiment_config
    from microctl.stage.config import load_stage_config

    monkeypatch.chdir(tmp_path)
    text = (ROOT / "README.md").read_text()
    paths = set(re.findall(r"configs/(?:stage|experiments)/\w+\.yaml", text))
    assert paths
    for p in sorted(paths):
        (load_stage_config if "/stage/" in p else load_experiment_config)(p)
    assert load_stage_config("sim_paper").stage == load_stage_config(ROOT / "configs/stage/sim_paper.yaml").stage


def _check_step_by_step(proc: subprocess.CompletedProcess, where: Path) -> None:
    """The step by step ran to its end in ``where``: its outputs are there, its JSON on stdout."""
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert (where / "model_ext.npz").is_file() and (where / "diag" / "report.md").is_file()
    assert '"target_um": 14.0' in proc.stdout  # solve --json's result is on stdout


@pytest.mark.slow
def test_readme_step_by_step_verbatim_outside_the_clone(tmp_path):
    """The step by step in a folder with no ``configs`` (the packaged configs answer). From a
    clone's root it runs in ``test_readme_install_block_in_a_copy``, after the install block."""
    _check_step_by_step(_bash(readme_block("Step by step"), tmp_path, timeout=900), tmp_path)


@pytest.mark.slow
def test_readme_main_job_and_test_blocks(tmp_path):
    main_job = readme_block("The main job")
    assert "microctl experiment configs/experiments/paper.yaml --out runs/paper" in main_job
    proc = _bash(main_job.replace("experiments/paper.yaml", "experiments/quick.yaml"), tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "runs/paper/results.json").is_file() and (tmp_path / "runs/paper/report.md").is_file()
    for line in readme_block("Run the tests").splitlines():
        if line.strip():
            proc = subprocess.run(shlex.split(line.replace("python ", f"{sys.executable} ", 1)) + ["--collect-only"],
                                  cwd=ROOT, capture_output=True, text=True, timeout=600)
            assert proc.returncode == 0, proc.stdout[-2000:]


@pytest.mark.slow
def test_readme_install_block_in_a_copy(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("no git")
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True, timeout=300)
    proc = _bash(readme_block("Install") + "\n" + readme_block("Step by step"), clone, timeout=1800)
    _check_step_by_step(proc, clone)  # the clone's own configs folder answers configs/...
    assert "reachable t" in proc.stdout  # stage show, the block's first line


def test_docs_have_no_dangling_references():
    """No page points at files or threads a reader of the repository cannot open (issue 22 item 12)."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    bad = re.compile(r"`(?:shared/)?spec/[\w.-]+`|notes/[\w.-]+\.md|\bissue \d+\b")
    found = [f"{p.name}: {m.group(0)}" for p in pages for m in bad.finditer(p.read_text())]
    assert not found, found
    for link in re.findall(r"\]\(([^)#:]+)\)", "\n".join(p.read_text() for p in pages[:1])):
        assert (ROOT / link).exists(), f"README links to {link}, which does not exist"


def test_readme_bench_command_names_the_published_methods():
    """README names, verbatim, the command that made the published bench_rigs table (with its --methods)."""
    page = (ROOT / "docs/generated/bench_rigs.md").read_text()
    command = re.search(r"Command: `(python scripts/bench_rigs.py [^`]+)`", page).group(1)
    readme = " ".join((ROOT / "README.md").read_text().split())  # a command may wrap across lines
    assert f"`{command}`" in readme, command
