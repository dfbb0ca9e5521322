"""Reading run files for people: the data API (run.py), the run list (summary.py), decimation for plots."""
