"""The study's local Dask cluster: the dashboard and the scheduler listen on 127.0.0.1 only unless asked, and the
scratch space (the workers' local_directory, dask's temporary-directory) lies under the study directory."""

from __future__ import annotations

import socket
import urllib.request
from pathlib import Path

import pytest
from distributed import Client

from qmg_lab.study.runner import SCRATCH_DIR, local_cluster


def _dashboard_sockets(cluster) -> list[tuple[str, int]]:
    server = cluster.scheduler.http_server  # tornado's HTTPServer of the scheduler's dashboard
    return [sock.getsockname()[:2] for sock in server._sockets.values()]


def _worker_scratch(dask_worker) -> tuple[str, str]:
    import dask

    return dask_worker.local_directory, str(dask.config.get("temporary-directory"))


def test_the_dashboard_listens_on_localhost_and_scratch_is_under_the_study(tmp_path: Path) -> None:
    with local_cluster(1, tmp_path) as cluster, Client(cluster) as client:
        addresses = _dashboard_sockets(cluster)
        assert addresses and all(host == "127.0.0.1" for host, _ in addresses), addresses
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        port = addresses[0][1]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=30) as page:  # it serves
            assert page.status == 200
        scratch = (tmp_path / SCRATCH_DIR).resolve()
        for local_directory, temporary in client.run(_worker_scratch).values():
            assert Path(local_directory).resolve().is_relative_to(scratch), local_directory
            assert Path(temporary).resolve() == scratch


def test_the_dashboard_address_can_open_it_on_purpose(tmp_path: Path) -> None:
    with local_cluster(1, tmp_path, "0.0.0.0:0") as cluster:
        hosts = {host for host, _ in _dashboard_sockets(cluster)}
        assert hosts == {"0.0.0.0"}


@pytest.mark.skipif(not hasattr(socket, "AF_INET"), reason="IPv4 needed")
def test_localhost_is_the_only_interface_of_the_default(tmp_path: Path) -> None:
    """On a host with a non-loopback IPv4 address, the dashboard's port is closed on it (the issue saw HTTP 200)."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.connect(("192.0.2.1", 9))  # TEST-NET-1: no packet is sent; it only picks the outgoing interface
        host_ip = probe.getsockname()[0]
    except OSError:
        pytest.skip("no IPv4 route: the host has no address other than loopback")
    finally:
        probe.close()
    if host_ip.startswith("127."):
        pytest.skip("the host's only address is loopback")
    with local_cluster(1, tmp_path) as cluster:
        port = _dashboard_sockets(cluster)[0][1]
        with pytest.raises(OSError), socket.create_connection((host_ip, port), timeout=5):
            pass
