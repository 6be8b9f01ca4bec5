"""benchmarks/readme_example_threads.py: it runs the README's ten-line example itself, as
written and with ``num_threads=1`` (only that argument added), and refuses a README that no
longer has the lines it changes."""

from __future__ import annotations

import ast

import pytest


def test_the_two_variants_are_the_readme_example_and_one_argument_more(
    load_script, tmp_path
) -> None:
    bench = load_script("benchmarks/readme_example_threads.py")
    example = bench.readme_example()
    assert "MAPETS(config).train()" in example and "num_threads" not in example
    one = bench.with_one_thread(example)
    call = next(
        node
        for node in ast.walk(ast.parse(one))
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "MAPETSConfig"
    )
    assert [(k.arg, ast.literal_eval(k.value)) for k in call.keywords][0] == ("num_threads", 1)
    assert one.replace("    num_threads=1,\n", "") == example
    assert "episodes=2," in bench.with_episodes(example, 2)
    readme = tmp_path / "README.md"
    readme.write_text("```python\nconfig = MAPETSConfig(preset='cpu')\n```\n")
    with pytest.raises(ValueError, match="no longer has one 'MAPETSConfig"):
        bench.with_one_thread(bench.readme_example(readme))
    with pytest.raises(ValueError, match="no longer says 'episodes=5'"):
        bench.with_episodes(bench.readme_example(readme), 1)
