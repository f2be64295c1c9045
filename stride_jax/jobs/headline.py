"""A merged closed-loop table's headline: which of its rows are the current planner's.

``stride_jax.jobs.closed_loop.merge(..., headline=...)`` (``experiments/closed_loop_merge.py
--headline``) names them by entries ``PART[:MODEL+MODEL][/SCENARIO+SCENARIO]``: ``PART`` takes
all the part's rows, ``PART:MODEL+MODEL`` only those models' (a run's policy-alone rows without
its planner's, say), ``PART/SCENARIO+SCENARIO`` only those scenarios' (a part whose other
scenarios a later planner setting has replaced), ``PART:MODELS/SCENARIOS`` both. The merge
validates the entries against its rows (:func:`check_entries`); the report and the experiment
scripts read them (:func:`headline_picks`, :func:`in_headline`). One grammar, one place; no JAX
(``stride_paper.seeds`` and the report import it).
"""

from __future__ import annotations

from typing import Iterable

Pick = frozenset  # of (models, scenarios) clauses, each a frozenset of names or None (any)


def parse_entry(entry: str) -> tuple[str, frozenset[str] | None, frozenset[str] | None]:
    """``PART[:MODEL+MODEL][/SCENARIO+SCENARIO]`` as ``(part, models, scenarios)`` (None: all).
    A ``:`` or ``/`` followed by no name is an error (it would silently take every row)."""
    head, slash, scen = entry.partition("/")
    part, colon, models = head.partition(":")
    if not part:
        raise ValueError(f"headline entry {entry!r}: no part named")
    names = frozenset(m for m in models.split("+") if m) or None
    scenarios = frozenset(s for s in scen.split("+") if s) or None
    for sep, given, what in ((colon, names, "models"), (slash, scenarios, "scenarios")):
        if sep and given is None:
            raise ValueError(f"headline entry {entry!r}: {sep!r} names no {what}")
    return part, names, scenarios


def check_entries(entries: Iterable[str], parts: Iterable[str], rows: list[dict]) -> None:
    """Raises where an entry names a part the table lacks, or models or scenarios its part has no
    rows of (rows with ``part``, ``model`` and ``scenario``; a model by its merged name or the
    name before ``@part``)."""
    parts = list(parts)
    for entry in entries:
        part, models, scenarios = parse_entry(entry)
        if part not in parts:
            raise ValueError(f"headline {entry!r}: {part!r} is not a part of the table "
                             f"(parts: {', '.join(parts)})")
        mine = [r for r in rows if r.get("part") == part]
        held_models = {n for r in mine for n in (r["model"], str(r["model"]).split("@")[0])}
        held_scenarios = {r["scenario"] for r in mine}
        for what, given, held in (("models", models, held_models),
                                  ("scenarios", scenarios, held_scenarios)):
            absent = sorted((given or set()) - held)
            if absent:
                raise ValueError(f"headline {entry!r}: part {part!r} has no rows of {absent!r} "
                                 f"(its {what}: {', '.join(sorted(held))})")


def headline_picks(table: dict) -> dict[str, Pick | None] | None:
    """A merged table's ``headline`` as ``{part: clauses}`` (None: all the part's rows); a row is
    in where any of its part's entries takes it. None where the table names no headline."""
    entries = (table.get("headline") or {}).get("parts")
    if not entries:
        return None
    picks: dict[str, Pick | None] = {}
    for entry in entries:
        part, models, scenarios = parse_entry(str(entry))
        have = picks.get(part, frozenset())
        whole = models is None and scenarios is None
        picks[part] = None if whole or have is None else have | {(models, scenarios)}
    return picks


def in_headline(row: dict, picks: dict[str, Pick | None]) -> bool:
    """Whether ``row`` is among :func:`headline_picks`' rows (a model named by its merged name
    or by the name before ``@part``)."""
    part = row.get("part")
    if part not in picks:
        return False
    if picks[part] is None:
        return True
    names = {row["model"], str(row["model"]).split("@")[0]}
    return any((models is None or bool(names & models))
               and (scenarios is None or row["scenario"] in scenarios)
               for models, scenarios in picks[part])
