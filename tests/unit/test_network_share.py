"""A run file's folder on a network file system is found from the mount table (qmg_lab/storage/network_share.py),
given here as data in the form psutil.disk_partitions reports it (/proc/mounts rows on Linux; drive letters with
"remote" in opts, as GetDriveType DRIVE_REMOTE, on Windows), plus UNC paths."""

from __future__ import annotations

from pathlib import Path

import pytest

from qmg_lab.storage.network_share import Mount, mount_table, network_share, swmr_warning

LINUX = [
    Mount("/", "ext4", "rw,relatime"),
    Mount("/home", "xfs", "rw"),
    Mount("/mnt/lab", "nfs4", "rw,vers=4.2,addr=10.0.0.5"),
    Mount("/mnt/lab/scratch", "tmpfs", "rw"),  # a local mount inside the share: the longest mount point wins
    Mount("/media/nas", "cifs", "rw,vers=3.0"),
    Mount("/home/op/remote", "fuse.sshfs", "rw,nosuid"),
    Mount("/mnt/wsl-share", "9p", "rw"),
]
WINDOWS = [Mount("C:\\", "NTFS", "rw,fixed"), Mount("Z:\\", "NTFS", "rw,remote"), Mount("D:\\", "", "cdrom")]


@pytest.mark.parametrize(
    ("folder", "expected"),
    [
        ("/mnt/lab/runs", "nfs4 at /mnt/lab"),
        ("/mnt/lab", "nfs4 at /mnt/lab"),
        ("/media/nas/2026", "cifs at /media/nas"),
        ("/home/op/remote/x", "fuse.sshfs at /home/op/remote"),
        ("/mnt/wsl-share/runs", "9p at /mnt/wsl-share"),
        ("/mnt/lab/scratch/runs", None),
        ("/mnt/laboratory/runs", None),  # a sibling whose name starts like the share's
        ("/home/op/runs", None),
        ("/tmp", None),
    ],
)
def test_linux_mount_table(folder: str, expected: str | None) -> None:
    assert network_share(folder, LINUX, platform="linux") == expected


@pytest.mark.parametrize(
    ("folder", "expected"),
    [
        ("Z:\\runs\\2026", "NTFS at Z:\\"),
        ("z:\\runs", "NTFS at Z:\\"),  # drive letters are case-insensitive
        ("C:\\Users\\op\\runs", None),
        ("\\\\nas01\\lab\\runs", "UNC path \\\\nas01\\lab\\runs"),
        ("//nas01/lab/runs", "UNC path \\\\nas01\\lab\\runs"),
    ],
)
def test_windows_drives_and_unc_paths(folder: str, expected: str | None) -> None:
    assert network_share(folder, WINDOWS, platform="win32") == expected


def test_the_warning_names_the_folder_and_swmr(tmp_path: Path) -> None:
    local = [Mount("/", "ext4", "rw")]
    assert swmr_warning("/mnt/lab/runs/run.h5", LINUX) is not None
    text = swmr_warning("/mnt/lab/runs/run.h5", LINUX) or ""
    assert "/mnt/lab/runs" in text and "nfs4" in text and "SWMR" in text
    assert swmr_warning("/data/run.h5", local) is None


def test_this_machines_table_is_read_and_holds_the_test_folder(tmp_path: Path) -> None:
    table = mount_table()
    assert table and all(m.mountpoint for m in table)
    assert any(str(tmp_path).lower().startswith(m.mountpoint.rstrip("\\/").lower()) for m in table)
    assert network_share(tmp_path) == network_share(tmp_path, table)  # the default is this very table
