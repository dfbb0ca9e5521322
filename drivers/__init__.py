"""Drivers of the real instruments. Module loggers (logging.getLogger(__name__)) are silent unless the
application configures logging."""

import logging as _logging

_logging.getLogger(__name__).addHandler(_logging.NullHandler())
