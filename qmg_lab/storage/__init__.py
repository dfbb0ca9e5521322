"""The run file (HDF5, layout qmg-lab/2; /1 still read): writing, reading, resuming, records."""
