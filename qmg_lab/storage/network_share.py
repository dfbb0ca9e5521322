"""Is a folder on a network file system? A run file is written with HDF5 SWMR (single writer, multiple readers),
which needs POSIX write semantics (ordered writes, seen at once by readers, a working flush): the HDF5 SWMR
documentation rules out network file systems (NFS, SMB/CIFS and the like), where a reader can see a stale or torn
file. The command line warns when the run file's folder is on one (`network_share`); it does not refuse, since
a share may be all a lab PC has.

How the folder's file system is found:
* Linux, macOS: the mount table (psutil.disk_partitions(all=True), i.e. /proc/mounts on Linux); the folder's
  mount is the longest mount point that contains it; its fstype is network if in NETWORK_FS_TYPES (or a
  "fuse.<name>" of one of them).
* Windows: a UNC path (\\\\server\\share\\...) is a share; a drive letter is a share when psutil reports it
  remote (GetDriveType DRIVE_REMOTE, shown by psutil as "remote" in the partition's opts).

`network_share(folder, mounts=...)` takes the mount table as plain data (`Mount`), so it is tested on any table.
"""

from __future__ import annotations

import ntpath
import os
import posixpath
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import psutil

#: file systems whose writes reach a server: no POSIX write ordering for SWMR readers
NETWORK_FS_TYPES = frozenset(
    {
        "nfs", "nfs4", "cifs", "smbfs", "smb3", "smb2", "sshfs", "9p", "afs", "ncpfs", "coda", "ceph",
        "glusterfs", "lustre", "gpfs", "beegfs", "davfs", "davfs2", "webdav", "s3fs", "rclone", "virtiofs",
        "vboxsf", "prl_fs", "vmhgfs", "fuse.vmhgfs-fuse",
    }
)  # fmt: skip


@dataclass(frozen=True)
class Mount:
    """One row of the mount table: where it is mounted, its file-system type and its options (comma-separated)."""

    mountpoint: str
    fstype: str
    opts: str = ""


def mount_table() -> list[Mount]:
    """This machine's mount table (psutil.disk_partitions(all=True): every mount, network ones included)."""
    return [Mount(p.mountpoint, p.fstype, p.opts) for p in psutil.disk_partitions(all=True)]


def is_network_fstype(fstype: str) -> bool:
    """nfs, cifs, ... or a FUSE mount of one of them ("fuse.sshfs")."""
    t = fstype.lower()
    return t in NETWORK_FS_TYPES or (t.startswith("fuse.") and t[5:] in NETWORK_FS_TYPES)


def _contains(mountpoint: str, path: str, windows: bool) -> bool:
    if windows:
        m, p = ntpath.normcase(mountpoint).rstrip("\\/"), ntpath.normcase(path)
        return p == m or p.startswith(m + "\\")
    m = mountpoint.rstrip("/") or "/"
    return m in ("/", path) or path.startswith(m + "/")


def network_share(
    folder: str | Path, mounts: Iterable[Mount] | None = None, platform: str = sys.platform
) -> str | None:
    """A description of the network file system `folder` lies on ("nfs4 at /mnt/lab", "UNC path \\\\srv\\data"),
    or None for a local one. `mounts`: the mount table (default this machine's); `platform`: sys.platform's form."""
    windows = platform == "win32"
    path = os.fspath(folder)
    if windows:
        path = ntpath.abspath(path) if os.name == "nt" else ntpath.normpath(path)
        if path.startswith(("\\\\", "//")) and not path.startswith(("\\\\?\\", "\\\\.\\")):
            return f"UNC path {path}"
    else:
        path = posixpath.normpath(os.path.abspath(path) if os.name != "nt" else path)
    table: Sequence[Mount] = list(mount_table() if mounts is None else mounts)
    inside = [m for m in table if _contains(m.mountpoint, path, windows)]
    if not inside:
        return None
    mount = max(inside, key=lambda m: len(m.mountpoint.rstrip("\\/")))
    remote = "remote" in [o.strip() for o in mount.opts.split(",")]
    if is_network_fstype(mount.fstype) or remote:
        return f"{mount.fstype or 'remote'} at {mount.mountpoint}"
    return None


def swmr_warning(run_file: str | Path, mounts: Iterable[Mount] | None = None) -> str | None:
    """The warning for a run file whose folder is on a network file system, or None."""
    folder = Path(run_file).parent
    where = network_share(folder, mounts)
    if where is None:
        return None
    return (
        f"{folder} is on a network file system ({where}): the run file is written with HDF5 SWMR, which needs "
        "POSIX write semantics that network shares do not give; a reader (watch, runs, analyze) may see a stale or "
        "damaged file while the run writes. Write the run to a local disk and copy it afterwards."
    )
