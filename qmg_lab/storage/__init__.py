"""The run file (HDF5, layout qmg-lab/1): writing, reading, resuming, records."""
