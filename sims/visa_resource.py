"""The part every VISA-like twin resource shares (the DS345 twin's, the line twins'): what pyvisa's
MessageBasedResource offers a driver of its state and its receive buffer.

pyvisa only (no serial plumbing): importable wherever pyvisa is, Windows included.
"""

from __future__ import annotations

import pyvisa.constants
import pyvisa.errors


class VisaLikeResource:
    """What the twins' VISA-like resources share: the open/closed state, the receive buffer and its reads.

    A subclass implements write(), read() and `_more()` (put more reply bytes into `_rx`; False when the
    instrument has none: the read then times out at once, the clock being virtual).
    """

    def __init__(self, resource_name: str) -> None:
        self.resource_name = resource_name
        self.write_termination = "\r\n"  # pyvisa's defaults; drivers set their own
        self.read_termination = "\n"
        self.timeout: float | None = 2000.0
        self._rx = bytearray()
        self._closed = False

    def _check_open(self) -> None:
        if self._closed:
            raise pyvisa.errors.InvalidSession()

    @staticmethod
    def _timeout() -> pyvisa.errors.VisaIOError:
        return pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_timeout)

    def _more(self) -> bool:
        raise NotImplementedError

    def write(self, message: str) -> int:
        raise NotImplementedError

    def read(self) -> str:
        raise NotImplementedError

    def read_bytes(self, count: int) -> bytes:
        self._check_open()
        while len(self._rx) < count:
            if not self._more():
                raise self._timeout()
        out = bytes(self._rx[:count])
        del self._rx[:count]
        return out

    def query(self, message: str) -> str:
        self.write(message)
        return self.read()

    def clear(self) -> None:
        self._check_open()
        self._rx.clear()

    def close(self) -> None:
        self._closed = True
