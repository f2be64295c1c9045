"""The committed checkpoints are the ones results/SHA256SUMS lists (experiments/checksums.py)."""

import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_checkpoints_match_their_listed_sha256(tmp_path, experiment):
    mod = experiment("checksums")
    listed = (ROOT / "results" / "SHA256SUMS").read_text()
    assert listed == mod.listing(), ("results/SHA256SUMS is stale or a checkpoint changed: "
                                     "run `python experiments/checksums.py` after checking why")
    # the check notices a changed byte
    copy = tmp_path / "models" / "a"
    copy.parent.mkdir()
    copy.write_bytes(b"x")
    before = mod.listing(tmp_path)
    copy.write_bytes(b"y")
    assert mod.listing(tmp_path) != before


def test_every_checkpoint_folder_pattern_names_a_folder_and_prose_is_left_out(tmp_path, experiment):
    mod = experiment("checksums")
    # a pattern that matches nothing would silently drop its checkpoints from the list
    for pattern in mod.FOLDERS:
        assert any(p.is_dir() for p in (ROOT / "results").glob(pattern)), pattern
    # a README beside a checkpoint is not listed; a second learned_* folder is
    for name in ("learned_a", "learned_b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "reward_value.msgpack").write_bytes(b"x")
        (tmp_path / name / "README.md").write_text("notes")
    listed = mod.listing(tmp_path)
    assert "learned_a/reward_value.msgpack" in listed and "learned_b/reward_value.msgpack" in listed
    assert "README.md" not in listed
