"""docs/api.md: its ``python`` examples run, in order, in a scratch folder with the repository's configs."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "api.md"


def blocks() -> list[str]:
    """The ``python`` code blocks of docs/api.md, in order."""
    return re.findall(r"^```python\n(.*?)^```", DOC.read_text(encoding="utf-8"), flags=re.S | re.M)


def test_the_page_has_examples_of_every_part_of_the_api():
    code = "\n".join(blocks())
    for name in ("load_stage", "collect", "train", "Controller", "solve", "Operator", "move", "read_measurements",
                 "reload", "UnreachableTargetError"):
        assert name in code, name


def test_api_md_examples_run(tmp_path, capsys):
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    old = os.getcwd()
    os.chdir(tmp_path)
    namespace: dict = {"__name__": "api_md"}
    try:
        for k, code in enumerate(blocks()):
            try:
                exec(compile(code, f"docs/api.md block {k + 1}", "exec"), namespace)
            except Exception as exc:  # name the block that failed
                pytest.fail(f"docs/api.md block {k + 1} raised {type(exc).__name__}: {exc}\n{code}")
    finally:
        os.chdir(old)
    out = capsys.readouterr().out
    assert out.count("refused:") == 2
    assert len(re.findall(r"^\d: target \d+, predicted", out, re.M)) == 3


# 12 moves leave the noise floor unidentified, and train warns so (microctl.models.floor_check,
# tested in tests/models/test_floor_check.py); this test is about refine's input errors
@pytest.mark.filterwarnings("ignore:train. .*not an estimate:RuntimeWarning")
def test_refine_refuses_a_missing_log_and_a_bad_count(tmp_path):
    from microctl import api
    from microctl.errors import ConfigError

    stage = api.load_stage(Path(__file__).resolve().parents[1] / "configs/stage/sim_paper.yaml")
    log = tmp_path / "t.csv"
    api.collect(stage, 12, log, seed=1)
    model = api.train(log, stage, restarts=1)
    with pytest.raises(ConfigError, match="no such measurement log"):
        api.refine(stage, model, 3, tmp_path / "none.csv")
    with pytest.raises(ConfigError, match="number of moves >= 1"):
        api.refine(stage, model, 0, log)
    before = log.read_bytes()
    assert api.refine(stage, model, 3, log, target_range_um=(0.0, 30.0)) == 3
    assert log.read_bytes().startswith(before) and len(api.read_measurements(log, stage)) == 15
