"""Transaction cost of the 1291BR and EC1x drivers against their twins, per transport; prints JSON.

For each transport (in-process, pty, loopback socket) it times `table.read()` (3 transactions: PVE, PPO, STA)
and `chamber.read()` (C1?, SET?, STATUS?) and reports the mean wall time per read and per transaction, and the
process CPU time per read (all threads: the pty and socket servers' too), which a loaded machine disturbs less.

    python benchmarks/bench_serial_twins.py [--reads N]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import serial

from drivers.aerosmith import Aerosmith1291BR
from drivers.chamber import SunEC1xChamber
from qmg_lab.config.schema import Config
from qmg_lab.station import make_world
from sims.chamber_twin import ChamberTwin
from sims.serial_twin import InProcessSerial, LineTwin, serve_pty, serve_socket
from sims.table_twin import RateTableTwin


def open_port(twin: LineTwin, transport: str) -> tuple[Any, Callable[[], None]]:
    if transport == "inprocess":
        return InProcessSerial(twin), lambda: None
    if transport == "pty":
        path, stop = serve_pty(twin)
        return serial.Serial(path, 9600, timeout=2.0), stop
    url, stop = serve_socket(twin)
    return serial.serial_for_url(url, timeout=2.0), stop


def time_reads(read: Callable[[], object], n: int) -> tuple[float, float]:
    """(wall s, process CPU s) per call of `read`, mean of n calls after one warm-up call."""
    read()
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n):
        read()
    return (time.perf_counter() - t0) / n, (time.process_time() - c0) / n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reads", type=int, default=2000)
    n = ap.parse_args().reads
    out: dict[str, Any] = {"reads": n, "transactions_per_read": 3}
    for transport in ("inprocess", "pty", "socket"):
        world = make_world(Config(), clock="virtual")  # the default configuration's stand
        tport, tstop = open_port(RateTableTwin(world, servo_on=True), transport)
        cport, cstop = open_port(
            ChamberTwin(
                world,
                status_layout="flags16",
                self_test=0,
                acknowledges_settings=True,
                powered_at_start=True,
                set_query_while_off="held",
                silent_commands=0,
            ),
            transport,
        )
        table = Aerosmith1291BR(tport, max_rate_dps=100.0, max_accel_dps2=500.0)
        chamber = SunEC1xChamber(cport, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0)
        table.set_rate(5.0, 300.0)
        t_table, cpu_table = time_reads(table.read, n)
        t_chamber, cpu_chamber = time_reads(chamber.read, n)
        out[transport] = {
            "table_read_us": round(t_table * 1e6, 1),
            "table_transaction_us": round(t_table / 3 * 1e6, 1),
            "chamber_read_us": round(t_chamber * 1e6, 1),
            "chamber_transaction_us": round(t_chamber / 3 * 1e6, 1),
            "table_read_cpu_us": round(cpu_table * 1e6, 1),
            "chamber_read_cpu_us": round(cpu_chamber * 1e6, 1),
        }
        table.close()
        chamber.close()
        tstop()
        cstop()
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
