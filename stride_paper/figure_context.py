"""What the parts of ``experiments/reproduce.py`` share: the context each part runs in (its
title line, its JSON writer), the device it ran on, list parsing of the config's strings, and
matplotlib for the figures (files only: the Agg backend)."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import platform
from typing import Callable

import jax
import numpy as np

from stride_jax.io import atomic_write_text
from stride_paper.figures_config import ReproduceConfig


def split_ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x.strip()]


def split_names(s: str) -> list[str]:
    return [x.strip() for x in s.split(",") if x.strip()]


def device_text() -> str:
    d, host = jax.devices()[0], platform.processor() or platform.machine()
    return f"{d.device_kind} ({jax.default_backend()}; {host})"


@dataclasses.dataclass(frozen=True)
class Context:
    """What every part of a reproduction shares: its config, the preset tag of its runs, the
    figures folder, the evaluation cache, the command (for titles and JSON) and the log."""

    cfg: ReproduceConfig
    tag: str
    out: pathlib.Path
    cache: pathlib.Path
    command: str
    log: Callable[[str], None]

    def title(self, what: str) -> str:
        return f"{what}\n`{self.command}` ({self.tag} runs; {device_text()})"

    def write(self, name: str, numbers: dict) -> None:
        atomic_write_text(self.out / f"{name}.json", json.dumps(
            {"command": self.command, "preset_tag": self.tag, "device": device_text(),
             **numbers}, indent=1, default=json_default))


def json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (figures go to files; no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: pathlib.Path, title: str = "", dpi: int = 110) -> pathlib.Path:
    """Writes ``fig`` to ``path`` under ``title`` (small, above the panels) and closes it."""
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path
