"""experiments/device_tree.sh: large committed folders leave the tree a device call sends (untracked
and excluded, the files kept), and come back with the index and exclude file as they were."""

import pathlib
import shutil
import subprocess

import pytest

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "device_tree.sh"


def _git(repo, *args):
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True,
                          text=True).stdout


@pytest.fixture
def repo(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    _git(tmp_path, "init", "-q")
    for name in ("results/models/a/w.npz", "results/models/b/w.npz", "results/table.md", "code.py"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(name)
    (tmp_path / ".git" / "info").mkdir(exist_ok=True)
    (tmp_path / ".git" / "info" / "exclude").write_text("/.whl/\n")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-q", "-m", "x")
    return tmp_path


def _run(repo, *args, ok=True):
    p = subprocess.run(["bash", str(SCRIPT), *args], cwd=repo, capture_output=True, text=True)
    assert (p.returncode == 0) == ok, p.stderr
    return p.stdout + p.stderr


def test_out_leaves_the_folders_out_of_what_a_call_sends_and_back_restores_them(repo):
    exclude = (repo / ".git" / "info" / "exclude").read_text()
    said = _run(repo, "out")
    kept = len("code.py") + len("results/table.md")  # each file holds its own name
    assert f"tracked tree now {kept} bytes" in said
    assert _run(repo, "size").strip() == str(kept)
    tracked = _git(repo, "ls-files").split()
    assert tracked == ["code.py", "results/table.md"]
    # what a device call sends: tracked plus untracked-not-ignored files
    sent = _git(repo, "ls-files", "--cached", "--others", "--exclude-standard").split()
    assert not any(p.startswith("results/models") for p in sent)
    assert (repo / "results/models/a/w.npz").read_text() == "results/models/a/w.npz"
    assert "already out" in _run(repo, "out", "results/table.md", ok=False)
    assert "out: results/models" in _run(repo, "status")
    _run(repo, "back")
    assert len(_git(repo, "ls-files").split()) == 4 and _git(repo, "status", "--short") == ""
    assert (repo / ".git" / "info" / "exclude").read_text() == exclude
    assert "nothing is out" in _run(repo, "back")


def test_named_paths_and_bad_ones(repo):
    _run(repo, "out", "results/models/a/")
    assert "results/models/b/w.npz" in _git(repo, "ls-files")
    _run(repo, "back")
    assert "no tracked files" in _run(repo, "out", "results/nothing", ok=False)
    assert "usage" in _run(repo, "sideways", ok=False)


def test_keep_leaves_out_every_model_policy_and_large_result_folder_but_the_kept(repo):
    """``keep PATH...``: every folder of results/models and results/policies and the large
    result folders go out but the kept paths; a kept path inside a folder keeps that folder's
    other folders out (its files stay: the exclude file takes folders); ``back`` as ever."""
    for name in ("results/models/a/s0/w.npz", "results/models/a/s1/w.npz", "results/models/a/c.json",
                 "results/policies/p/w.npz", "results/policies/q/w.npz", "results/policies/README.md",
                 "results/closed_loop/t.json"):
        (repo / name).parent.mkdir(parents=True, exist_ok=True)
        (repo / name).write_text(name)
    _git(repo, "add", ".")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-q", "-m", "more")
    _run(repo, "keep", "results/models/a/s0", "results/policies/p/")
    out = _run(repo, "status").split("\n")[0].split()[1:]
    assert sorted(out) == ["results/closed_loop", "results/models/a/s1", "results/models/b",
                           "results/policies/q"]
    sent = _git(repo, "ls-files", "--cached", "--others", "--exclude-standard").split()
    assert "results/models/a/s0/w.npz" in sent and "results/policies/p/w.npz" in sent
    assert "results/models/a/c.json" in sent and "results/models/a/s1/w.npz" not in sent
    _run(repo, "back")
    assert _git(repo, "status", "--short") == ""
    assert "no tracked files" in _run(repo, "keep", "results/policies/none", ok=False)
