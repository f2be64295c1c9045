"""``stride show`` (stride_jax/jobs/show.py): its one-line summary and its error without runs.
The whole job runs at the end of ``make demo``; its maths are tests/test_reproduce.py's."""

import pytest

from stride_jax import cli
from stride_jax.jobs import show


def test_summary_line_names_each_model_and_the_floor():
    numbers = {"truth": {"w1_near_deterministic_floor": 1.0},
               "stride": {"field_rmse": 0.2, "w1_near": 0.6, "w1_near_over_floor": 0.6},
               "delan": {"field_rmse": 0.3, "w1_near": 1.1, "w1_near_over_floor": 1.1}}
    line = show.summary_line(numbers, {"stride": "STRIDE", "delan": "DeLaN"})
    assert line == ("STRIDE: field RMSE 0.20 rad/s², near-upright W1 0.60 (0.60 x the "
                    "deterministic floor 1.00); DeLaN: field RMSE 0.30 rad/s², near-upright W1 "
                    "1.10 (1.10 x the deterministic floor 1.00)")


def test_missing_runs_say_how_to_make_them(tmp_path):
    with pytest.raises(SystemExit, match="no trained run at .*stride train"):
        cli.main(["show", "--preset", "tiny", "--stride", str(tmp_path / "none"),
                  "--phase.grid", "5"])
