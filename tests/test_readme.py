"""The README's example of composing a trained model into user JAX code runs as written."""

import pathlib
import re

from stride_jax import cli

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_example_runs(tmp_path, capsys):
    run = tmp_path / "run"
    cli.main(["data", "--robot", "pendulum", "--preset", "tiny", "--out", str(tmp_path / "d")])
    cli.main(["train", "--robot", "pendulum", "--preset", "tiny", "--steps", "20",
              "--eval-every", "10", "--data", str(tmp_path / "d"), "--out", str(run)])
    text = README.read_text()
    block = re.search(r"README-EXAMPLE.*?```python\n(.*?)```", text, re.S).group(1)
    capsys.readouterr()
    exec(compile(block, "README example", "exec"), {"RUN": str(run)})
    assert "(64, 30, 1)" in capsys.readouterr().out
