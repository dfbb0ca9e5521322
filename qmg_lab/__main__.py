"""`python -m qmg_lab` runs the command line."""

from qmg_lab.cli.main import main

main()
