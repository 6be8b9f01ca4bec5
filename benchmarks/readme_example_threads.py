"""The README's ten-line example as written, and with ``num_threads=1``: how long each takes.

Issue 52: on a busy 2-core machine the example took 13 min 53 s as written (the Python API kept
torch's two spinning OpenMP threads) and 1 min 25 s with ``num_threads=1``. The Python API now
chooses the thread count by the machine's load as ``mapets-rl`` does (``mapets_rl/threads.py``),
so the two should take about as long on a busy machine.

The example is read from ``README.md`` (the Python block that builds ``MAPETSConfig``) and run as
written in a fresh interpreter from the repository root, then again with ``num_threads=1``
added to its ``MAPETSConfig(...)``; ``MAPETS_RL_THREADS`` and ``OMP_NUM_THREADS`` are removed
from the children's environment (a user's shell sets neither). Each child prints the thread
line of :mod:`mapets_rl.threads` on stderr; it is shown with the wall time. ``--episodes N``
runs ``N`` episodes instead of the example's budget (a quick check, not the measurement).

Run (a few minutes on a busy 2-core VM)::

    nice .venv/bin/python benchmarks/readme_example_threads.py
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from mapets_rl.machine import machine_line
from mapets_rl.threads import THREADS_ENV, available_cpus, load_average

ROOT = Path(__file__).resolve().parents[1]
BUDGET = "episodes=5"
"""The example's budget, as the README writes it."""


def readme_example(readme: Path = ROOT / "README.md") -> str:
    """The README's ten-line example: its one Python block that builds ``MAPETSConfig``."""
    blocks = re.findall(r"```python\n(.*?)```", readme.read_text(), re.S)
    (example,) = [b for b in blocks if "config = MAPETSConfig(" in b]
    return example


def with_one_thread(example: str) -> str:
    """``example`` with ``num_threads=1`` as the first argument of its ``MAPETSConfig(...)``."""
    if example.count("MAPETSConfig(\n") != 1:
        raise ValueError("the README's example no longer has one 'MAPETSConfig(' line")
    return example.replace("MAPETSConfig(\n", "MAPETSConfig(\n    num_threads=1,\n")


def with_episodes(example: str, episodes: int) -> str:
    """``example`` with ``episodes`` in place of its budget."""
    if example.count(BUDGET) != 1:
        raise ValueError(f"the README's example no longer says {BUDGET!r} once")
    return example.replace(BUDGET, f"episodes={episodes}")


def run(code: str) -> tuple[float, str, str]:
    """Run ``code`` in a fresh interpreter from the repository root, as a user's shell would
    (no thread variables); returns the wall time [s], its thread line and its last stdout
    line. RuntimeError with its stderr when it fails."""
    env = {k: v for k, v in os.environ.items() if k not in (THREADS_ENV, "OMP_NUM_THREADS")}
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True
    )
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"the example failed:\n{proc.stderr}")
    threads = [line for line in proc.stderr.splitlines() if line.startswith("torch threads:")]
    last = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    return seconds, threads[0] if threads else "(no thread line)", last


def _minutes(seconds: float) -> str:
    return f"{int(seconds // 60)} min {seconds % 60:04.1f} s"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--episodes", type=int, default=0, help="episodes instead of the example's 5 (0: as is)"
    )
    args = parser.parse_args()
    if args.episodes < 0:
        parser.error(f"--episodes must be >= 0, got {args.episodes}")
    example = readme_example()
    if args.episodes:
        example = with_episodes(example, args.episodes)
    print(f"machine: {machine_line()}", flush=True)
    load = load_average()
    shown = "unknown" if load is None else f"{load:.2f}"
    print(f"CPUs available: {available_cpus()}, load average at start: {shown}", flush=True)
    times = {}
    for label, code in (("as written", example), ("num_threads=1", with_one_thread(example))):
        seconds, threads, last = run(code)
        times[label] = seconds
        print(f"{label}: {_minutes(seconds)} ({seconds:.1f} s); {threads}", flush=True)
        print(f"  history[-1]: {last}", flush=True)
    ratio = times["as written"] / times["num_threads=1"]
    print(f"ratio as written / num_threads=1: {ratio:.2f}", flush=True)


if __name__ == "__main__":
    main()
