"""experiments/table1_device.sh names its archive and the runs folder it packs as
experiments/table1.py names them (a mismatch costs a device call: the driver trains, the packing
finds no folder)."""

import pathlib
import shutil
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "experiments" / "table1_device.sh"

CASES = [
    ({}, {}),
    ({"DATA": "walk"}, {"data": "walk"}),
    ({"DATA": "walk", "DATA_POLICY": "results/policies/ppo_go1_slope", "SLOPE": "20", "POT": "com",
      "TW": "1", "TF": "0.25"},
     {"data": "walk", "data_policy": "results/policies/ppo_go1_slope", "slope_deg": 20.0,
      "potential": "com", "transition_weight": 1.0, "transition_fraction": 0.25}),
    # numbers written otherwise than %g writes them name the same folders
    ({"DATA": "walk", "SLOPE": "15.0", "TW": "1.0", "TF": "0.250"},
     {"data": "walk", "slope_deg": 15.0, "transition_weight": 1.0, "transition_fraction": 0.25}),
    ({"TW": "0.5", "TF": "1"}, {"transition_weight": 0.5}),  # a whole-batch fraction adds nothing
    ({"DATA": "walk", "TW": "1", "TF": "0.25", "BW": "4.0", "POT": "com"},
     {"data": "walk", "transition_weight": 1.0, "transition_fraction": 0.25, "base_weight": 4.0,
      "potential": "com"}),
    ({"TW": "1", "BW": "1.0"}, {"transition_weight": 1.0}),  # weight 1: every dof alike, no suffix
]


@pytest.mark.parametrize("env,flags", CASES)
def test_device_script_names_the_folders_table1_makes(experiment, env, flags):
    if shutil.which("bash") is None:
        pytest.skip("bash is not installed")
    table1 = experiment("table1")
    data, variant = table1.folder_suffixes(table1.Table1Config(robot="g1", **flags))
    out = subprocess.run(["bash", str(SCRIPT), "/nonexistent", "g1", "1", "0", ""], cwd=ROOT,
                         env={"PATH": "/usr/bin:/bin", "NAMES_ONLY": "1", **env},
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == [f"g1{data}{variant}", f"g1{data}{variant}-paper"]


def test_training_groups_one_process_per_run_or_per_model_side_by_side(experiment):
    """``--side-by-side`` trains each model's seeds in one process; the ablation's first-seed run
    stays a process of its own under its run's name; without it every run is its own process."""
    table1 = experiment("table1")
    jobs = [("go1", m, s, "") for s in (0, 1, 2) for m in ("stride", "onn")] + [("go1", "stride", 0, "prior")]
    one_by_one = table1.training_groups(jobs, side_by_side=False)
    assert sorted(one_by_one) == sorted(table1.run_name(*j) for j in jobs)
    assert all(len(g) == 1 for g in one_by_one.values())
    side = table1.training_groups(jobs, side_by_side=True)
    assert sorted(side) == ["go1/onn-s0+1+2", "go1/stride-prior-s0", "go1/stride-s0+1+2"]
    assert [j[2] for j in side["go1/stride-s0+1+2"]] == [0, 1, 2]
    assert sorted(j for g in side.values() for j in g) == sorted(jobs)  # every run trained once
