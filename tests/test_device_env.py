"""experiments/device_env.sh: a device call's carried site and Menagerie unpacked once, the jobs'
environment exported, and a clear stop where something was not carried."""

import pathlib
import shutil
import subprocess
import tarfile

import pytest

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "device_env.sh"


def _txz(path: pathlib.Path, name: str, text: str) -> None:
    src = path.parent / f"src_{path.name}"
    (src / name).parent.mkdir(parents=True, exist_ok=True)
    (src / name).write_text(text)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(path, "w:xz") as t:
        t.add(src / name.split("/")[0], arcname=name.split("/")[0])
    shutil.rmtree(src)


def _source(cwd, site, *args, env=None):
    cmd = (f'source "{SCRIPT}" {" ".join(args)} && '
           'echo "$PYTHONPATH|$MENAGERIE_ROOT|$STRIDE_COMMIT|$JAX_COMPILATION_CACHE_DIR"')
    return subprocess.run(["bash", "-c", cmd], cwd=cwd, capture_output=True, text=True,
                          env={"PATH": "/usr/bin:/bin", "DEVICE_SITE": str(site), **(env or {})})


def test_unpacks_once_and_exports(tmp_path):
    if shutil.which("bash") is None or shutil.which("xz") is None:
        pytest.skip("bash and xz needed")
    repo, site = tmp_path / "repo", tmp_path / "site"
    _txz(repo / ".whl" / "split" / "site.part.aa", "pkg/mod.py", "x = 1")
    _txz(repo / ".menagerie" / "menagerie_all.tar.xz", "menagerie/unitree_go1/go1.xml", "<mujoco/>")
    out = _source(repo, site, "abc1234")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == (f"{site}:{repo}|{repo}/.menagerie/menagerie|abc1234"
                                  "|/tmp/jax_cache")  # JAX's persistent compilation cache
    assert (site / "pkg" / "mod.py").read_text() == "x = 1" and (site / ".done").exists()
    assert (repo / ".menagerie" / "menagerie" / "unitree_go1" / "go1.xml").exists()
    # once per machine: a second call finds both and unpacks nothing (the archives may be gone)
    (repo / ".whl" / "split" / "site.part.aa").unlink()
    (repo / ".menagerie" / "menagerie_all.tar.xz").unlink()
    again = _source(repo, site, env={"JAX_COMPILATION_CACHE_DIR": "/x/cache"})
    assert again.returncode == 0 and again.stdout.strip().endswith("|/x/cache")  # a set one kept


def test_the_older_archive_names(tmp_path):
    """``.whl/site.tar.xz`` and ``.menagerie/menagerie.tar.xz`` (what table1_device.sh took
    before it used this script) still do."""
    if shutil.which("bash") is None or shutil.which("xz") is None:
        pytest.skip("bash and xz needed")
    repo, site = tmp_path / "repo", tmp_path / "site"
    _txz(repo / ".whl" / "site.tar.xz", "pkg/mod.py", "y = 2")
    _txz(repo / ".menagerie" / "menagerie.tar.xz", "menagerie/unitree_g1/g1.xml", "<mujoco/>")
    out = _source(repo, site)
    assert out.returncode == 0, out.stderr
    assert (site / "pkg" / "mod.py").read_text() == "y = 2"
    assert (repo / ".menagerie" / "menagerie" / "unitree_g1" / "g1.xml").exists()


def test_stops_where_nothing_was_carried(tmp_path):
    if shutil.which("bash") is None:
        pytest.skip("bash needed")
    (tmp_path / "repo").mkdir()
    out = _source(tmp_path / "repo", tmp_path / "site")
    assert out.returncode == 3 and "no carried site" in out.stderr
