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
