"""``python -m cpas_bayes``: the command line."""

from cpas_bayes.app.entry import run_program

run_program()
