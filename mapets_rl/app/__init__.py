"""The application, the top floor: the ``mapets-rl`` command (:mod:`mapets_rl.app.cli`), sweeps
(:mod:`mapets_rl.app.sweep`) and ``compare`` (:mod:`mapets_rl.app.comparison`). It stands above
the recipes: it finds them by name at run time, and nothing below it imports it."""
