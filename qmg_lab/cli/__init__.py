"""The qmg-lab command line."""
