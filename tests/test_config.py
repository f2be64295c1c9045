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


def test_given_flags_go_on_top_of_the_preset():
    base = Outer(rate=0.1, inner=Inner(steps=3))
    cfg = _parse(["--inner.when", "always", "--no-fast", "--name", "b"], base)
    assert cfg == Outer(name="b", rate=0.1, fast=False, inner=Inner(steps=3, when="always"))
    assert _parse([], {"rate": 2.0}) == Outer(rate=2.0)


def test_to_flags_inverts_from_flags():
    cfg = Outer(name="x y", rate=3.0, fast=False, inner=Inner(steps=7, on=True))
    assert _parse(config.to_flags(cfg)) == cfg


def test_unknown_preset_names_the_choices():
    with pytest.raises(SystemExit, match="tiny, default"):
        config.preset(Outer, {"tiny": {}, "default": {}}, "huge")


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
