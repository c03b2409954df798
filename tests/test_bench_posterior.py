"""scripts/bench_posterior.py runs end to end on a small model and prints one row per size whose
differences are those the feature form allows (tests/gp/test_f_variance_feature_form.py)."""

from __future__ import annotations

from script_loader import load_script

bench = load_script("bench_posterior")


def test_the_benchmark_prints_a_row_per_size_with_a_difference_inside_the_interval(capsys):
    assert bench.main(["--sizes", "40", "--points", "60", "--evals", "4", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.strip().startswith("40 ")]
    assert len(rows) == 1, out
    n, p, form, *times, rel, width = rows[0]
    assert form == "features" and int(p) >= 2  # the default model of 40 covering moves drops f's SE part
    assert all(float(t) > 0 for t in times)
    # the form's excess over the exact variance is at most e(x*, x*) <= sf2 (at its floor e^-12
    # with the SE part off), tiny against the variances themselves
    assert float(width) < 1e-4 and float(rel) < 1e-4
