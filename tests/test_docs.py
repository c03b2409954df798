"""The generated docs (docs/generated/, written by scripts/reproduce.py) against what the code
produces now: a structural check that does not rerun the expensive jobs.

Each generated table is marked ``<!-- table: NAME -->``. For the experiment pages a tiny
seeded run with the paper's targets is rendered with the same functions reproduce.py uses;
every table must then have the same header and the same row labels (bar names, metric and
controller, quantity) as the generated page. For bench_rigs.md the headers must be the ones
its Markdown writer produces and the rows must name sizes and methods it knows. A change of
the report's structure (a renamed bar, a new row, a column) fails here until
``python scripts/reproduce.py`` has been rerun. The numbers themselves are not compared: they
are the measured ones, and rerunning reproduce.py is what refreshes them.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from script_loader import load_script

ROOT = Path(__file__).resolve().parents[1]
GENERATED = ROOT / "docs" / "generated"

reproduce = load_script("reproduce")


def tables(text: str) -> dict[str, list[list[str]]]:
    """``{name: rows}`` of every marked Markdown table; a row is its list of cells."""
    out: dict[str, list[list[str]]] = {}
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = re.fullmatch(r"<!-- table: (\w+) -->", line.strip())
        if not m:
            continue
        rows = []
        for row in lines[i + 1:]:
            if not row.startswith("|"):
                break
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", row.strip())[1:-1]]
            if not all(set(c) <= {"-"} for c in cells):  # not the |---| line
                rows.append(cells)
        assert m.group(1) not in out, f"table {m.group(1)} twice"
        out[m.group(1)] = rows
    return out


def _page(name: str) -> str:
    path = GENERATED / name
    assert path.is_file(), f"{path} is missing: run python scripts/reproduce.py"
    return path.read_text()


#: Row labels: how many leading cells name a row (the rest are measured values).
LABEL_CELLS = {"bars": 1, "table_ii": 2, "scale": 1, "per_target_tests": 1, "seed_offsets": 2, "offset_summary": 0}


def _structure(tabs: dict[str, list[list[str]]], skip_labels: tuple[str, ...] = ()) -> dict:
    """Per table: the header and the row labels (``skip_labels``: tables whose labels are data)."""
    out = {}
    for name, rows in tabs.items():
        k = 0 if name in skip_labels else LABEL_CELLS.get(name, 1)
        out[name] = (rows[0], [tuple(r[:k]) for r in rows[1:]])
    return out


#: Generated experiment page -> the experiment file reproduce.py runs for it.
PAGES = {"main_job.md": reproduce.MAIN_JOB, "paper_scale.md": reproduce.PAPER_SCALE}
_TINY: dict[str, dict] = {}


def tiny_results(page: str, tmp_path_factory) -> dict:
    """A seeded run of the page's experiment (its stage, controllers and targets), small enough
    for seconds, so every section, table row and bar the page reports is produced."""
    if page not in _TINY:
        from microctl.experiments.config import load_experiment_config
        from microctl.experiments.runner import run_experiment

        exp_path = ROOT / PAGES[page]
        full = yaml.safe_load(exp_path.read_text())
        d = tmp_path_factory.mktemp("docs")
        doc = {"stage": str((exp_path.parent / full["stage"]).resolve()), "controllers": full["controllers"],
               "training": {"moves": 20, "restarts": 1, "max_iter": 60},
               "absolute": {"points": 3, "trials": 2},
               "incremental": {"targets_um": full["incremental"]["targets_um"], "trials": 3},
               "oracle": {"grid": 9, "line_points": 15, "zooms": 1}, "figures": False}
        (d / "exp.yaml").write_text(yaml.safe_dump(doc))
        _TINY[page] = run_experiment(load_experiment_config(d / "exp.yaml"), d / "out", quiet=True)
    return _TINY[page]


@pytest.mark.slow
@pytest.mark.parametrize("page", sorted(PAGES))
def test_experiment_pages_match_the_code(page, tmp_path_factory):
    text = _page(page)
    assert text.startswith(reproduce.BANNER.split("`")[0]), "not written by scripts/reproduce.py"
    got = _structure(tables(text))
    want = _structure(tables("\n".join(reproduce.experiment_markdown(tiny_results(page, tmp_path_factory)))))
    for name, (header, labels) in want.items():
        assert name in got, f"{page}: table '{name}' missing; rerun python scripts/reproduce.py"
        assert got[name][0] == header, f"{page}: table '{name}' header differs from the code's"
        assert got[name][1] == labels, f"{page}: table '{name}' rows differ from the code's"
    # the figures the page embeds are there
    for img in re.findall(r"!\[[^]]*\]\(([^)]+)\)", text):
        assert (GENERATED / img).is_file(), img


def test_paper_scale_offsets_match_the_code(tmp_path_factory):
    text = _page("paper_scale.md")
    got = tables(text)
    want = tables("\n".join(reproduce.offsets_markdown([(0, tiny_results("paper_scale.md", tmp_path_factory))])))
    for name in ("seed_offsets", "offset_summary", "paper_scale_bars"):
        assert got[name][0] == want[name][0], f"paper_scale.md: table '{name}' header differs from the code's"
    quantities = {r[1] for r in got["seed_offsets"][1:]}
    assert quantities == {r[1] for r in want["seed_offsets"][1:]}
    offsets = {r[0] for r in got["offset_summary"][1:]}
    assert offsets == {"0", *map(str, reproduce.PAPER_SCALE_OFFSETS)}, offsets


def test_bench_rigs_page_matches_the_code():
    bench = load_script("bench_rigs")
    text = _page("bench_rigs.md")
    got = tables(text)
    assert got["seed_sets"][0] == bench.seed_set_columns()
    assert [r[0] for r in got["seed_sets"][1:-1]] == [str(k) for k in range(1, len(got["seed_sets"]) - 1)]
    assert got["families"][0] == [h for _, h, _ in bench.FAMILY_COLUMNS]
    fam_col = [h for _, h, _ in bench.FAMILY_COLUMNS].index("family")
    meth_col = [h for _, h, _ in bench.FAMILY_COLUMNS].index("method")
    for row in got["families"][1:]:
        assert row[meth_col] in bench.METHODS and row[fam_col] in bench.rig_families.FAMILIES, row
    # the held-out rigs: the same columns, the methods reproduce.py runs there, every family
    held = got["families_held_out"]
    assert held[0] == got["families"][0]
    args = reproduce.BENCH_RIGS_HELD_OUT_ARGS
    assert {r[meth_col] for r in held[1:]} == set(args[args.index("--methods") + 1].split(","))
    assert {r[fam_col] for r in held[1:]} == set(bench.rig_families.FAMILIES)
    # two parts, each with its own provenance line and the command reproduce.py runs for it
    blocks = reproduce.bench_page_parts(text)
    assert list(blocks) == list(reproduce.BENCH_PARTS), list(blocks)
    for name, block in blocks.items():
        assert block.count("\nMeasured ") == 1, name
        assert f"`python scripts/bench_rigs.py {' '.join(reproduce.BENCH_PARTS[name][0])} --jobs " in block, name
    assert "<!-- table: families_held_out -->" in blocks["held_out"]
    # each part's rigs with the mean half of the bar judged by the data's accuracy (DATA_BAR_COLUMNS)
    for fam_table, bar_table in (("families", "data_bar"), ("families_held_out", "data_bar_held_out")):
        data_bar = got[bar_table]
        assert data_bar[0] == [h for _, h, _ in bench.DATA_BAR_COLUMNS], bar_table
        assert ({(r[0], r[2]) for r in data_bar[1:]}
                == {(r[fam_col], r[meth_col]) for r in got[fam_table][1:]}), bar_table


@pytest.mark.parametrize("section", sorted(reproduce.CAPTURED))
def test_captured_pages_name_their_command(section):
    text = _page(f"{section}.md")
    script, extra = reproduce.CAPTURED[section]
    assert f"`python {script}{''.join(' ' + a for a in extra)}`" in text
    src = (ROOT / script).read_text()
    assert all(a in src for a in extra if a.startswith("--")), "the script no longer takes these options"


def test_every_generated_page_is_a_known_section():
    names = {p.stem for p in GENERATED.glob("*.md")}
    assert names <= set(reproduce.SECTIONS), names - set(reproduce.SECTIONS)


def test_diagnose_help_points_to_docs(capsys):
    """``diagnose --help`` names files that are shipped (docs/), not the unshipped spec."""
    from microctl.cli import main

    with pytest.raises(SystemExit):
        main(["diagnose", "--help"])
    out = capsys.readouterr().out
    assert "docs/diagnosis.md" in out and "docs/measurement-log.md" in out and "spec" not in out
    for ref in re.findall(r"docs/[\w.-]+\.md", out):
        assert (ROOT / ref).is_file(), ref
