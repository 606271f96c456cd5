"""An exclusive lock on a run directory, held for the life of the training process that owns it."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

__all__ = ["RunDirectoryBusy", "lock_run_directory"]

LOCK_FILE = ".lock"


class RunDirectoryBusy(ValueError):
    """Another live process trains in this directory."""


def lock_run_directory(directory: str | Path):
    """Take the directory's lock or raise ``RunDirectoryBusy`` naming the process that holds it.

    The lock is an ``flock`` on ``<directory>/.lock``: the OS drops it when its process ends, however
    it ends, so a killed trainer never leaves a stale lock. Keep the returned file open.
    """
    path = Path(directory) / LOCK_FILE
    handle = open(path, "a+")  # noqa: SIM115 (held open on purpose: closing it releases the lock)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        owner = handle.read().strip() or "another process"
        handle.close()
        raise RunDirectoryBusy(f"run directory {directory} is in use by another training ({owner})") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"pid {os.getpid()}")
    handle.flush()
    return handle
