"""`qmg-lab watch RUN.h5`: a live page of a run file in the browser (docs/watch.md)."""
