"""The library imports no job, report or command line: every module of ``robots``, ``sim``,
``dynamics``, ``train``, ``control``, ``gap`` and ``eval`` (and the top-level helpers) is read as
an AST, and none of its imports -- at the top, inside a function, or relative -- names
``stride_jax.jobs``, ``stride_jax.cli``, ``stride_paper`` or ``experiments``."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "stride_jax"
LIBRARY = ("robots", "sim", "dynamics", "train", "control", "gap", "eval")
TOP_LEVEL = ("__init__.py", "_env.py", "config.py", "distributed.py", "io.py", "timing.py",
             "types.py")
FORBIDDEN = ("stride_jax.jobs", "stride_jax.cli", "stride_paper", "experiments")


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(source: str, module: str, is_package: bool = False) -> list[str]:
    """Every module name ``source`` (the text of ``module``) imports, relative imports resolved;
    for ``from X import Y`` both ``X`` and ``X.Y`` (``Y`` may be a submodule)."""
    package = module if is_package else module.rpartition(".")[0]
    names = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                origin = ".".join(base + ([node.module] if node.module else []))
            else:
                origin = node.module
            names.append(origin)
            names += [f"{origin}.{a.name}" for a in node.names]
    return names


def forbidden_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    return sorted({n for n in imported_names(source, module, is_package)
                   for f in FORBIDDEN if n == f or n.startswith(f + ".")})


def library_files() -> list[pathlib.Path]:
    files = [p for pkg in LIBRARY for p in sorted((PACKAGE / pkg).rglob("*.py"))]
    return files + [PACKAGE / name for name in TOP_LEVEL]


def test_every_library_package_and_helper_is_checked():
    """The list above covers every package of stride_jax but the jobs (a new package must be
    placed on one side or the other)."""
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    assert packages == set(LIBRARY) | {"jobs"}
    helpers = {p.name for p in PACKAGE.glob("*.py")}
    assert helpers == set(TOP_LEVEL) | {"cli.py"}


@pytest.mark.parametrize("path", library_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_library_module_imports_no_job_report_or_cli(path):
    found = forbidden_imports(path.read_text(), _module_name(path), path.name == "__init__.py")
    assert not found, f"{path.relative_to(ROOT)} imports {found}: move it to stride_jax.jobs"


def test_the_check_sees_every_spelling():
    """Absolute, from-, aliased, nested and relative imports of a job are all caught."""
    mod = "stride_jax.sim.x"
    for src in ("import stride_jax.jobs.data", "from stride_jax.jobs import data",
                "from stride_jax import jobs", "from stride_jax import cli as c",
                "def f():\n    from stride_paper import figures",
                "import experiments.table1", "from ..jobs import train", "from .. import cli"):
        assert forbidden_imports(src, mod), src
    for src in ("from stride_jax import config, io", "from stride_jax.sim import dataset",
                "from . import model", "import stride_jax", "from stride_jax.jobsite import x"):
        assert not forbidden_imports(src, mod), src


@pytest.mark.parametrize("path", sorted((PACKAGE / "train").rglob("*.py")),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_training_imports_no_evaluation(path):
    """Training comes before evaluation: ``train`` uses ``dynamics`` and ``sim`` helpers, never
    ``eval`` (which may load trained runs)."""
    names = imported_names(path.read_text(), _module_name(path), path.name == "__init__.py")
    found = sorted({n for n in names if n == "stride_jax.eval" or n.startswith("stride_jax.eval.")})
    assert not found, f"{path.relative_to(ROOT)} imports {found}"


@pytest.mark.parametrize("path", sorted(p for d in ("experiments", "stride_paper", "stride_jax")
                                        for p in (ROOT / d).rglob("*.py")),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_no_script_or_module_reaches_into_the_tests(path):
    """Drivers, probes and the library import nothing from ``tests/`` (a helper both need lives
    in the library or beside the script), nor put ``tests`` on ``sys.path``."""
    source = path.read_text()
    names = imported_names(source, _module_name(path), path.name == "__init__.py")
    found = sorted({n for n in names if n.split(".")[0].startswith(("test_", "tests", "conftest",
                                                                    "precision"))})
    assert not found, f"{path.relative_to(ROOT)} imports {found} from the tests"
    on_path = [line for line in source.splitlines() if "sys.path" in line and "tests" in line]
    assert not on_path, f"{path.relative_to(ROOT)} puts the tests on sys.path: {on_path}"


def _runtime_imports(path: pathlib.Path) -> set[str]:
    """The library modules ``path`` imports at run time (anywhere in the file, functions
    included), not those under ``if TYPE_CHECKING:`` (annotations only)."""
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for node in ast.walk(tree)
                   if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
                   for n in ast.walk(node)}
    module = _module_name(path)
    kept = ast.Module([n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
                       and id(n) not in typing_only], [])
    return set(imported_names(ast.unparse(kept), module, path.name == "__init__.py"))


def import_cycles() -> list[list[str]]:
    """The strongly connected groups of two or more modules in the graph of ``stride_jax``'s
    module-to-module imports (Tarjan). Edges into a package's ``__init__`` are left out: ``from
    stride_jax.gap import effects`` names the package only on the way to its module."""
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {m: sorted(n for n in _runtime_imports(p) if n in files and n != m
                       and not files[n].name == "__init__.py") for m, p in files.items()}
    index, low, stack, on, groups = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
                on.discard(group[-1])
            if len(group) > 1:
                groups.append(sorted(group))

    for v in graph:
        if v not in index:
            visit(v)
    return groups


def test_no_import_cycles():
    """No two modules of the package import each other, directly or around a circle, even from
    inside a function (a deferred import is a cycle all the same); type-only imports aside."""
    assert import_cycles() == []


def test_the_cycle_check_sees_a_deferred_cycle(tmp_path, monkeypatch):
    pkg = tmp_path / "stride_jax"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from stride_jax import b\n")
    (pkg / "b.py").write_text("def f():\n    from stride_jax import a\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                              "    from stride_jax import a\n")
    monkeypatch.setitem(globals(), "PACKAGE", pkg)
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    assert import_cycles() == [["stride_jax.a", "stride_jax.b"]]
