"""Leases: who holds a run of a shared results store, and whether that holder is still alive.

A sweep claims each run it computes with its `Lease` (`eval.store.Store.claim`): the claiming process's id and
host, a random token of the claiming sweep, and a heartbeat time the holder refreshes while it works. A lease
is live (`lease_live`) while its heartbeat is younger than `stale_s` seconds and, when it was taken on this
host, its process still exists (`pid_alive`; a zombie counts as gone); a run whose lease is not live was
interrupted and may be taken over.
"""
from __future__ import annotations

import os
import socket
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

#: Default age in seconds after which a lease whose heartbeat was not refreshed is taken over.
LEASE_S = 60.0


@dataclass(frozen=True)
class Lease:
    """Who holds a run: one per sweep (`Lease.new()`), written into the rows it claims."""

    pid: int      # process id of the claiming process
    host: str     # its host name
    token: str    # random id, so that two sweeps of one process (one after the other) are told apart

    @classmethod
    def new(cls) -> "Lease":
        return cls(pid=os.getpid(), host=socket.gethostname(), token=uuid.uuid4().hex)


def pid_alive(pid: int | None) -> bool:
    """Whether process `pid` exists on this host and is not a zombie (Linux /proc; elsewhere kill(pid, 0))."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # exists, owned by another user
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True  # no /proc (or it vanished just now): trust kill()
    state = stat.rsplit(")", 1)[-1].split()[:1]
    return state not in (["Z"], ["X"])  # a killed process its parent has not reaped yet is gone too


def lease_live(row, me: Lease, stale_s: float, now: float | None = None) -> bool:
    """Whether the lease written in `row` (lease_* and heartbeat_at columns) still holds, seen from `me`.

    Live: a heartbeat younger than `stale_s` seconds and, on this host, a process that still exists. A lease
    of this very process under another token belongs to an earlier sweep of this process that stopped
    without finishing (one process runs one sweep at a time), so it is not live either.
    """
    beat, token = row["heartbeat_at"], row["lease_token"]
    if token is None or beat is None:
        return False  # never leased (an older store), or released
    if token == me.token:
        return True
    if (time.time() if now is None else now) - float(beat) > stale_s:
        return False
    if row["lease_host"] == me.host:
        return row["lease_pid"] != me.pid and pid_alive(row["lease_pid"])
    return True  # another host: only the heartbeat tells


_PROCESS_LEASE: Lease | None = None


def _process_lease() -> Lease:
    global _PROCESS_LEASE
    if _PROCESS_LEASE is None or _PROCESS_LEASE.pid != os.getpid():  # a forked child gets its own
        _PROCESS_LEASE = Lease.new()
    return _PROCESS_LEASE
