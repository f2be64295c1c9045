"""The test suite in several pytest processes at once (``make test``).

Most of the suite's time is XLA and MJX compiling, one core per process, so on CI's two cores
two processes take about two thirds of one's time. Test files go to the processes greedily by
their measured durations (``tests/durations.json``, rewritten with ``--record``; a new file
counts as the median). Each process's output is streamed with its number in front; the exit
status is non-zero when any process fails.

    python tests/run_parallel.py [--workers N] [--all] [--record] [-- PYTEST_ARGS... [tests/test_X.py ...]]

``--all`` runs the tests marked slow too (``make test-all``); without it pytest's own default
(pyproject.toml: ``-m 'not slow'``) leaves them out, as ``make test`` does.

Test files among the pytest arguments are the ones run; without any, every ``tests/test_*.py``.
The workers share one JAX compilation cache for the run (a temporary folder, unless
``JAX_COMPILATION_CACHE_DIR`` is set).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import threading
import xml.etree.ElementTree as ET

TESTS = pathlib.Path(__file__).resolve().parent
DURATIONS = TESTS / "durations.json"


def plan(files: list[str], durations: dict[str, float], workers: int) -> list[list[str]]:
    """Files split into ``workers`` groups of about equal measured time (longest first)."""
    default = statistics.median(durations.values()) if durations else 1.0
    cost = {f: durations.get(f, default) for f in files}
    groups: list[list[str]] = [[] for _ in range(workers)]
    totals = [0.0] * workers
    for f in sorted(files, key=lambda f: -cost[f]):
        i = totals.index(min(totals))
        groups[i].append(f)
        totals[i] += cost[f]
    return [g for g in groups if g]


def _stream(i: int, proc: subprocess.Popen) -> None:
    for line in proc.stdout:
        sys.stdout.write(f"[{i}] {line}")
        sys.stdout.flush()


def file_durations(junit: pathlib.Path) -> dict[str, float]:
    """Seconds per test file (setup, call and teardown) from a pytest JUnit XML report."""
    out: dict[str, float] = {}
    for case in ET.parse(junit).getroot().iter("testcase"):
        module = case.get("classname", "").split(".")
        name = next((f"{'/'.join(module[:k + 1])}.py" for k in range(len(module))
                     if module[k].startswith("test_")), None)
        if name:
            out[name] = out.get(name, 0.0) + float(case.get("time", 0.0))
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--all", action="store_true", help="the tests marked slow too")
    p.add_argument("--record", action="store_true", help=f"rewrite {DURATIONS.name}")
    a = p.parse_args(argv)
    if a.workers < 1:
        p.error(f"--workers must be >= 1, got {a.workers}")
    root = TESTS.parent
    # test files named after "--" are the ones run (split over the workers); else every file
    named = [x for x in extra if x.endswith(".py") and (root / x).is_file()]
    extra = [x for x in extra if x not in named]
    if a.all:
        extra = ["-m", "slow or not slow", *extra]  # a later -m among the arguments wins
    files = sorted(named) or sorted(str(f.relative_to(root)) for f in TESTS.glob("test_*.py"))
    durations = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    groups = plan(files, durations, a.workers)
    with tempfile.TemporaryDirectory() as tmp:
        # one JAX compilation cache for the run, shared by the workers: tests compile many of the
        # same programs (14% less time on five of the files, measured on 2 cores)
        env = dict(os.environ)
        env.setdefault("JAX_COMPILATION_CACHE_DIR", str(pathlib.Path(tmp) / "jax_cache"))
        env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.3")
        procs, threads = [], []
        for i, group in enumerate(groups, 1):
            junit = pathlib.Path(tmp) / f"worker{i}.xml"
            cmd = [sys.executable, "-m", "pytest", "-q", f"--junitxml={junit}", *extra, *group]
            print(f"[{i}] {len(group)} files: {' '.join(pathlib.Path(f).stem for f in group)}",
                  flush=True)
            proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True, env=env)
            thread = threading.Thread(target=_stream, args=(i, proc))
            thread.start()
            procs.append((proc, junit))
            threads.append(thread)
        for t in threads:
            t.join()
        codes = [proc.wait() for proc, _ in procs]
        measured = {}
        for _, junit in procs:
            if junit.is_file():
                measured.update(file_durations(junit))
        if a.record and measured:
            DURATIONS.write_text(json.dumps(dict(sorted(measured.items())), indent=1) + "\n")
    print(f"workers' exit codes: {codes}", flush=True)
    return 0 if all(c == 0 for c in codes) else 1


if __name__ == "__main__":
    sys.exit(main())
