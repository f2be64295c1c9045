"""How fine an explanation the logs support, and which effects they cannot tell apart.

**The finer choice** (:func:`prefer_coarse`). A finer variant (``damping@calf``: one joint group)
has as many parameters as its all-joints effect (``damping``) but fewer joints: on training data it
can only lose to it where the effect is on every joint, yet held out it may win by chance or by a
hair. The held-out ranking decides, with a stated margin: the variant stays above its all-joints
effect only if (a) it removes at least ``finer_margin`` (10%) of what the all-joints effect leaves of
the held-out gap above the noise floor (the pair rule's measure) and (b) the paired block bootstrap
of the held-out split puts its gain above zero at level ``alpha``; otherwise it is moved just below the all-joints effect, and each variant's
row records the comparison (``vs_all_joints``). Variants of several groups at once are pairs
(``damping@calf`` + ``damping@thigh``) and pass the pair rule instead.

**Indistinguishable sets** (:func:`indistinguishable`): the best hypothesis's effects together with
(a) hypotheses fitted in full that match or beat it in at least ``alpha`` of the paired held-out
resamples (identical held-out score within noise), and (b) candidates whose sensitivity columns on
the training windows are collinear with one of its effects (``|cos| >= collinear``; the screen's
secants at the nominal model), each with its reason. One set, not a ranking: the logs support the
set, not a member.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stride_jax.gap import effects, finer

def coarse_of(sm, name: str) -> str | None:
    """The all-joints effect that the finer variant ``name`` refines, where it applies to ``sm``
    (None for an all-joints effect, or a finer effect without one: encoder offsets, link groups)."""

    c = finer.parent(name)
    return c if c != name and c in effects.ALL and effects.ALL[c].applies(sm) else None

def prefer_coarse(rows: list[dict[str, Any]], margin: float, alpha: float, floor=lambda names: 0.0
                  ) -> list[dict[str, Any]]:
    """Reorders ranking ``rows`` (sorted best first, each with ``_boot`` resamples of the held-out
    explained fraction) so that no single finer variant ranks above its all-joints effect unless it
    passes the margin rule; ``floor(names)`` is the noise floor of a hypothesis's held-out residual
    as a fraction of the nominal held-out gap. Returns the rows."""
    by_name = {r["effects"][0]: r for r in rows if len(r["effects"]) == 1}
    for name, row in list(by_name.items()):
        coarse = finer.parent(name)
        if coarse == name or coarse not in by_name:
            continue
        P = by_name[coarse]
        gain = row["explained"] - P["explained"]
        left = max(1 - P["explained"] - floor((coarse,)), 0.0)
        lower = float(np.quantile(row["_boot"] - P["_boot"], alpha))
        ok = bool(gain >= margin * left and gain > 0 and lower > 0)
        row["vs_all_joints"] = {"all_joints": coarse, "gain_explained": float(gain), "gain_lower": lower,
                                "coarse_left_above_floor": float(left), "fraction_of_left": float(gain / max(left, 1e-300)),
                                "margin": margin, "preferred": ok,
                                "rule": f"a finer variant is preferred only if it removes at least {margin:.0%} of what "
                                        f"{coarse} leaves of the held-out gap above the noise floor and its paired "
                                        f"gain's {alpha:.0%} bootstrap quantile is above zero"}
        if not ok and rows.index(row) < rows.index(P):
            rows.remove(row)
            rows.insert(rows.index(P) + 1, row)
    return rows

def indistinguishable(w: dict[str, Any], collinear: dict[str, dict[str, float]], alpha: float
                      ) -> dict[str, Any] | None:
    """The set of effects the logs cannot tell apart from the best hypothesis of ``w`` (the result
    of :func:`stride_jax.gap.attribute.which`), with a reason per member; ``collinear`` maps each of
    the best's effects to ``{candidate: cos}`` (:func:`stride_jax.gap.screen.collinear_with`).
    None when nothing ties."""
    best = w["ranking"][0]
    members: dict[str, str] = {}
    for r in w["ranking"][1:]:
        if r.get("p_matches_best", 0.0) < alpha:
            continue
        if set(r["effects"]) <= set(best["effects"]) or set(best["effects"]) <= set(r["effects"]):
            continue
        members["+".join(r["effects"])] = (
            f"identical held-out score within noise: explains {r['explained']:.1%} of the held-out gap against "
            f"{best['explained']:.1%}, and matches or beats it in {r['p_matches_best']:.0%} of the paired "
            f"resamples (at least {alpha:.0%})")
    for e, cos in collinear.items():
        for other, c in cos.items():
            if other in best["effects"]:
                continue
            # the best with e swapped for its collinear twin (a pair stays a pair)
            alt = "+".join(other if x == e else x for x in best["effects"])
            why = f"collinear sensitivity columns with {e} (cos {c:+.3f} on the training windows)"
            members[alt] = f"{members[alt]}; and {why}" if alt in members else why
    if not members:
        return None
    names = ["+".join(best["effects"])] + list(members)
    return {"effects": names, "reasons": members,
            "summary": "the logs cannot tell apart " + ", ".join(names) + ": "
                       + "; ".join(f"{k}: {v}" for k, v in members.items())}
