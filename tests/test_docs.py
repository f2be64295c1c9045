"""``docs/compose.md`` runs as written: its Python blocks in order, in one namespace, in a
scratch folder (they write ``runs/``)."""

import pathlib
import re

import numpy as np

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "compose.md"


def test_compose_page_runs(tmp_path, monkeypatch, capsys):
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert len(blocks) == 3
    monkeypatch.chdir(tmp_path)
    ns = {"__name__": "compose"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"docs/compose.md block {i + 1}", "exec"), ns)
        if i == 1:  # the gradient-based MPC brought the real pendulum to the target
            np.testing.assert_allclose(float(ns["q"][0]), float(ns["target"][0]), atol=0.05)
    target = float(ns["target"][0])
    np.testing.assert_allclose(float(ns["q"][0]), target, atol=0.05)  # held by computed torque
    assert (tmp_path / "runs" / "my_pendulum" / "model.json").is_file()
    model, params, up = ns["model"], ns["params"], ns["up"]
    np.testing.assert_allclose(ns["dyn"].gravity(model, params, up), 9.81, atol=0.2)
