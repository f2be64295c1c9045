"""experiments/probes/train_e2e_rates.py: steady training rates from runs' metrics.csv."""

import pytest


def _run(folder, steps, times):
    folder.mkdir(parents=True)
    rows = ["step,time,train_loss"] + [f"{s},{t},1.0" for s, t in zip(steps, times)]
    (folder / "metrics.csv").write_text("\n".join(rows) + "\n")


def test_the_rate_leaves_the_first_chunk_out_and_sums_seeds_side_by_side(experiment, tmp_path, capsys):
    mod = experiment("probes/train_e2e_rates")
    _run(tmp_path / "alone", [100, 200, 300], [50.0, 51.0, 51.5])  # 50 s of compiling before row 1
    for s in (0, 1):
        _run(tmp_path / f"side-s{s}", [100, 200, 300], [60.0, 61.0, 62.0])
    assert mod.rate(tmp_path / "alone") == pytest.approx(200.0)
    mod.main([str(tmp_path / "alone"), str(tmp_path / "side-s0"), str(tmp_path / "side-s1")])
    out = capsys.readouterr().out
    assert f"| {tmp_path / 'alone'} | 1 | 200 | 200 |" in out
    assert f"| {tmp_path / 'side'} | 2 | 100, 100 | 200 |" in out
    _run(tmp_path / "short", [100, 200], [1.0, 2.0])
    with pytest.raises(SystemExit, match="2 validation rows"):
        mod.rate(tmp_path / "short")
