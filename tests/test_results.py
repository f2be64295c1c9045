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
