"""Joint and body groups of any robot, from its kinematic tree and joint names.

The finer effects (:mod:`stride_jax.gap.finer`) act on a group of actuated joints -- one joint type
on every leg, one leg, one side -- or on the links those joints move. Groups are derived from the
compiled model, not from a list written for one robot:

* **limb**: the actuated joints below one branch of the kinematic tree. A body is a *branching
  point* when two or more of its child subtrees hold actuated joints; a limb starts at the child of
  the tree's root (the free joint's body, or the world for a fixed base) or of a branching point,
  and holds every actuated joint down to the next branching point. A Go1 has four limbs (one per
  leg), a G1 five (two legs, the waist, two arms), a serial arm one.
* **type**: joints that play the same part in different limbs. Joint names are split into tokens
  (at ``_``, ``-``, ``.``, spaces and letter/digit changes); the tokens every joint of a limb shares,
  less those all actuated joints share, name the limb (Go1: ``FR``; G1: ``left``); what is left of a
  joint's name is its type (Go1: ``hip``, ``thigh``, ``calf``; G1: ``knee``, ``hip_pitch``, ...).
  Where names carry no such structure the type is the joint's depth in its limb (``level0``, ...),
  for limbs of equal length only.
* **side** (``left`` / ``right``) and **end** (``front`` / ``rear``): from where each limb's first
  body sits in the base frame at the home pose (MuJoCo's convention: x forward, y left); a limb
  within 2 cm of the mid-plane (a humanoid's waist) belongs to neither side; ends are formed only
  when every limb sits at least 2 cm ahead of or behind the base origin (quadrupeds, not humanoids).
* **joint**: each actuated joint alone (encoder offsets).

Families with fewer than two groups, groups of one joint (other than the joint family) and groups
with the same joints as a group of an earlier family are dropped: such a "group" is either every joint (the plain effect) or one joint. Body groups: each
link body belongs to the nearest actuated joint at or above it; a body group is the links of a
joint group; bodies above every actuated joint form ``base``.

Convenience naming: when two limbs get the same name (a G1's left leg and left arm are both
``left``), leg words (hip, thigh, knee, calf, ankle, foot) and arm words (shoulder, elbow, wrist,
hand) tell them apart (``left_leg``, ``left_arm``), else the limb's first body name is appended.
"""

from __future__ import annotations

import dataclasses
import functools
import re

import mujoco
import numpy as np

from stride_jax.sim.model import SimModel

FAMILIES = ("type", "limb", "side", "end", "joint")
_LEG = {"hip", "thigh", "knee", "calf", "shank", "ankle", "foot", "leg"}
_ARM = {"shoulder", "elbow", "wrist", "hand", "arm", "forearm"}
_MID = 0.02  # m: a limb this close to the mid-plane (or the base origin) has no side (end)


@dataclasses.dataclass(frozen=True)
class Groups:
    """The groups of one robot.

    Attributes:
      joints: ``[nu]`` actuated joint names, in actuator order.
      limb: ``[nu]`` limb name of each actuated joint.
      depth: ``[nu]`` position of each joint in its limb (0: nearest the root).
      families: family -> group name -> actuator indices (sorted tuple).
      bodies: group name (and ``base``) -> body ids of the links the group moves.
    """

    joints: tuple[str, ...]
    limb: tuple[str, ...]
    depth: tuple[int, ...]
    families: dict[str, dict[str, tuple[int, ...]]]
    bodies: dict[str, tuple[int, ...]]

    def joint_index(self, group: str) -> tuple[int, ...]:
        """Actuator indices of ``group`` (a name of any family); ``KeyError`` naming the known
        groups otherwise."""
        for fam in self.families.values():
            if group in fam:
                return fam[group]
        raise KeyError(f"no joint group {group!r}; this robot has {', '.join(self.names())}")

    def family_of(self, group: str) -> str:
        for f, fam in self.families.items():
            if group in fam:
                return f
        raise KeyError(f"no joint group {group!r}")

    def names(self, families=FAMILIES) -> list[str]:
        return [g for f in families for g in self.families.get(f, {})]


def tokens(name: str) -> list[str]:
    """``"FR_calf_joint"`` -> ``["FR", "calf", "joint"]``; ``"joint12"`` -> ``["joint", "12"]``."""
    parts = [p for p in re.split(r"[_\-.\s]+", name) if p]
    return [t for p in parts for t in re.findall(r"[A-Za-z]+|\d+", p)]


def _chain_root(m: mujoco.MjModel, root: int) -> np.ndarray:
    """``[nbody]`` the first body of the limb each body belongs to (-1 for the root and above)."""
    n = m.nbody
    parent = m.body_parentid
    jointed = np.zeros(n, bool)  # subtree holds an actuated joint
    for j in m.actuator_trnid[:, 0]:
        b = int(m.jnt_bodyid[j])
        while True:
            jointed[b] = True
            if b == 0:
                break
            b = int(parent[b])
    branches = np.zeros(n, int)
    for b in range(1, n):
        if jointed[b]:
            branches[parent[b]] += 1
    above = np.zeros(n, bool)  # the root and its ancestors
    b = root
    while True:
        above[b] = True
        if b == 0:
            break
        b = int(parent[b])
    first = np.full(n, -1)
    for b in range(1, n):  # bodies are numbered parents first
        if above[b]:
            continue
        p = int(parent[b])
        first[b] = b if (above[p] or branches[p] >= 2) else first[p]
    return first


