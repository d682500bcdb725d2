"""SIGTERM as an orderly exit, as Ctrl-C is, so that a killed command leaves no ViZDoom engine behind.

A ViZDoom engine is a process of its own that ignores SIGTERM and outlives its parent: a command that dies on the spot
(SIGTERM's default: no `finally`, no exit handlers) leaves its engines running, each with ~10 MB of shared memory in
/dev/shm. `exit_on_sigterm` turns SIGTERM into `Terminated`, a SystemExit with the shell's status 143 (128 + 15),
raised in the main thread like Ctrl-C's KeyboardInterrupt: `finally` blocks and exit handlers run and close the
engines (a DoomEnv closes its own at exit). Every command that can start one installs it in its main: play.py,
evaluate.py (the policies protocol), diagnose.py (the control check), the renderer and the builder.

`stop_pool` ends a multiprocessing pool whose workers own engines: SIGTERM (an orderly exit in each worker), then
SIGKILL, with the worker's own children, for a worker still there after a grace period (blocked in a hung engine).
"""
import multiprocessing.pool
import os
import signal
import threading
from typing import List

EXIT_STATUS = 128 + signal.SIGTERM  # what a shell reports for a process ended by SIGTERM


class Terminated(SystemExit):
    """The process received SIGTERM: unwind and exit with status 143."""


_exiting_pid = None  # the process whose Terminated is on its way (a forked child is another process)


def _raise_terminated(signum, frame):
    global _exiting_pid
    if _exiting_pid == os.getpid():
        return  # already unwinding: a second SIGTERM must not cut the closing short (SIGKILL still ends it at once)
    _exiting_pid = os.getpid()
    raise Terminated(EXIT_STATUS)


def exit_on_sigterm() -> bool:
    """Make SIGTERM raise `Terminated` in the main thread instead of killing the process on the spot. A handler set
    before (training's StopSignal, a server's own) or SIG_IGN is left alone, and outside the main thread (where
    handlers cannot be set) nothing changes. Returns whether SIGTERM now exits in order; safe to call again.

    A server that handles SIGTERM itself and then re-raises it once it has stopped (uvicorn) ends up here too: it
    puts this handler back before re-raising."""
    if threading.current_thread() is not threading.main_thread():
        return signal.getsignal(signal.SIGTERM) is _raise_terminated
    current = signal.getsignal(signal.SIGTERM)
    if current is _raise_terminated:
        return True
    if current is not signal.SIG_DFL:
        return False
    signal.signal(signal.SIGTERM, _raise_terminated)
    return True


def _stat_ppid(pid: int):
    """The parent pid of `pid` from Linux's /proc (None: no such process, or no /proc)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    fields = stat[stat.rfind(b")") + 2:].split()  # after "pid (comm) ": state, ppid, ...
    return int(fields[1]) if len(fields) > 1 else None


def _children_pids(pid: int) -> List[int]:
    """The pids of `pid`'s children (Linux /proc; none elsewhere)."""
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    return [int(e) for e in entries if e.isdigit() and _stat_ppid(int(e)) == pid]


def _kill_stragglers(workers) -> None:
    """SIGKILL the workers still there, and their children (their engines, which nobody else would close)."""
    have_proc = os.path.isdir("/proc/self")
    for worker in workers:
        if worker.pid is None:
            continue
        if have_proc:  # still our child (not yet reaped: its pid cannot have been reused)
            if _stat_ppid(worker.pid) != os.getpid():
                continue
        elif worker.exitcode is not None:
            continue
        for pid in [*_children_pids(worker.pid), worker.pid]:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass


def stop_pool(pool: multiprocessing.pool.Pool, grace_s: float = 10.0) -> None:
    """Terminate `pool` and wait for its workers: each gets SIGTERM, which (with `exit_on_sigterm` installed in it)
    unwinds it and closes its engine; one still running `grace_s` later is blocked where no signal handler runs (a
    hung engine) and is killed, its children (its engine) with it, so that the wait cannot last forever."""
    workers = list(getattr(pool, "_pool", ()))  # the pool's worker processes (multiprocessing keeps them there)
    timer = threading.Timer(grace_s, _kill_stragglers, (workers,))
    timer.daemon = True
    timer.start()
    try:
        pool.terminate()
        pool.join()
    finally:
        timer.cancel()
