"""Real-time scheduling of the control loop's thread (Linux ``SCHED_FIFO``); the mapper stays normal.

The daemon's event loop (MAVLink, the 20 Hz control step, the frame hand-over) shares the core with
the mapper thread, which is busy ~30 % of the time at 30 frames/s. Under normal scheduling a control
tick that falls while the mapper runs waits until the kernel's scheduler gives the loop's thread
the core back: the ticks later than 3 ms fell almost all during a mapper step (docs/performance.md,
"Control loop"). With the loop's thread at a ``SCHED_FIFO`` priority it preempts the mapper as soon as
its timer fires; the mapper thread stays at normal scheduling, so a busy mapper can never hold the
loop up, and the loop (which sleeps between ticks) takes only the little time it needs.

Python's lock (the GIL) still has to be handed over, after at most ``sys.getswitchinterval()`` (the
daemon sets 1 ms): the mapper thread gets the core back while the loop's thread waits for the lock,
so the wait stays that short.

Privilege: root, ``CAP_SYS_NICE``, or an ``RLIMIT_RTPRIO`` at least the priority (systemd
``LimitRTPRIO=``, with ``RestrictRealtime=no``). Without it the loop runs at normal priority and the
reason is logged and reported in the status.

The policy is set with ``SCHED_RESET_ON_FORK``: threads and processes the loop's thread starts
begin at normal scheduling (the snapshot thread: bulk work), and nothing inherits real-time
scheduling by accident. The asyncio executor's threads (camera reads: short, and on the frame's way
to the setpoint) are raised to one priority below the loop (:func:`below`): the loop preempts them,
they preempt the mapper.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Scheduling:
    """A thread's scheduling policy and priority, as :func:`current` reads them."""

    policy: int
    priority: int


def supported() -> bool:
    """Whether this platform can set a thread's scheduling policy (Linux)."""
    return all(hasattr(os, name) for name in ("sched_setscheduler", "sched_getscheduler", "SCHED_FIFO", "SCHED_OTHER"))


def current() -> Scheduling | None:
    """The calling thread's policy (without the reset-on-fork flag) and priority; None where unsupported."""
    if not supported():
        return None
    policy = os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
    return Scheduling(policy, os.sched_getparam(0).sched_priority)


def enter_fifo(priority: int) -> tuple[Scheduling | None, str]:
    """Put the calling thread (only it: on Linux ``pid 0`` is the calling thread) under
    ``SCHED_FIFO`` at ``priority`` (1-99), with ``SCHED_RESET_ON_FORK``.

    Returns the scheduling it had (for :func:`restore`) and ``""``, or ``(None, reason)`` when the
    system refused or cannot do it; the thread's scheduling is then unchanged.
    """
    if not 1 <= int(priority) <= 99:
        raise ValueError(f"SCHED_FIFO priority must be 1-99, got {priority}")
    if not supported():
        return None, "not supported on this platform (Linux only)"
    before = current()
    policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
    try:
        os.sched_setscheduler(0, policy, os.sched_param(int(priority)))
    except PermissionError:
        return None, (f"SCHED_FIFO priority {priority} refused (needs root, CAP_SYS_NICE or "
                      f"LimitRTPRIO={priority} with RestrictRealtime=no in the service unit)")
    except OSError as exc:
        return None, f"SCHED_FIFO priority {priority} refused: {exc}"
    return before, ""


def restore(before: Scheduling | None) -> None:
    """Give the calling thread back the scheduling :func:`enter_fifo` returned (no-op for None)."""
    if before is None or not supported():
        return
    try:
        os.sched_setscheduler(0, before.policy, os.sched_param(before.priority))
    except OSError:
        pass  # lowering one's own priority is always allowed; nothing else to do if it is not


def below(priority: int) -> None:
    """Thread initializer: the calling thread under ``SCHED_FIFO`` one priority below ``priority``
    (1 at least), or normal scheduling where that is refused. For the I/O threads a ``SCHED_FIFO``
    loop starts: the loop preempts them, they preempt the normal threads (the mapper)."""
    if not supported():
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                              os.sched_param(max(1, int(priority) - 1)))
    except OSError:
        normal_scheduling()


def normal_scheduling() -> None:
    """Put the calling thread under normal scheduling (``SCHED_OTHER``): :func:`below`'s fallback,
    and for a thread that was given a real-time policy some other way. Lowering needs no privilege."""
    if not supported():
        return
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass


def yield_to_others(nice: int) -> tuple[int | None, str]:
    """Raise the calling thread's nice value to ``nice`` (0-19; Linux gives each thread its own; a
    thread already nicer keeps its own): on a core it shares with normal threads of nice 0, the
    kernel then gives them the core first (at nice 10 a thread gets about a tenth of a core they
    both want). For bulk work beside the mapper: the dense flow's thread. Returns the thread's nice
    value after (None where unknown) and why it was not set ("" when it was). Raising one's own
    nice value needs no privilege."""
    if not hasattr(os, "setpriority"):
        return None, "thread priorities are not supported on this platform"
    import threading

    tid = threading.get_native_id()
    try:
        if os.getpriority(os.PRIO_PROCESS, tid) < int(nice):
            os.setpriority(os.PRIO_PROCESS, tid, int(nice))
        return os.getpriority(os.PRIO_PROCESS, tid), ""
    except OSError as exc:
        return None, f"setpriority refused: {exc.strerror or exc}"
