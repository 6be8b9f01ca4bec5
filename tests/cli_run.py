"""Run the ``mapets-rl`` CLI in-process, as the tests of the CLI paths do."""

from __future__ import annotations

from mapets_rl.app.cli import main


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``mapets-rl argv`` (``SystemExit`` caught)."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err
