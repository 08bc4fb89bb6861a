"""The monitor's health and its events in words: what ``monitor status`` and ``monitor serve`` say.

:func:`health` is the one rule for "is an offset being applied now" (from the heartbeat), :func:`daemon_alive`
asks this host whether a heartbeat's daemon still runs, and :func:`event_summary` says an event in one line.
"""

from __future__ import annotations

import os


def daemon_alive(beat: dict) -> bool | None:
    """Whether the daemon of a heartbeat runs: asked of the process on this host, None for another host."""
    import socket

    pid = beat.get("pid")
    if beat.get("host") != socket.gethostname() or not isinstance(pid, int):
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def health(st: dict, stale_after_s: float) -> tuple[str, str]:
    """Whether an offset is being applied now: ``("healthy" | "unhealthy", why)`` from a status dict.

    A daemon on this host that no longer runs (killed with -9: its last heartbeat says running) is unhealthy at
    once; on another host, once no offset was applied for ``stale_after_s``. The freshness of the offsets comes from
    the newer of the database's heartbeat and this host's copy (a locked database delays the one, not the other).
    """
    if st["running"] is None:
        return "unhealthy", "no daemon has run on this machine and pose"
    if not st["running"]:
        return "unhealthy", "the daemon stopped: no offsets are applied"
    if st.get("daemon_alive") is False:
        return "unhealthy", f"the daemon (pid {st.get('daemon_pid')}) is not running: killed or crashed, no offsets " \
                            "are applied"
    age = st["seconds_since_offset"]
    if age is None:
        return "unhealthy", "no offset applied yet"
    if age > stale_after_s:
        return "unhealthy", f"no offset applied for {age:.0f} s (limit {stale_after_s:g} s)"
    said = f"last offset applied {age:.1f} s ago"
    if (st["store_backlog"] or 0) > 1000:  # the offsets do not wait for the database: healthy, and said
        return "healthy", f"{said}; {st['store_backlog']} database writes queued (the database does not take writes)"
    return "healthy", said


def event_summary(kind: str, p: dict) -> str:
    """One line for an event of ``kind`` with payload ``p``."""
    if kind == "decision":
        return f"{p.get('action')}: {p.get('reason')}"
    if kind == "activation":
        return f"active {p.get('ids')} ({p.get('reason')})"
    if kind == "generation":
        return f"{p.get('status')} {p.get('ids') or p.get('error') or ''}".strip()
    if kind == "model_drift":
        return f"structure model and sensors differ by {p.get('max_abs_K', float('nan')):.2f} K at {p.get('sensor')}"
    if kind == "sensor":
        return p.get("message", "")
    return str(p.get("message") or p)[:160]


__all__ = ["daemon_alive", "event_summary", "health"]
