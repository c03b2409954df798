"""scripts/reproduce.py keeps each part of the bench page in ``--runs`` and, with ``--resume``,
reuses a part only when this checkout measured it: same commit (clean tree), environment and
command, and the run ended. The bench itself is replaced by a stand-in that writes the part's
Markdown the way ``bench_rigs.py --markdown FILE`` does, so this runs in milliseconds."""

from __future__ import annotations

import argparse
import json

import pytest
from script_loader import load_script

reproduce = load_script("reproduce")


@pytest.fixture
def bench(monkeypatch, tmp_path):
    """A stand-in for the bench: records each run and writes the Markdown file it was given."""
    calls: list[list[str]] = []

    def fake_run(cmd, log=None):
        calls.append(cmd)
        md = cmd[cmd.index("--markdown") + 1]
        with open(md, "w") as f:
            f.write(f"<!-- table: families -->\n| run {len(calls)} |\n")
        return "", 0.0

    monkeypatch.setattr(reproduce, "_run", fake_run)
    monkeypatch.setattr(reproduce, "_commit", lambda: "abc1234")
    return calls


def _args(resume: bool, jobs: int = 2) -> argparse.Namespace:
    return argparse.Namespace(resume=resume, jobs=jobs)


def test_part_is_kept_and_reused_only_with_resume(bench, tmp_path):
    body, shown = reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, _args(False), tmp_path)
    assert len(bench) == 1 and "| run 1 |" in body
    assert shown.startswith("python scripts/bench_rigs.py ") and "--markdown" not in shown
    stamp = json.loads((tmp_path / "bench_rigs.stamp").read_text())
    assert stamp["commit"] == "abc1234" and stamp["command"] == shown and stamp["measured"] in body
    reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, _args(False), tmp_path)
    assert len(bench) == 2  # without --resume every part runs
    body, _ = reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, _args(True), tmp_path)
    assert len(bench) == 2 and "| run 2 |" in body  # reused: the last run's tables, not rerun


@pytest.mark.parametrize("change", ["commit", "dirty", "command", "environment"])
def test_part_is_rerun_when_the_checkout_differs(bench, tmp_path, monkeypatch, change):
    reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, _args(False), tmp_path)
    args = _args(True)
    if change == "commit":
        monkeypatch.setattr(reproduce, "_commit", lambda: "def5678")
    elif change == "dirty":
        monkeypatch.setattr(reproduce, "_commit", lambda: "abc1234 with uncommitted changes")
    elif change == "command":
        args = _args(True, jobs=1)
    else:
        monkeypatch.setattr(reproduce, "_environment", lambda: "another machine")
    body, _ = reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, args, tmp_path)
    assert len(bench) == 2 and "| run 2 |" in body


def test_interrupted_part_is_not_reused(bench, tmp_path, monkeypatch):
    reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, _args(False), tmp_path)

    def interrupted(cmd, log=None):
        raise SystemExit("reproduce: bench failed")

    monkeypatch.setattr(reproduce, "_run", interrupted)
    with pytest.raises(SystemExit):
        reproduce._bench_part("bench_rigs", reproduce.BENCH_RIGS_ARGS, _args(True, jobs=1), tmp_path)
    assert not (tmp_path / "bench_rigs.stamp").exists()  # the earlier stamp went before the run began


def test_held_out_failure_keeps_the_dev_part(bench, tmp_path, monkeypatch):
    """The page is written from both parts; the dev part's tables stay in --runs when the
    held-out part fails, and a resumed run measures only the held-out part."""
    docs = tmp_path / "docs"
    docs.mkdir()
    real = reproduce._run

    def held_out_fails(cmd, log=None):
        if "--seed" in cmd:
            raise SystemExit("reproduce: held-out part interrupted")
        return real(cmd, log)

    monkeypatch.setattr(reproduce, "_run", held_out_fails)
    with pytest.raises(SystemExit):
        reproduce.section_bench_rigs(_args(False), docs, tmp_path)
    assert (tmp_path / "bench_rigs.stamp").is_file() and not (docs / "bench_rigs.md").exists()
    monkeypatch.setattr(reproduce, "_run", real)
    page = reproduce.section_bench_rigs(_args(True), docs, tmp_path).read_text()
    assert len(bench) == 2  # the dev part once, the held-out part once
    assert "| run 1 |" in page and "| run 2 |" in page and "<!-- table: families_held_out -->" in page
