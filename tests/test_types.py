"""The concrete parts meet the contracts of ``stride_jax.types``: every dynamics model, both
generators, the MPPI planner, a model's step as a planner's dynamics, and every explorer."""

import functools
import inspect
import typing

import jax
import jax.numpy as jnp
import pytest

from stride_jax import robots, types
from stride_jax.control import mppi, walk
from stride_jax.dynamics import generative, mlp, models

SPEC = types.ModelSpec(nq=2, nv=2, floating_base=False, periodic=(True, False))


def _members(proto) -> list[str]:
    """The methods a protocol declares (``__call__`` for a callable's protocol)."""
    return [n for n, v in vars(proto).items()
            if inspect.isfunction(v) and (n == "__call__" or not n.startswith("_"))]


def _conforms(obj, proto, skip_self: bool = False) -> None:
    """``obj`` has every member of ``proto`` and each accepts the protocol's calls: its required
    arguments alone, and all of them."""
    for name in _members(proto):
        fn = obj if name == "__call__" else getattr(obj, name)
        want = list(inspect.signature(getattr(proto, name)).parameters.values())[1:]
        required = [p for p in want if p.default is inspect.Parameter.empty]
        sig = inspect.signature(fn)
        lead = [None] if skip_self else []
        for args in (required, want):
            try:
                sig.bind(*lead, *[object()] * len(args))
            except TypeError as e:
                raise AssertionError(f"{proto.__name__}.{name}: {fn} does not take "
                                     f"{[p.name for p in args]}: {e}") from None


@pytest.mark.parametrize("name", list(models.MODELS))
def test_every_dynamics_model_is_a_model(name):
    m = models.make(name, SPEC)
    assert isinstance(m, types.Model)
    _conforms(m, types.Model)
    if models.MODELS[name][0] == "structured":
        _conforms(m.acceleration, types.Acceleration)
    else:
        assert m.acceleration is None
    # a model's step with its parameters bound is a planner's dynamics, and runs
    params = m.init(jax.random.key(0))
    dyn = functools.partial(m.step, params)
    assert isinstance(dyn, types.Dynamics)
    _conforms(dyn, types.Dynamics)
    q, qd = dyn(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2), jax.random.key(1))
    assert q.shape == qd.shape == (2,)


@pytest.mark.parametrize("kind", generative.KINDS)
def test_generators_are_generators(kind):
    gen = generative.make(kind, mlp.MLPConfig(8, 1), nfe=2)
    assert isinstance(gen, types.Generator)
    _conforms(gen, types.Generator)
    params = gen.init(jax.random.key(0), 3, 4)
    assert gen.sample(params, jnp.zeros(4), jax.random.key(1), 3).shape == (3,)


def test_mppi_is_a_planner():
    step = lambda q, qd, u, key: (q + qd, qd + u)
    cost = lambda q, qd, u, t: jnp.sum(q ** 2)
    planner = mppi.make(mppi.MPPIConfig(samples=8, horizon=3), step, cost, [-1.0], [1.0])
    assert isinstance(planner, types.Planner) and isinstance(step, types.Dynamics)
    _conforms(planner, types.Planner)
    action, _, _ = planner.step(planner.init(jax.random.key(0)), jnp.zeros(1), jnp.zeros(1))
    assert action.shape == (1,)


@pytest.mark.parametrize("robot", list(robots.ROBOTS))
def test_every_robot_explorer_is_an_explorer(robot):
    ex = robots.get(robot).explorer
    assert isinstance(ex, types.Explorer) and robots.Explorer is types.Explorer
    _conforms(ex, types.Explorer)


def test_the_sine_explorer_of_mjcf_robots_is_an_explorer():
    from stride_jax.robots import mjcf

    ex = mjcf.SineExplorer((0.0,), (1.0,))
    assert isinstance(ex, types.Explorer)
    _conforms(ex, types.Explorer)


def test_the_policy_explorer_is_an_explorer():
    # its constructor loads a PPO run; the methods are checked on the class
    _conforms(walk.PolicyExplorer, types.Explorer, skip_self=True)


def test_a_wrong_signature_does_not_conform():
    with pytest.raises(AssertionError, match="Dynamics.__call__"):
        _conforms(lambda q, qd, u: (q, qd), types.Dynamics)  # no key


def test_the_aliases_name_their_shapes():
    for alias in (types.Q, types.Qd, types.Tau, types.Ctrl, types.Ctrls):
        assert typing.get_origin(alias) is typing.Annotated
        assert typing.get_args(alias)[1].startswith("[")
