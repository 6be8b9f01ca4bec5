"""The command's name, ``PROG``, in its own module: the parser (:mod:`mapets_rl.app.cli`) and
the recipe help (:mod:`mapets_rl.app.help`) both print it, and neither imports the other for
it."""

PROG = "mapets-rl"
"""The name of the command line program, at the head of its usage, errors and warnings."""
