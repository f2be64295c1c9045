"""Flags derived from config dataclasses (stride_jax/config.py): nested, bool and str fields."""

import argparse
import dataclasses

import pytest

from stride_jax import config


@dataclasses.dataclass(frozen=True)
class Inner:
    steps: int = 10
    when: str = "never"
    on: bool = False


@dataclasses.dataclass(frozen=True)
class Outer:
    name: str = "a"
    rate: float = 0.5
    fast: bool = True
    inner: Inner = Inner()
    shape: tuple[int, ...] = (1, 2)  # no flag: stays at the preset's value


def _parse(argv, base=None):
    p = argparse.ArgumentParser()
    config.add_flags(p, Outer)
    return config.from_flags(Outer, p.parse_args(argv), base)


def test_flags_cover_nested_bool_and_str_fields():
    names = {flag for flag, _, _ in config.flag_names(Outer).values()}
    assert names == {"--name", "--rate", "--fast", "--inner.steps", "--inner.when", "--inner.on"}


def test_a_nested_default_is_the_outer_configs():
    """Help shows the default the outer config holds for a nested field, not the nested class's
    own (a job that nests ``MPPIConfig(horizon=25)`` says 25)."""

    @dataclasses.dataclass(frozen=True)
    class Job:
        inner: Inner = Inner(steps=3, on=True)

    defaults = {dest: d for dest, (_, _, d) in config.flag_names(Job).items()}
    assert defaults == {"inner.steps": 3, "inner.when": "never", "inner.on": True}
    p = argparse.ArgumentParser()
    config.add_flags(p, Job)
    assert "(default 3)" in p.format_help()


def test_given_flags_go_on_top_of_the_preset():
    base = Outer(rate=0.1, inner=Inner(steps=3))
    cfg = _parse(["--inner.when", "always", "--no-fast", "--name", "b"], base)
    assert cfg == Outer(name="b", rate=0.1, fast=False, inner=Inner(steps=3, when="always"))
    assert _parse([], Outer(rate=2.0)) == Outer(rate=2.0)


def test_to_flags_inverts_from_flags():
    cfg = Outer(name="x y", rate=3.0, fast=False, inner=Inner(steps=7, on=True))
    assert _parse(config.to_flags(cfg)) == cfg


def test_unknown_preset_names_the_choices():
    presets = {"tiny": Outer(rate=0.1), "default": Outer(), "old": {"rate": 0.1}}
    assert config.preset(Outer, presets, "tiny") is presets["tiny"]
    with pytest.raises(SystemExit, match="tiny, default"):
        config.preset(Outer, presets, "huge")
    with pytest.raises(TypeError, match="named instances"):
        config.preset(Outer, presets, "old")


def test_every_preset_table_holds_named_instances():
    """No ``PRESETS`` table of the library, its jobs, experiments or the paper holds a dict of
    overrides (``dict(...)`` or ``{...}``): each preset is an instance of its config."""
    import ast
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1]
    tables = 0
    for path in [p for d in ("stride_jax", "experiments", "stride_paper")
                 for p in sorted((root / d).rglob("*.py"))]:
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict)
                    and any(isinstance(t, ast.Name) and t.id.endswith("PRESETS")
                            for t in node.targets)):
                continue
            tables += 1
            for key, value in zip(node.value.keys, node.value.values):
                is_dict = isinstance(value, ast.Dict) or (
                    isinstance(value, ast.Call) and isinstance(value.func, ast.Name)
                    and value.func.id == "dict")
                assert not is_dict, f"{path.relative_to(root)}:{value.lineno}: preset " \
                                    f"{ast.literal_eval(key)!r} is a dict of overrides"
    assert tables >= 15


def test_help_comes_from_the_attributes_docstring():
    @dataclasses.dataclass(frozen=True)
    class Documented:
        """Attributes:
          a, b: two numbers that
            share a line.
          c: a third.
        """

        a: int = 1
        b: int = 2
        c: int = 3

    assert config.field_docs(Documented) == {"a": "two numbers that share a line.",
                                             "b": "two numbers that share a line.",
                                             "c": "a third."}
