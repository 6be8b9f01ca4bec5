"""Start-up cost: wall time and peak RSS of fresh processes that only import or print help.

Each case runs in a new interpreter (``--repeats`` times, median and spread reported) so that
nothing is cached in-process; the OS file cache is warm after the first run. The breakdown
lists which heavy third-party modules each case ends up importing.

``mapets-rl train mapets --help`` is timed cold (once, with an empty help cache: the recipe is
imported and every scenario built) and warm (the text read back from the cache, the usual
case; the target is under 1 s), in a private ``XDG_CACHE_HOME``.

    PYTHONPATH=. python benchmarks/startup.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "torch._dynamo", "tensordict", "torchrl", "ray", "sympy", "highway_env")
HEAVY += ("matplotlib", "pandas", "pygame", "scipy")
REPORT = (
    "import json, resource, sys\n"
    "print(json.dumps([resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,"
    " [m for m in {heavy!r} if m in sys.modules]]))\n"
)
CASES = {
    "mapets-rl --help": "from mapets_rl.app.cli import main\n"
    "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n",
    "import mapets_rl.app.cli": "import mapets_rl.app.cli\n",
    "import mapets_rl.experiment.runner": "import mapets_rl.experiment.runner\n",
    "import mapets_rl.envs": "import mapets_rl.envs\n",
    "runner + envs (a run's imports)": "import mapets_rl.experiment.runner, mapets_rl.envs\n",
}
RECIPE_HELP = (
    "from mapets_rl.app.cli import main\nmain(['train', 'mapets', 'preset=cpu', '--help'])\n"
)
"""``mapets-rl train mapets preset=cpu --help``, timed cold and warm."""


def run_case(code: str, cache: str | None = None) -> tuple[float, float, list[str]]:
    """Wall seconds, peak RSS [MiB] and heavy modules of one fresh interpreter running ``code``
    (with ``XDG_CACHE_HOME=cache`` when given)."""
    env = {**os.environ, **({"XDG_CACHE_HOME": cache} if cache else {})}
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code + REPORT.format(heavy=HEAVY)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    wall = time.perf_counter() - start
    peak_kib, heavy = json.loads(proc.stdout.splitlines()[-1])
    return wall, peak_kib / 1024, heavy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="fresh processes per case")
    args = parser.parse_args()
    # torch is imported in a child only: Linux keeps a process's peak RSS across exec, so this
    # process must stay small for the children's peaks to be their own
    capability = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.backends.cpu.get_cpu_capability())"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    print(f"CPU capability {capability}")
    print(f"{'case':34s} {'wall s (median, min..max)':>26s} {'peak RSS MiB':>13s}  heavy modules")
    with tempfile.TemporaryDirectory() as cache:
        cases = [(label, code, None, args.repeats) for label, code in CASES.items()]
        cases += [
            ("train mapets --help (cold cache)", RECIPE_HELP, cache, 1),
            ("train mapets --help (warm cache)", RECIPE_HELP, cache, args.repeats),
        ]
        for label, code, cache_dir, repeats in cases:
            walls, rss, heavy = [], 0.0, []
            for _ in range(repeats):
                wall, rss, heavy = run_case(code, cache_dir)
                walls.append(wall)
            spread = f"{statistics.median(walls):.2f} ({min(walls):.2f}..{max(walls):.2f})"
            print(f"{label:34s} {spread:>26s} {rss:13.0f}  {', '.join(heavy) or '-'}")


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