def _limb_names(m, firsts: list[int], members: dict[int, list[str]], common: set[str]) -> dict[int, str]:
    raw = {}
    for f in firsts:
        toks = [tokens(n) for n in members[f]]
        shared = set.intersection(*({t.lower() for t in tk} for tk in toks)) - common
        if len(members[f]) < 2:
            shared = set()
        raw[f] = "_".join(t for t in toks[0] if t.lower() in shared) or m.body(f).name or f"limb{f}"
    out = {}
    for f, name in raw.items():
        if list(raw.values()).count(name) > 1:
            words = {t.lower() for n in members[f] for t in tokens(n)}
            word = "leg" if words & _LEG else "arm" if words & _ARM else (m.body(f).name or str(f))
            name = f"{name}_{word}"
        out[f] = name
    if len(set(out.values())) < len(out):  # still ambiguous: the first body's name
        out = {f: f"{n}_{m.body(f).name or f}" for f, n in out.items()}
    return out


@functools.lru_cache(maxsize=None)
def of(sm: SimModel) -> Groups:
    """The groups of robot ``sm`` (cached per compiled model)."""
    m = sm.mj
    jnt = [int(j) for j in m.actuator_trnid[:, 0]]
    names = tuple(m.joint(j).name or f"joint{j}" for j in jnt)
    root = int(sm.base_body) if sm.robot.floating_base else 0
    first = _chain_root(m, root)
    lf = [int(first[m.jnt_bodyid[j]]) for j in jnt]
    firsts = sorted(set(lf))
    members = {f: [names[i] for i in range(len(jnt)) if lf[i] == f] for f in firsts}
    common = set.intersection(*({t.lower() for t in tokens(n)} for n in names)) if names else set()
    limb_name = _limb_names(m, firsts, members, common)
    limb = tuple(limb_name[f] for f in lf)
    depth = tuple(sorted(i for i in range(len(jnt)) if lf[i] == lf[a]).index(a) for a in range(len(jnt)))
    fam: dict[str, dict[str, list[int]]] = {f: {} for f in FAMILIES}
    # types: the name less the limb's own tokens and the tokens every joint shares
    for a, n in enumerate(names):
        own = {t.lower() for t in tokens(limb[a])} if len(members[lf[a]]) >= 2 else set()
        key = "_".join(t for t in tokens(n) if t.lower() not in own | common)
        fam["type"].setdefault(key or f"level{depth[a]}", []).append(a)
    if not any(len(v) >= 2 for v in fam["type"].values()):  # no name structure: depth in equal limbs
        sizes = {f: len(members[f]) for f in firsts}
        fam["type"] = {}
        if len(set(sizes.values())) == 1 and len(firsts) >= 2:
            for a in range(len(names)):
                fam["type"].setdefault(f"level{depth[a]}", []).append(a)
    for a in range(len(names)):
        fam["limb"].setdefault(limb[a], []).append(a)
        fam["joint"][names[a]] = [a]
    # sides and ends from the limbs' first bodies in the base frame at the home pose
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(sm.info.qpos0, np.float64)
    mujoco.mj_kinematics(m, d)
    R, p0 = d.xmat[root].reshape(3, 3), d.xpos[root]
    pos = {f: R.T @ (d.xpos[f] - p0) for f in firsts}
    for a in range(len(names)):
        y = pos[lf[a]][1]
        if abs(y) > _MID:
            fam["side"].setdefault("left" if y > 0 else "right", []).append(a)
    if len(firsts) >= 4 and all(abs(pos[f][0]) > _MID for f in firsts):
        for a in range(len(names)):
            fam["end"].setdefault("front" if pos[lf[a]][0] > 0 else "rear", []).append(a)
    families: dict[str, dict[str, tuple[int, ...]]] = {}
    taken: set[str] = set()
    seen: set[tuple[int, ...]] = set()  # a group of an earlier family with the same joints (a
    for f in FAMILIES:                  # two-armed robot's left limb and left side) is not repeated
        groups = {g: tuple(sorted(ix)) for g, ix in fam[f].items()
                  if f == "joint" or (2 <= len(ix) < len(names) and tuple(sorted(ix)) not in seen)}
        seen |= set(groups.values())
        if f != "joint" and len(groups) < 2:
            continue
        renamed = {}
        for g, ix in groups.items():
            name = g if g not in taken and g != "base" else f"{f}_{g}"
            taken.add(name)
            renamed[name] = ix
        families[f] = renamed
    # link bodies: each body belongs to the nearest actuated joint at or above it
    owner = np.full(m.nbody, -1)
    jbody = {int(m.jnt_bodyid[j]): a for a, j in enumerate(jnt)}
    for b in range(1, m.nbody):
        owner[b] = jbody.get(b, owner[m.body_parentid[b]])
    # (a fixed base's links above every joint are welded to the world: their mass does nothing)
    bodies = {"base": tuple(int(b) for b in range(1, m.nbody) if owner[b] < 0 and m.body_mass[b] > 0
                            and sm.robot.floating_base)}
    for f in ("type", "limb"):
        for g, ix in families.get(f, {}).items():
            bodies[g] = tuple(int(b) for b in range(1, m.nbody) if owner[b] in ix and m.body_mass[b] > 0)
    return Groups(joints=names, limb=limb, depth=depth, families=families, bodies=bodies)


def describe(g: Groups) -> str:
    """One line per family, for reports."""
    return "; ".join(f"{f}: " + ", ".join(f"{n} ({len(ix)})" for n, ix in fam.items())
                     for f, fam in g.families.items() if f != "joint")
