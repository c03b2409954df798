"""scripts/reproduce.py's pages: the commands they show, and the bench page's parts.

reproduce.py writes the bench page (docs/generated/bench_rigs.md) in two parts, each
with its own provenance line and command: the page is rewritten as soon as a part ends, and
``--part`` remakes one part while keeping the other's block as it was measured. The bench is
replaced by a stand-in that writes the part's Markdown the way ``bench_rigs.py --markdown FILE``
does, so this runs in milliseconds."""

from __future__ import annotations

import argparse

import pytest
from script_loader import load_script

reproduce = load_script("reproduce")


@pytest.fixture
def bench(monkeypatch):
    """A stand-in for the bench: records each run and writes the Markdown file it was given."""
    calls: list[list[str]] = []

    def fake_run(cmd, log=None):
        calls.append(cmd)
        md = cmd[cmd.index("--markdown") + 1]
        with open(md, "w") as f:
            f.write(f"<!-- table: families -->\n| run {len(calls)} |\n\n<!-- table: data_bar -->\n| bar {len(calls)} |\n")
        return "", 0.0

    monkeypatch.setattr(reproduce, "_run", fake_run)
    return calls


def _args(part=None) -> argparse.Namespace:
    return argparse.Namespace(part=part, jobs=2)


def _dirs(tmp_path):
    docs, runs = tmp_path / "docs", tmp_path / "runs"
    docs.mkdir()
    runs.mkdir()
    return docs, runs


def test_both_parts_each_with_provenance_and_command(bench, tmp_path, monkeypatch):
    docs, runs = _dirs(tmp_path)
    monkeypatch.setattr(reproduce, "_commit", lambda: "abc1234")
    text = reproduce.section_bench_rigs(_args(), docs, runs).read_text()
    assert len(bench) == 2 and "--seed-sets" in bench[0] and "--seed" in bench[1]
    blocks = reproduce.bench_page_parts(text)
    assert list(blocks) == ["dev", "held_out"]
    for name, block in blocks.items():
        assert block.count("commit abc1234") == 1, name
        assert f"`python scripts/bench_rigs.py {' '.join(reproduce.BENCH_PARTS[name][0])} --jobs 2`" in block
    assert "| run 1 |" in blocks["dev"] and "<!-- table: families -->" in blocks["dev"]
    assert "| run 2 |" in blocks["held_out"] and "<!-- table: families_held_out -->" in blocks["held_out"]
    # each part's tables under their own tags: the held-out part's data bar is not the dev part's
    assert "<!-- table: data_bar -->" in blocks["dev"] and "<!-- table: data_bar_held_out -->" in blocks["held_out"]
    assert "<!-- table: data_bar -->" not in blocks["held_out"] and "| bar 2 |" in blocks["held_out"]


def test_one_part_keeps_the_other_as_measured(bench, tmp_path, monkeypatch):
    docs, runs = _dirs(tmp_path)
    monkeypatch.setattr(reproduce, "_commit", lambda: "abc1234")
    dev_before = reproduce.bench_page_parts(reproduce.section_bench_rigs(_args(), docs, runs).read_text())["dev"]
    monkeypatch.setattr(reproduce, "_commit", lambda: "def5678")
    blocks = reproduce.bench_page_parts(reproduce.section_bench_rigs(_args("held_out"), docs, runs).read_text())
    assert len(bench) == 3 and "--seed" in bench[2]  # only the held-out part ran again
    assert blocks["dev"] == dev_before  # kept, with its own commit
    assert "commit def5678" in blocks["held_out"] and "| run 3 |" in blocks["held_out"]


def test_one_part_refused_without_the_other_to_keep(bench, tmp_path):
    docs, runs = _dirs(tmp_path)
    (docs / "bench_rigs.md").write_text("# a page of another layout\n")
    with pytest.raises(SystemExit, match="no 'dev' part to keep"):
        reproduce.section_bench_rigs(_args("held_out"), docs, runs)
    assert bench == []  # refused before anything ran
    with pytest.raises(SystemExit, match="no 'held_out' part to keep"):
        reproduce.section_bench_rigs(_args("dev"), tmp_path / "runs", runs)  # no page there at all


def test_held_out_failure_keeps_the_new_dev_part(bench, tmp_path, monkeypatch):
    """The page is rewritten after the dev part, so a held-out failure loses nothing measured."""
    docs, runs = _dirs(tmp_path)
    reproduce.section_bench_rigs(_args(), docs, runs)
    real = reproduce._run

    def held_out_fails(cmd, log=None):
        if "--seed" in cmd:
            raise SystemExit("reproduce: held-out part interrupted")
        return real(cmd, log)

    monkeypatch.setattr(reproduce, "_run", held_out_fails)
    with pytest.raises(SystemExit):
        reproduce.section_bench_rigs(_args(), docs, runs)
    blocks = reproduce.bench_page_parts((docs / "bench_rigs.md").read_text())
    assert "| run 3 |" in blocks["dev"] and "| run 2 |" in blocks["held_out"]  # new dev, old held-out


def test_part_without_the_bench_section_is_refused(bench, capsys):
    with pytest.raises(SystemExit):
        reproduce.main(["--only", "main_job", "--part", "held_out"])
    assert "--part held_out is a part of bench_rigs" in capsys.readouterr().err
    assert bench == []


def test_commands_show_the_runs_folder_as_the_default(tmp_path):
    """A page names the command a user types (``--out runs/paper``), wherever reproduce.py's
    ``--runs`` was; other arguments are kept."""
    runs = tmp_path / "elsewhere"
    cmd = reproduce.experiment_cmd("configs/experiments/paper.yaml", runs / "paper", 10_000)
    assert reproduce._shown(cmd, runs=runs) == ("microctl experiment configs/experiments/paper.yaml --out runs/paper "
                                                "--seed-offset 10000")
    assert str(tmp_path) in reproduce._shown(cmd)  # without runs=, the path as it was


def test_part_without_a_block_to_keep_is_refused_before_any_section(bench, tmp_path, capsys):
    """The refusal comes before main_job (the section before bench_rigs) runs, with exit 2."""
    docs, runs = _dirs(tmp_path)
    with pytest.raises(SystemExit) as e:
        reproduce.main(["--only", "main_job,bench_rigs", "--part", "held_out", "--docs", str(docs),
                        "--runs", str(runs)])
    assert e.value.code == 2
    assert "has no 'dev' part to keep" in capsys.readouterr().err
    assert bench == [] and not list(runs.iterdir())
