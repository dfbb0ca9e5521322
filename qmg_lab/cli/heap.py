"""Python's cyclic garbage collector over the life of one command-line process.

A campaign process builds a large heap of long-lived objects before it does any work: the imports of numba,
zhinst-toolkit, scipy, h5py and pydantic, numba's typing and target contexts when the first cached kernel loads,
the station's drivers and twins. The collector's automatic passes over that heap find almost nothing to free
(a measured `qmg-lab run`: three full passes during start-up, 10-20 objects each, about 0.25 s in all), and the
interpreter's own collection at exit walks it all once more (about 0.4 s, most of it numba's objects). So:

* `quiet_start`: no automatic collection while the command starts (imports, configuration, connecting);
* `settle`: once the command is up, everything alive is moved to the collector's permanent generation
  (`gc.freeze`: never scanned again) and automatic collection is switched back on for the command's own work,
  which is when garbage is made (a multi-hour campaign must not grow);
* `quiet_exit`: when the command is done, the same for whatever is left, so that the interpreter's exit does not
  walk the heap. Nothing is skipped that matters: the run file is closed by then, the `atexit` handlers (h5py's
  and HDF5's file closing, logging's flush, Dask's shutdown) and the joining of threads still run, and the
  operating system frees the memory.

Only the console entry point (`qmg_lab.cli.main.main`) switches collection off; the commands call `settle`, which
does nothing while collection is on, so code that imports qmg-lab as a library, and the tests, keep Python's
default collector.
"""

from __future__ import annotations

import gc


def quiet_start() -> None:
    """No automatic cyclic collection until `settle` (start-up allocates what lives until exit)."""
    gc.disable()


def settle() -> None:
    """Start-up is over: freeze what is alive (gc.freeze) and collect automatically again. Idempotent."""
    if not gc.isenabled():
        gc.freeze()
        gc.enable()


def quiet_exit() -> None:
    """The command is done: freeze what is left and collect no more, so the interpreter's exit is not a full
    collection over the whole heap."""
    gc.disable()
    gc.freeze()
