"""The one table writer of the benchmarks (``stride bench-sim``, ``stride bench-mppi``): a JSON
file of the rows and the environment they were measured in, and a Markdown table of them.

    <out>/<stem>_<cpu|gpu>.json   {"env": {...}, "rows": [{...}, ...]}
    <out>/<stem>_<cpu|gpu>.md     title, command, what was measured, one line per row

The tag is the JAX backend the rows were measured on, so a CPU run never overwrites a GPU table.
Both files are written atomically; a benchmark rewrites them after every row, so a killed run
keeps what it measured.
"""

from __future__ import annotations

import json
import pathlib
from typing import Callable, Sequence

from stride_jax.io import atomic_write_text


def device_tag() -> str:
    """``cpu`` or ``gpu``: the backend the rows are measured on (any accelerator counts as gpu)."""
    import jax

    return "cpu" if jax.default_backend() == "cpu" else "gpu"


def markdown(title: str, command: str, about: str, columns: Sequence[str],
             cells: Sequence[Sequence[str]]) -> str:
    """A Markdown page: ``# title``, the command, ``about`` (a paragraph) and a table whose
    ``columns`` ending in ``:`` are right-aligned (the colon is not shown)."""
    for row in cells:
        if len(row) != len(columns):
            raise ValueError(f"a row has {len(row)} cells for {len(columns)} columns: {row}")
    head = "| " + " | ".join(c.rstrip(":") for c in columns) + " |"
    rule = "|" + "|".join("---:" if c.endswith(":") else "---" for c in columns) + "|"
    lines = [f"# {title}", "", f"Command: `{command}`", "", about, "", head, rule]
    lines += ["| " + " | ".join(row) + " |" for row in cells]
    return "\n".join(lines) + "\n"


def write(out: str | pathlib.Path, stem: str, title: str, command: str, env: dict,
          about: str, columns: Sequence[str], rows: list[dict],
          cells: Callable[[dict], Sequence[str]]) -> pathlib.Path:
    """Writes ``<out>/<stem>_<tag>.json`` (``env`` and ``rows``) and ``.md`` (``cells(row)`` per
    row under ``columns``; see :func:`markdown`); returns the Markdown file's path."""
    tag = device_tag()
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / f"{stem}_{tag}.json", json.dumps(dict(env=env, rows=rows), indent=1))
    path = out / f"{stem}_{tag}.md"
    atomic_write_text(path, markdown(f"{title} ({tag})", command, about, columns,
                                     [cells(r) for r in rows]))
    return path
