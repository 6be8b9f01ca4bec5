"""The application, the top floor: the ``mapets-rl`` command (:mod:`mapets_rl.app.cli`, its
``train RECIPE --help`` in :mod:`mapets_rl.app.help`), sweeps (:mod:`mapets_rl.app.sweep`) and
``compare`` (:mod:`mapets_rl.app.comparison`). It stands above the recipes: it finds them by
name at run time (:mod:`mapets_rl.app.plugins`), and nothing below it imports it."""
