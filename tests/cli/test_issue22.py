"""A newcomer's first hour and a lab's bad day (issue 22): outputs, hints, streams, bad inputs."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from microctl.cli import main
from microctl.gp.fitted import FittedVHGPR
from microctl.measurement.log import read_log
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
TABLE1 = ROOT / "configs/stage/table1.yaml"
SIM = ROOT / "configs/stage/sim_paper.yaml"


def _err_line(capsys, rc, want_rc=2, contains=()):
    cap = capsys.readouterr()
    assert rc == want_rc, cap.err
    assert cap.err.count("\n") == 1 and "Traceback" not in cap.err, cap.err
    for text in contains:
        assert text in cap.err, cap.err
    return cap.err


# ---- item 7: collect -o never overwrites a log silently ----------------------------------------

def test_collect_refuses_an_existing_log_without_force_or_append(tmp_path, capsys):
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(TABLE1), "-n", "3", "-o", str(log), "--quiet"]) == 0
    before = log.read_bytes()
    rc = main(["collect", "--config", str(TABLE1), "-n", "4", "-o", str(log), "--quiet"])
    _err_line(capsys, rc, contains=("the file exists; refusing to overwrite it", "--force", "--append"))
    assert log.read_bytes() == before


def test_collect_force_replaces_and_append_continues(tmp_path, capsys):
    stage = load_stage_config(TABLE1).stage
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(TABLE1), "-n", "3", "-o", str(log), "--quiet"]) == 0
    assert main(["collect", "--config", str(TABLE1), "-n", "4", "-o", str(log), "--force", "--quiet"]) == 0
    assert len(read_log(log, stage)) == 4
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")) == ["log.csv"]
    assert main(["collect", "--config", str(TABLE1), "-n", "2", "--seed", "5", "-o", str(log), "--append",
                 "--quiet"]) == 0
    got = read_log(log, stage)
    assert got.seq.tolist() == [0, 1, 2, 3, 4, 5]
    assert all(b >= a for a, b in zip(got.time_s, got.time_s[1:]))
    rc = main(["collect", "--config", str(TABLE1), "-n", "2", "-o", str(tmp_path / "none.csv"), "--append"])
    _err_line(capsys, rc, contains=("--append needs an existing log",))


def test_collect_append_refuses_another_header(tmp_path, capsys):
    log = tmp_path / "log.csv"
    log.write_text("a,b\n1,2\n")
    rc = main(["collect", "--config", str(TABLE1), "-n", "2", "-o", str(log), "--append", "--quiet"])
    _err_line(capsys, rc, contains=(f"{log}: cannot append: its header is 'a,b'",))
    assert log.read_text() == "a,b\n1,2\n"


# ---- item 15: two writers of one log ------------------------------------------------------------

def test_collect_refuses_a_log_another_process_is_writing(tmp_path, capsys):
    from microctl.util.atomic import output_lock

    log = tmp_path / "log.csv"
    with output_lock(log):  # as a running collect holds it
        rc = main(["collect", "--config", str(TABLE1), "-n", "3", "-o", str(log), "--quiet"])
    _err_line(capsys, rc, contains=("another microctl process is writing this file",))
    assert not log.exists()
    assert main(["collect", "--config", str(TABLE1), "-n", "3", "-o", str(log), "--quiet"]) == 0


# ---- item 8: results on stdout, progress and notes on stderr -----------------------------------

def test_train_and_collect_results_on_stdout(tmp_path, capsys, planted_log, table1_path):
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(TABLE1), "-n", "3", "-o", str(log), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert "collect: 3 moves on the simulated backend written to" in cap.out and cap.err == ""
    rc = main(["train", str(planted_log), "--config", str(table1_path), "-o", str(tmp_path / "m.npz"),
               "--restarts", "1", "--quiet"])
    cap = capsys.readouterr()
    assert rc == 0 and "model for stage" in cap.out and "noise model" in cap.out and cap.err == ""


# ---- item 9: emulate on Ctrl-C ------------------------------------------------------------------

def test_emulate_ctrl_c_exits_130_with_a_message(capsys, monkeypatch):
    import microctl.cli.commands.emulate as emulate_cmd

    def interrupt(_):
        raise KeyboardInterrupt

    monkeypatch.setattr(emulate_cmd.time, "sleep", interrupt)
    rc = main(["emulate", "--config", str(ROOT / "configs/stage/emulated.yaml"), "--ports", "0,0,0", "--quiet"])
    cap = capsys.readouterr()
    assert rc == 130 and cap.err.strip().splitlines()[-1] == "microctl: interrupted", cap.err


# ---- item 18: no tracebacks ---------------------------------------------------------------------

def test_diagnose_on_a_log_in_other_units_is_refused(tmp_path, capsys):
    import csv

    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(SIM), "-n", "45", "-o", str(log), "--quiet"]) == 0
    rows = list(csv.reader(log.open()))
    col = rows[0].index("t")
    for r in rows[1:]:
        r[col] = repr(float(r[col]) * 1000)  # t in nm
    with log.open("w") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)
    capsys.readouterr()
    rc = main(["diagnose", str(log), "--config", str(SIM), "--out", str(tmp_path / "d"), "--quiet"])
    _err_line(capsys, rc, contains=(f"{log}: ", "rows are implausible for the stage", "in other units"))


def test_yaml_alias_bomb_is_refused_quickly(tmp_path, capsys):
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    prev = "a"
    for name in "bcdefghi":
        lines.append(f"{name}: &{name} [" + ",".join([f"*{prev}"] * 9) + "]")
        prev = name
    lines += ["stage:", "  name: *i"]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(lines) + "\n")
    rc = main(["stage", "show", "--config", str(bomb)])
    _err_line(capsys, rc, contains=(f"{bomb}: the YAML expands to", "alias"))


def test_sigint_swallowed_during_start_up_still_exits_130(capsys, monkeypatch):
    import os
    import signal

    import microctl.cli as cli

    real = cli.build_parser

    def swallowing_import(*args, **kwargs):  # a library that catches the KeyboardInterrupt of a Ctrl-C while it loads
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        except KeyboardInterrupt:
            pass
        return real(*args, **kwargs)

    monkeypatch.setattr(cli, "build_parser", swallowing_import)
    rc = main(["stage", "show", "--config", str(TABLE1)])
    cap = capsys.readouterr()
    assert rc == 130 and cap.err == "microctl: interrupted\n" and cap.out == ""


def test_sigint_surfacing_as_import_error_exits_130(capsys, monkeypatch):
    import os
    import signal

    import microctl.cli as cli

    def failing_import(*args, **kwargs):  # a compiled module interrupted while it initialises
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None

    monkeypatch.setattr(cli, "build_parser", failing_import)
    rc = main(["stage", "show", "--config", str(TABLE1)])
    assert rc == 130 and capsys.readouterr().err == "microctl: interrupted\n"


# ---- items 16, 17, 19, 21: gp fit and train inputs ---------------------------------------------

def _table(path: Path, xs, ys) -> Path:
    path.write_text("x,y\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(xs, ys)))
    return path


@pytest.mark.parametrize("column", ["x", "y"])
def test_gp_fit_refuses_values_too_large_to_standardise(tmp_path, capsys, column):
    import numpy as np

    xs = np.linspace(0, 1, 20)
    ys = np.sin(xs)
    if column == "x":
        xs = xs * 1e300
    else:
        ys = ys * 1e300
    data = _table(tmp_path / "d.csv", xs, ys)
    rc = main(["gp", "fit", str(data), "--x", "x", "--y", "y", "-o", str(tmp_path / "g.npz"), "--quiet"])
    _err_line(capsys, rc, contains=(f"{data}:", "cannot be standardised"))
    assert not (tmp_path / "g.npz").exists()


def test_gp_fit_refuses_too_few_rows_and_unbounded_restarts(tmp_path, capsys):
    data = _table(tmp_path / "d.csv", [0.0, 1.0], [0.0, 1.0])
    rc = main(["gp", "fit", str(data), "--x", "x", "--y", "y", "-o", str(tmp_path / "g.npz"), "--quiet"])
    _err_line(capsys, rc, contains=(str(data), "5"))
    with pytest.raises(SystemExit) as info:
        main(["gp", "fit", str(data), "--x", "x", "--y", "y", "-o", str(tmp_path / "g.npz"),
              "--restarts", "1000000000"])
    assert info.value.code == 2 and "must be at most 100" in capsys.readouterr().err


def test_train_on_identical_moves_names_the_file(tmp_path, capsys, table1_path):
    import numpy as np

    from microctl.models.afm import AnalyticForwardModel

    afm = AnalyticForwardModel(load_stage_config(table1_path).stage)
    u = afm.workspace.sample(1, np.random.default_rng(0))[0]
    q = afm.K @ u
    t = float(afm.t_of(u[None])[0])
    log = tmp_path / "same.csv"
    log.write_text("seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t\n" + "".join(
        ",".join([str(k), *(repr(float(v)) for v in (*u, *q)), repr(t)]) + "\n" for k in range(30)))
    rc = main(["train", str(log), "--config", str(table1_path), "-o", str(tmp_path / "m.npz"), "--restarts", "1"])
    _err_line(capsys, rc, contains=(f"{log}: ", "constant"))


# ---- item 3: hints on typical mistakes ----------------------------------------------------------

@pytest.mark.parametrize("argv,hint", [
    (["collect", "--config", "sim_paper", "--moves", "5", "-o", "x.csv"], "did you mean -n instead of --moves?"),
    (["stage", "show", "--config", "sim_paper", "--jsn"], "did you mean --json instead of --jsn?"),
])
def test_mistyped_option_gets_a_suggestion(capsys, argv, hint):
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and hint in err and err.count("\n") == 1, err


def test_json_or_yaml_given_as_a_log(tmp_path, capsys):
    js = tmp_path / "s.json"
    js.write_text('{\n  "target_um": 14.0\n}\n')
    rc = main(["train", str(js), "--config", str(TABLE1), "-o", str(tmp_path / "m.npz")])
    _err_line(capsys, rc, contains=(f"{js}: this is JSON",))
    rc = main(["train", str(TABLE1), "--config", str(TABLE1), "-o", str(tmp_path / "m.npz")])
    _err_line(capsys, rc, contains=("this looks like YAML",))


def test_stage_file_to_experiment_and_experiment_file_to_config(tmp_path, capsys):
    rc = main(["experiment", str(SIM), "--out", str(tmp_path / "x")])
    _err_line(capsys, rc, contains=("this is a stage file", "not an experiment file"))
    rc = main(["stage", "show", "--config", str(ROOT / "configs/experiments/quick.yaml")])
    _err_line(capsys, rc, contains=("this is an experiment file", "microctl experiment"))


def test_connection_refused_suggests_emulate(tmp_path, capsys):
    import socket

    import yaml

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    doc = yaml.safe_load((ROOT / "configs/stage/emulated.yaml").read_text())
    text = yaml.safe_dump(doc)
    import re

    text = re.sub(r"socket://127\.0\.0\.1:\d+", f"socket://127.0.0.1:{port}", text)
    cfg = tmp_path / "stage.yaml"
    cfg.write_text(text)
    rc = main(["collect", "--config", str(cfg), "-n", "2", "-o", str(tmp_path / "l.csv"), "--quiet"])
    _err_line(capsys, rc, want_rc=1, contains=("Connection refused", "microctl emulate"))


def test_packaged_config_by_short_name(capsys):
    assert main(["stage", "show", "--config", "sim_paper", "--json"]) == 0
    rc = main(["stage", "show", "--config", "no_such_stage"])
    _err_line(capsys, rc, contains=("no_such_stage", "sim_paper", "table1"))


# ---- item 21: negative numbers as option values; --seed bounds ----------------------------------

def test_negative_option_values_parse():
    from microctl.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["solve", "--config", "x", "--model", "m", "--target", "1", "--state", "-3,0,0,0,0"])
    assert args.state == "-3,0,0,0,0"
    args = parser.parse_args(["solve", "--config", "x", "--model", "m", "--targets", "-20,-10"])
    assert args.targets == "-20,-10"
    args = parser.parse_args(["emulate", "--config", "x", "--start-q", "-0,0,0,0"])
    assert args.start_q == "-0,0,0,0"


def test_seed_beyond_64_bits_is_a_usage_error_at_once(capsys):
    with pytest.raises(SystemExit) as info:
        main(["diagnose", "x.csv", "--config", str(TABLE1), "--out", "d", "--seed", str(2**64)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --seed: must be at most 9223372036854775807" in err


# ---- item 6: readings in mm ---------------------------------------------------------------------

def test_train_refuses_readings_in_mm(tmp_path, capsys):
    import csv

    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(SIM), "-n", "30", "-o", str(log), "--quiet"]) == 0
    rows = list(csv.reader(log.open()))
    for name in ("t", "t_prev"):
        col = rows[0].index(name)
        for r in rows[1:]:
            r[col] = repr(float(r[col]) / 1000)  # µm -> mm
    with log.open("w") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)
    capsys.readouterr()
    rc = main(["train", str(log), "--config", str(SIM), "-o", str(tmp_path / "m.npz"), "--restarts", "1"])
    _err_line(capsys, rc, contains=(f"{log}: column 't'", "are they in mm?"))


# ---- item 16: wrong accepts ---------------------------------------------------------------------

def _stage_variant(tmp_path, edit) -> Path:
    import yaml

    doc = yaml.safe_load(TABLE1.read_text())
    edit(doc)
    path = tmp_path / "stage.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@pytest.mark.parametrize("field,value,needle", [
    ("contact", None, "two balls cannot push at one point"),
    ("actuator", "seq", "is a measurement-log column name"),
    ("actuator", "time_s", "is a measurement-log column name"),
    ("actuator", "u_z", "is a measurement-log column name"),
    ("actuator", "q1_prev", "is a measurement-log column name"),
    ("tool", "t_prev", "is a measurement-log column name"),
])
def test_stage_yaml_wrong_accepts_refused(tmp_path, capsys, field, value, needle):
    def edit(doc):
        acts = doc["stage"]["actuators"]
        if field == "contact":
            acts[1]["contact_mm"] = list(acts[0]["contact_mm"])
        elif field == "actuator":
            acts[3]["name"] = value
        else:
            doc["stage"]["tool"]["name"] = value

    path = _stage_variant(tmp_path, edit)
    rc = main(["stage", "show", "--config", str(path)])
    _err_line(capsys, rc, contains=(str(path), needle))


def test_reply_pattern_without_capture_group_refused(tmp_path, capsys):
    import yaml

    doc = yaml.safe_load((ROOT / "configs/stage/emulated.yaml").read_text())
    doc["backend"]["serial"]["gauge"]["reply_pattern"] = r"^-?\d+\.\d+$"
    path = tmp_path / "stage.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    rc = main(["stage", "show", "--config", str(path)])
    _err_line(capsys, rc, contains=("reply_pattern", "exactly one capture group"))


def test_emulate_refuses_one_port_for_several_devices(capsys):
    rc = main(["emulate", "--config", str(ROOT / "configs/stage/emulated.yaml"), "--ports", "50999,50999,50999"])
    _err_line(capsys, rc, contains=("--ports: port 50999 is given 3 times",))


# ---- items 17, 20: unbounded work and blocking files ---------------------------------------------

@pytest.mark.parametrize("section,value,needle", [
    ("absolute", {"points": 1000000000, "trials": 2}, "absolute: points × trials"),
    ("absolute", {"points": 30, "trials": 1000000000}, "absolute: points × trials"),
    ("incremental", {"targets_um": [7, 14], "trials": 1000000000}, "incremental: targets × trials"),
    ("oracle", {"grid": 1000000}, "oracle.grid: must be an integer in [5, 201]"),
    ("training", {"moves": 125, "refine_rounds": 100}, "training.refine_rounds"),
    ("training", {"moves": 100001}, "training rows"),
])
def test_experiment_sizes_bounded_at_load(tmp_path, capsys, section, value, needle):
    import yaml

    doc = yaml.safe_load((ROOT / "configs/experiments/quick.yaml").read_text())
    doc["stage"] = str(SIM)
    doc[section] = {**(doc.get(section) or {}), **value}
    exp = tmp_path / "exp.yaml"
    exp.write_text(yaml.safe_dump(doc))
    rc = main(["experiment", str(exp), "--out", str(tmp_path / "out")])
    _err_line(capsys, rc, contains=(needle,))


def test_train_refuses_more_rows_than_it_can_fit(tmp_path, capsys, monkeypatch):
    import microctl.models.training as training

    monkeypatch.setattr(training, "MAX_TRAIN_ROWS", 20)
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(TABLE1), "-n", "30", "-o", str(log), "--quiet"]) == 0
    capsys.readouterr()
    rc = main(["train", str(log), "--config", str(TABLE1), "--gp", "exact", "-o", str(tmp_path / "m.npz")])
    _err_line(capsys, rc, contains=(f"{log}: 30 rows", "--gp exact", "subsample"))


def test_train_above_the_exact_limit_fits_the_sparse_form(tmp_path, capsys, monkeypatch):
    """``--gp auto`` (the default) above AUTO_SPARSE_ROWS fits the sparse model instead of refusing."""
    import microctl.models.training as training
    from microctl.gp.fitted import FittedVHGPR

    monkeypatch.setattr(training, "AUTO_SPARSE_ROWS", 20)
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(TABLE1), "-n", "30", "-o", str(log), "--quiet"]) == 0
    out = tmp_path / "m.npz"
    assert main(["train", str(log), "--config", str(TABLE1), "--inducing", "12", "-o", str(out), "--quiet"]) == 0
    assert "sparse, 12 inducing points" in capsys.readouterr().out
    model = FittedVHGPR.load(out)
    assert model.posterior_form == "sparse" and model.X.shape[0] == 12


def test_fifos_refused_as_inputs_and_outputs(tmp_path, capsys):
    import os

    fifo = tmp_path / "ff"
    os.mkfifo(fifo)
    cases = [
        (["stage", "show", "--config", str(fifo)], "not a regular file"),
        (["train", str(fifo), "--config", str(TABLE1), "-o", str(tmp_path / "m.npz")], "not a regular file"),
        (["gp", "predict", str(fifo), str(ROOT / "tests/data/mcycle.csv"), "-o", str(tmp_path / "p.csv")],
         "not a regular file"),
        (["collect", "--config", str(TABLE1), "-n", "3", "-o", str(fifo)], "is a FIFO or socket"),
    ]
    for argv, needle in cases:
        rc = main(argv)
        _err_line(capsys, rc, contains=(needle,))


def test_atomic_write_to_a_device_writes_through(tmp_path):
    from microctl.util.atomic import write_text_atomic

    write_text_atomic("/dev/null", "x")  # never replaced by a regular file
    assert Path("/dev/null").is_char_device()


# ---- item 5: a model used for another stage -------------------------------------------------------

def test_model_for_another_stage_is_named(tmp_path, capsys, planted_log, table1_path):
    import yaml

    model = tmp_path / "m.npz"
    assert main(["train", str(planted_log), "--config", str(table1_path), "-o", str(model), "--restarts", "1",
                 "--quiet"]) == 0
    doc = yaml.safe_load(table1_path.read_text())
    # same geometry, other contact physics (as sim_paper.yaml vs sim_paper_scale.yaml): said on stderr
    doc["stage"]["name"] = "other-rig"
    doc["stage"]["physics"] = {"preload_n": 50.0}
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(doc, sort_keys=False))
    capsys.readouterr()
    assert main(["solve", "--config", str(other), "--model", str(model), "--target", "10", "--json"]) == 0
    err = capsys.readouterr().err
    assert "was trained for stage 'table1'" in err and "contact physics" in err, err
    # same geometry, other model corrections (the extended config of diagnose): not "another geometry"
    doc = yaml.safe_load(table1_path.read_text())
    doc["stage"]["corrections"] = {"actuator_gain": [{"actuator": 4, "gain": 0.6}]}
    ext = tmp_path / "extended.yaml"
    ext.write_text(yaml.safe_dump(doc, sort_keys=False))
    rc = main(["solve", "--config", str(ext), "--model", str(model), "--target", "10"])
    _err_line(capsys, rc, contains=("same geometry with other model corrections",))


# ---- item 10: diagnose's one-line verdict ------------------------------------------------------------

@pytest.mark.parametrize("extended,verdict", [
    ([0.5, 0.4], "the extended controller is better"),
    ([0.993 * 0.6, 0.988 * 0.7], "no clear difference"),
    ([0.9, 0.9], "the plain controller is better"),
    ([0.3, 0.9], "mixed"),
])
def test_diagnose_control_line_has_a_verdict(extended, verdict):
    from microctl.diagnosis.report import control_line

    c = {"truth": True, "targets_um": [14.0, 21.0],
         "models": {"plain": [{"true_std_um": 0.6}, {"true_std_um": 0.7}],
                    "extended": [{"true_std_um": v} for v in extended]}}
    line = control_line(c)
    assert f"verdict: {verdict}" in line and "\n" not in line


def test_diagnose_wrote_line_names_the_figures(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(SIM), "-n", "40", "-o", str(log), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(log), "--config", str(SIM), "--out", str(tmp_path / "d"), "--no-gp"]) == 0
    wrote = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("wrote ")]
    assert wrote and "residuals.png" in wrote[0] and "causes.png" in wrote[0], wrote


# ---- item 11: Fig. 6's MSSE lines --------------------------------------------------------------------

def test_fig6_msse_lines_never_hide_each_other_and_are_in_the_legend():
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from microctl.experiments.figures import figure_fig6

    sse = [[0.1, 0.2], [0.3, 0.1], [0.2, 0.2]]
    same = {"sse_um": sse, "msse_um": [0.2, 0.1667]}
    inc = {"targets_um": [7, 14], "trials": 3,
           "controllers": {"afm": {"sse_um": [[1, 2]] * 3, "msse_um": [1, 2]}, "eafm": same,
                           "eafm_sequence": dict(same)}}
    fig = figure_fig6(inc)
    ax = fig.axes[0]
    msse = [ln for ln in ax.get_lines() if ln.get_label().endswith("MSSE")]
    assert len(msse) == 3
    a, b = [ln for ln in msse if ln.get_ydata()[0] == 0.2]
    assert a.get_color() != b.get_color()
    assert a._dash_pattern[0] != b._dash_pattern[0]  # interleaved dashes: both colours visible
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert sum(t.endswith("MSSE") for t in legend) == 3
    plt.close(fig)


# ---- items 4, 21: one range, rounded; absurd targets --------------------------------------------------

def test_unreachable_target_message_is_rounded_and_absurd_targets_refused_early(capsys, planted_log,
                                                                               table1_path, tmp_path):
    import re
    import warnings

    model = tmp_path / "m.npz"
    assert main(["train", str(planted_log), "--config", str(table1_path), "-o", str(model), "--restarts", "1",
                 "--quiet"]) == 0
    capsys.readouterr()
    rc = main(["solve", "--config", str(table1_path), "--model", str(model), "--target", "500"])
    err = _err_line(capsys, rc, contains=("unreachable", "reaches ["))
    assert not re.search(r"\d\.\d{5,}", err), err
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning before the error line
        rc = main(["solve", "--config", str(table1_path), "--model", str(model), "--target", "1e308"])
    _err_line(capsys, rc, contains=("far outside what stage 'table1' reaches", "stage show"))


def test_diagnose_control_table_explains_a_std_below_the_oracle():
    from microctl.diagnosis.report import control_markdown

    c = {"truth": True, "targets_um": [41.1],
         "models": {m: [{"q_um": [1, 2, 3, 4], "predicted_std_um": 0.6, "true_std_um": v, "true_error_um": 0.3,
                         "oracle_std_um": 0.608}] for m, v in (("plain", 0.598), ("extended", 0.611))}}
    text = "\n".join(control_markdown(c))
    assert "| 0.5980* |" in text and "| 0.6110 |" in text and "misses the target" in text


def test_gp_fit_refuses_more_rows_than_it_can_fit(tmp_path, capsys, monkeypatch):
    import microctl.models.training as training

    monkeypatch.setattr(training, "MAX_TRAIN_ROWS", 10)
    data = _table(tmp_path / "d.csv", range(12), [v * v for v in range(12)])
    rc = main(["gp", "fit", str(data), "--x", "x", "--y", "y", "-o", str(tmp_path / "g.npz")])
    _err_line(capsys, rc, contains=(f"{data}: 12 rows", "subsample"))


def test_diagnose_refuses_readings_on_another_scale(tmp_path, capsys):
    import csv

    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(SIM), "-n", "45", "-o", str(log), "--quiet"]) == 0
    rows = list(csv.reader(log.open()))
    for name in ("t", "t_prev"):
        col = rows[0].index(name)
        for r in rows[1:]:
            r[col] = repr(float(r[col]) * 8)  # plausible row by row, wrong as a whole
    with log.open("w") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)
    capsys.readouterr()
    rc = main(["diagnose", str(log), "--config", str(SIM), "--out", str(tmp_path / "d"), "--quiet"])
    _err_line(capsys, rc, contains=(f"{log}: column 't'", "another unit"))


def test_train_g_inputs_and_g_start_reach_the_model_file(tmp_path, capsys, planted_log, table1_path):
    """``--g-inputs actuators --g-start residuals``: the model file carries g's input map (one
    name per row: each actuator's position, then its step) and the fit's extra run; a wrong
    choice names the option and the valid ones."""
    out = tmp_path / "m.npz"
    rc = main(["train", str(planted_log), "--config", str(table1_path), "-o", str(out), "--restarts", "1",
               "--noise-model", "hgp", "--g-inputs", "actuators", "--g-start", "residuals", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    model = FittedVHGPR.load(out)
    assert model.g_input_names == ("q1", "q2", "q3", "q4", "dq1", "dq2", "dq3", "dq4")
    assert model.g_input_map.shape == (8, 8)
    assert [r["start"] for r in model.info["runs"]][-1] == "g_resid"
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["train", str(planted_log), "--config", str(table1_path), "-o", str(tmp_path / "x.npz"),
              "--g-inputs", "loads"])
    err = capsys.readouterr().err
    assert "--g-inputs" in err and "actuators" in err
