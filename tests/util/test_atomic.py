"""Output files are written atomically and log writers are exclusive (issue 22, items 14 and 15)."""

from __future__ import annotations

import numpy as np
import pytest

from microctl.util import atomic
from microctl.util.io import write_json


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old\n")
    with pytest.raises(KeyboardInterrupt):
        with atomic.atomic_write(path) as fh:
            fh.write("half of the new")
            raise KeyboardInterrupt
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]  # no stray temporary file
    atomic.write_text_atomic(path, "new\n")
    assert path.read_text() == "new\n"


def test_write_json_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "results.json"
    write_json(path, {"a": 1})

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", boom)
    with pytest.raises(OSError):
        write_json(path, {"a": 2})
    assert path.read_text().strip().startswith("{") and '"a": 1' in path.read_text()


def test_model_file_write_interrupted_keeps_the_old_model(tmp_path, monkeypatch, planted_log, table1_path):
    from microctl.cli import main
    from microctl.gp.vhgpr import FittedVHGPR

    model = tmp_path / "model.npz"
    assert main(["train", str(planted_log), "--config", str(table1_path), "-o", str(model), "--restarts", "1"]) == 0
    before = model.read_bytes()
    real = np.savez

    def torn(fh, **arrays):  # writes part of the archive, then the process is interrupted
        real(fh, **{k: arrays[k] for k in list(arrays)[:2]})
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", torn)
    assert main(["train", str(planted_log), "--config", str(table1_path), "-o", str(model), "--restarts", "1",
                 "--seed", "1"]) == 130
    assert model.read_bytes() == before
    FittedVHGPR.load(model)
    assert [p.name for p in tmp_path.iterdir()] == ["model.npz"]


def test_output_lock_refuses_a_second_writer(tmp_path):
    path = tmp_path / "log.csv"
    with atomic.output_lock(path):
        with pytest.raises(atomic.OutputBusyError, match="another microctl process is writing this file"):
            with atomic.output_lock(path):
                pass
    with atomic.output_lock(path):  # released
        pass


def test_save_figure_is_atomic(tmp_path):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure()
    atomic.save_figure(fig, tmp_path / "f.png", dpi=30)
    plt.close(fig)
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"


def test_atomic_write_over_a_fifo_replaces_it_without_blocking(tmp_path):
    import os

    path = tmp_path / "results.json"
    os.mkfifo(path)
    atomic.write_text_atomic(path, "{}\n")  # opening the FIFO for writing would wait for a reader forever
    assert path.is_file() and path.read_text() == "{}\n"
