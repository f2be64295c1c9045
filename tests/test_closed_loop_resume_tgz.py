"""``experiments/closed_loop_targets.sh`` resumes a part from a carried ``OUT.tgz`` (``RESUME``):
unpacked beside OUT where OUT does not exist yet, a clear error where the file is missing or holds
another part."""

import os
import pathlib
import subprocess
import sys
import tarfile

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run(tmp_path, out, resume):
    env = dict(os.environ, RESUME=str(resume), PATH=f"{pathlib.Path(sys.executable).parent}:{os.environ['PATH']}")
    # a 1 s limit: the closed-loop job itself is stopped at once; only the unpacking is looked at
    return subprocess.run(["bash", str(ROOT / "experiments/closed_loop_targets.sh"), "go1", str(out), "1", "policy",
                           "slope"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)


def _tgz(tmp_path, name):
    part = tmp_path / "made" / name
    (part / "partial").mkdir(parents=True)
    (part / "closed_loop.json").write_text('{"rows": []}')
    (part / "partial" / "slope_policy.npz").write_bytes(b"state")
    with tarfile.open(tmp_path / f"{name}.tgz", "w:gz") as t:
        t.add(part, arcname=name)
    return tmp_path / f"{name}.tgz"


def test_a_carried_tgz_is_unpacked_where_the_part_does_not_exist(tmp_path):
    tgz = _tgz(tmp_path, "d4_slope")
    out = tmp_path / "w" / "d4_slope"
    r = _run(tmp_path, out, tgz)
    assert f"{out} unpacked from {tgz}" in r.stdout, r.stdout + r.stderr
    assert (out / "partial" / "slope_policy.npz").read_bytes() == b"state"
    assert (out / "closed_loop.json").read_text() == '{"rows": []}'
    # a part already there is not overwritten
    (out / "closed_loop.json").write_text("newer")
    r = _run(tmp_path, out, tgz)
    assert "unpacked" not in r.stdout and (out / "closed_loop.json").read_text() == "newer"


def test_a_missing_or_foreign_tgz_is_an_error_naming_it(tmp_path):
    r = _run(tmp_path, tmp_path / "w" / "d4_slope", tmp_path / "nothing.tgz")
    assert r.returncode == 2 and "nothing.tgz: no such file" in r.stderr
    r = _run(tmp_path, tmp_path / "w" / "d4_tilt", _tgz(tmp_path, "d4_slope"))
    assert r.returncode == 2 and "holds no folder d4_tilt/" in r.stderr
