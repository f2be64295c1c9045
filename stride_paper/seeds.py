"""Closed-loop rows over trained seeds, without JAX: which model kind and trained seed a row is,
and whether two kinds are told apart by their seeds (the report and
``experiments/trained_seeds.py`` read rows the same way).

One trained model is one draw of its training (data order, initialisation), so a comparison of
kinds is a comparison of their seeds: each seed's mean over its planner draws that stayed up is
one value, and Welch's t-interval of the difference of the kinds' means says whether these seeds
tell them apart (an interval holding 0 does not).
"""

from __future__ import annotations

import pathlib
import re
from typing import Iterable

import numpy as np

# the closed-loop headline's reading lives beside its grammar (re-exported for the scripts)
from stride_jax.jobs.headline import headline_picks, in_headline  # noqa: F401

_NAME_SEED = re.compile(r"^(?P<kind>.+?)_s(?P<seed>\d+)$")
_RUN_SEED = re.compile(r"-s(?P<seed>\d+)$")


def kind_and_seed(row: dict) -> tuple[str, int]:
    """A row's model kind (its name without a ``_sN`` suffix or ``@part``, then `` (VARIANT)``
    where its table was given as ``VARIANT=PATH``) and trained seed (the run folder's ``-sN``
    where the row names one, else the name's ``_sN``, else 0)."""
    name = str(row["model"]).split("@")[0]
    m = _NAME_SEED.match(name)
    kind = m["kind"] if m else name
    if row.get("variant"):
        kind = f"{kind} ({row['variant']})"
    run = _RUN_SEED.search(pathlib.PurePath(str(row.get("run", ""))).name)
    seed = int(run["seed"]) if run else int(m["seed"]) if m else 0
    return kind, seed


def seed_means(rows: Iterable[dict], fallen: str = "drop") -> dict[int, float]:
    """Each trained seed's mean velocity RMSE over its rows (planner draws) that stayed up.
    A seed whose every draw fell is left out (``fallen="drop"``: it has no tracking to compare)
    or given the mean over all its draws, the error until each fall (``fallen="all"``: for a
    table that shows every seed)."""
    if fallen not in ("drop", "all"):
        raise ValueError(f"fallen must be 'drop' or 'all', got {fallen!r}")
    up: dict[int, list[float]] = {}
    every: dict[int, list[float]] = {}
    for r in rows:
        if r.get("vel_rmse") is None or not np.isfinite(r["vel_rmse"]):
            continue
        seed = kind_and_seed(r)[1]
        every.setdefault(seed, []).append(float(r["vel_rmse"]))
        if not r.get("fell"):
            up.setdefault(seed, []).append(float(r["vel_rmse"]))
    kept = up if fallen == "drop" else {s: up.get(s) or v for s, v in every.items()}
    return {s: float(np.mean(v)) for s, v in sorted(kept.items())}


def welch(x: Iterable[float], y: Iterable[float], level: float = 0.9) -> dict | None:
    """``mean(x) - mean(y)`` with Welch's ``level`` t-interval: ``{diff, lo, hi, n: [nx, ny]}``;
    None with fewer than two values on either side or no spread on both."""
    from scipy import stats

    x, y = np.asarray(list(x), float), np.asarray(list(y), float)
    if len(x) < 2 or len(y) < 2:
        return None
    ci = stats.ttest_ind(x, y, equal_var=False).confidence_interval(level)
    if not (np.isfinite(ci.low) and np.isfinite(ci.high)):
        return None
    return dict(diff=float(x.mean() - y.mean()), lo=float(ci.low), hi=float(ci.high),
                n=[len(x), len(y)])


def fall_rates_differ(falls: int, runs: int, other_falls: int, other_runs: int) -> bool:
    """Whether ``falls`` of ``runs`` and ``other_falls`` of ``other_runs`` are different rates."""
    return falls * other_runs != other_falls * runs


def at_most(falls: int, runs: int, error: float, other_falls: int, other_runs: int,
            other_error: float) -> bool:
    """The closed-loop order of two model kinds in a scenario: the one that falls less often is
    better, whatever its error while upright (measured until each fall); at equal fall rates the
    lower velocity error (a NaN error, no upright draw, loses to any). Whether the first is at
    most the second."""
    if fall_rates_differ(falls, runs, other_falls, other_runs):
        return falls * other_runs < other_falls * runs
    return bool(np.nan_to_num(error, nan=np.inf) <= np.nan_to_num(other_error, nan=np.inf))


def cell_at_most(a: dict | None, b: dict | None) -> bool | None:
    """:func:`at_most` of two cells (a kind's rows in one scenario, as dicts with ``falls``,
    ``episodes`` and ``vel_rmse``); None where either is missing (not run)."""
    if a is None or b is None:
        return None
    return at_most(a["falls"], a["episodes"], a["vel_rmse"], b["falls"], b["episodes"], b["vel_rmse"])
