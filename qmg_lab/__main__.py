"""`python -m qmg_lab` runs the command line."""

from qmg_lab.cli import main

main()
