"""experiments/sensor_noise.py: tracking against the sensors' noise factor, per scenario and model."""

import json

import numpy as np
import pytest


def _run(folder, rows, disturbance=None):
    folder.mkdir(parents=True)
    (folder / "closed_loop.json").write_text(json.dumps({"rows": rows}))
    for r in rows:
        d = np.zeros((5, 6)) if disturbance is None else disturbance
        name = f"trace_{r['scenario']}_{r['model']}" + (f"_seed{r['seed']}" if r["episode"] else "")
        np.savez(folder / f"{name}.npz", disturbance=d, fallen=np.zeros(5, bool))
    return str(folder / "closed_loop.json")


def test_rows_group_by_noise_factor_and_the_observers_spread_is_read_from_the_traces(
        experiment, tmp_path):
    mod = experiment("sensor_noise")
    row = lambda sc, m, v, noise=None, seed=0, ep=0, fell=False: dict(
        scenario=sc, model=m, vel_rmse=v, fell=fell, seed=seed, episode=ep,
        **({"sensor_noise": noise} if noise else {}))
    exact = _run(tmp_path / "n0", [row("rough", "stride", 0.06), row("rough", "policy", 0.09)])
    steps = np.zeros((5, 6))
    steps[:, 0] = [0.0, 1.0, 0.0, 1.0, 0.0]  # the estimate jumps by 1 m/s^2 every period
    noisy = _run(tmp_path / "n3", [row("rough_noise3", "stride", 0.08, 3.0),
                                   row("rough_noise3", "stride", 0.10, 3.0, seed=1, ep=1),
                                   row("rough_noise3", "stride", 5.0, 3.0, seed=2, ep=2, fell=True)],
                 steps)
    recorded = _run(tmp_path / "n1", [dict(row("rough_noise1", "stride", 0.07, 1.0),
                                           observer_step_rms=0.5)])
    data = mod.main([exact, noisy, recorded, f"filter 0.5={exact}", "--out", str(tmp_path / "t")])
    assert data["rough"]["stride"][1.0]["spread"] == pytest.approx(0.5)  # the row's own, no trace
    assert data["rough"]["stride (filter 0.5)"][0.0]["rmse"] == pytest.approx(0.06)
    by = data["rough"]["stride"]
    assert by[0.0]["rmse"] == pytest.approx(0.06) and by[0.0]["spread"] is None  # no observer
    assert by[3.0]["rmse"] == pytest.approx(0.09)  # the episode that fell left out
    assert (by[3.0]["falls"], by[3.0]["episodes"]) == (1, 3)
    assert by[3.0]["spread"] == pytest.approx(1.0)
    text = (tmp_path / "t.md").read_text()
    assert "| stride | 0.0600 (0/1) | 0.0700 (0/1) | 0.0900 (1/3) | - | 0.50 | 1.00 |" in text
    assert "| policy | 0.0900 (0/1) | - | - | - | - | - |" in text and (tmp_path / "t.png").is_file()
    with pytest.raises(FileNotFoundError, match="no closed_loop.json"):
        mod.collect([str(tmp_path / "nope.json")])
