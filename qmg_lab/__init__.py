"""qmg-lab: closed-loop scale-factor self-calibration campaigns for MEMS Coriolis vibratory gyroscopes."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("qmg-lab")
except PackageNotFoundError:  # running from a checkout without installing
    __version__ = "0.0.0+local"

import logging as _logging

# module loggers throughout (logging.getLogger(__name__)); silent unless the application configures logging
# (`qmg-lab --log-level INFO ...`)
_logging.getLogger(__name__).addHandler(_logging.NullHandler())

__all__ = ["Run", "__version__", "open_run"]


def __getattr__(name: str) -> object:
    """`qmg_lab.open_run` and `qmg_lab.Run` (qmg_lab/data/run.py), imported on first use so that `import qmg_lab`
    (every CLI command's start) does not load h5py, pandas or xarray."""
    if name in ("open_run", "Run"):
        from qmg_lab.data import run as run_file

        return getattr(run_file, name)
    raise AttributeError(f"module 'qmg_lab' has no attribute {name!r}")
