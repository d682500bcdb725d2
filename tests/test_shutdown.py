"""Nothing left behind: a command that started ViZDoom engines closes them when it is stopped with SIGTERM (a
service manager, `docker stop`, `kill`) as it does on Ctrl-C (common/shutdown.py). The engine is a process of its
own that ignores SIGTERM and outlives a killed parent, with ~10 MB of shared memory in /dev/shm."""
import json
import multiprocessing
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from common import shutdown
from common.shutdown import EXIT_STATUS, Terminated, exit_on_sigterm, stop_pool

REPO = Path(__file__).resolve().parents[1]
linux_only = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads the process tree from Linux's /proc")


# --- the process tree, from /proc ------------------------------------------------------------------------------------

def _stat(pid: int):
    """(state, ppid) of a process, or None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return None
    fields = stat[stat.rfind(b")") + 2:].split()
    return fields[0].decode(), int(fields[1])


def _alive(pid: int) -> bool:
    stat = _stat(pid)
    return stat is not None and stat[0] not in ("Z", "X")  # a zombie has stopped: only its exit status is left


def _descendants(root: int) -> set:
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit() and (stat := _stat(int(entry))) is not None:
            parents[int(entry)] = stat[1]
    found, frontier = set(), {root}
    while frontier:
        frontier = {pid for pid, ppid in parents.items() if ppid in frontier} - found
        found |= frontier
    return found


def _cmdline(pid: int) -> list:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def _engine_id(pid: int):
    """The ViZDoom instance id of an engine process (it names the engine's shared memory), else None."""
    args = _cmdline(pid)
    if not args or Path(args[0]).name != "vizdoom" or "+viz_instance_id" not in args:
        return None
    return args[args.index("+viz_instance_id") + 1]


def _engine_folder(cmdline: list):
    """The private working folder of an engine (its -config file's folder, a temporary one), else None."""
    if "-config" not in cmdline:
        return None
    folder = Path(cmdline[cmdline.index("-config") + 1]).parent
    return folder if folder.name.startswith("vizdoom.") else None


def _engines_running(instance_ids) -> list:
    """Processes anywhere on the machine still running an engine of these instances (its pid may have moved on)."""
    return [pid for entry in os.listdir("/proc") if entry.isdigit() and _alive(pid := int(entry))
            and _engine_id(pid) in instance_ids]


def _shared_memory_left(instance_ids) -> list:
    shm = Path("/dev/shm")
    return sorted(p.name for p in shm.iterdir() if p.name.startswith("ViZDoom") and
                  any(p.name.endswith(i) for i in instance_ids)) if shm.is_dir() else []


def _still_running(seen: dict) -> list:
    return [pid for pid, cmdline in seen.items() if _alive(pid) and _cmdline(pid) == cmdline]


def _kill_leftovers(pids) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


def stop_and_check(proc: subprocess.Popen, log: Path, engines: int, ready=lambda: True, sig=signal.SIGTERM,
                   timeout_s: float = 90.0) -> int:
    """Once `proc` runs `engines` ViZDoom engines and `ready()`, send it `sig`; assert that it exits within 30 s and
    that every process it started (its engines, its workers) is gone, and the engines' shared memory with them.
    Returns its exit status. Only this command's own process tree is looked at: other engines on the machine are
    none of its business."""
    seen, ids = {}, {}  # pid: command line (a pid reused by someone else is not this command's), pid: engine id
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            assert proc.poll() is None, f"exited with {proc.returncode} before it was stopped:\n{log.read_text()}"
            seen.update({pid: _cmdline(pid) for pid in _descendants(proc.pid) - seen.keys()})
            ids.update({pid: i for pid in seen if pid not in ids and (i := _engine_id(pid))})
            if len(ids) >= engines and ready():
                break
            assert time.monotonic() < deadline, f"{len(ids)} of {engines} engines after {timeout_s:.0f} s"
            time.sleep(0.2)
        time.sleep(0.5)
        seen.update({pid: _cmdline(pid) for pid in _descendants(proc.pid) - seen.keys()})
        proc.send_signal(sig)
        status = proc.wait(timeout=30)
        time.sleep(0.5)  # an engine told to quit is gone in a few ms
        left = _still_running(seen)
        assert not left, f"left running after {sig.name}: {[(p, seen[p][:1]) for p in left]}\n{log.read_text()}"
        assert not _engines_running(set(ids.values()))
        assert not _shared_memory_left(set(ids.values()))
        assert not [f for pid in ids if (f := _engine_folder(seen[pid])) and f.exists()]  # their temporary folders
        return status
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _kill_leftovers(_still_running(seen))
        for pid, instance in ids.items():  # a failed run's leftovers, so that they do not pile up on the machine
            for name in _shared_memory_left({instance}):
                Path("/dev/shm", name).unlink(missing_ok=True)
            if (folder := _engine_folder(seen[pid])) is not None:
                shutil.rmtree(folder, ignore_errors=True)


def start(args, log: Path) -> subprocess.Popen:
    with open(log, "wb") as out:  # a file, not a pipe: nobody reads it while the command runs
        return subprocess.Popen([sys.executable, *map(str, args)], cwd=REPO, stdout=out, stderr=subprocess.STDOUT)


# --- SIGTERM as an orderly exit --------------------------------------------------------------------------------------

@pytest.fixture
def sigterm_default():
    """SIGTERM's default disposition for the test; the handler pytest had is put back after."""
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield
    signal.signal(signal.SIGTERM, previous)
    shutdown._exiting_pid = None


def test_sigterm_raises_terminated_once(sigterm_default):
    assert exit_on_sigterm() and exit_on_sigterm()  # again: a no-op
    with pytest.raises(Terminated) as stop:
        signal.raise_signal(signal.SIGTERM)
    assert isinstance(stop.value, SystemExit) and stop.value.code == EXIT_STATUS == 143
    signal.raise_signal(signal.SIGTERM)  # already unwinding: a second one does not cut the closing short


def test_a_handler_set_before_is_left_alone(sigterm_default):
    def handler(signum, frame):
        pass

    signal.signal(signal.SIGTERM, handler)
    assert not exit_on_sigterm()
    assert signal.getsignal(signal.SIGTERM) is handler
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    assert not exit_on_sigterm() and signal.getsignal(signal.SIGTERM) is signal.SIG_IGN


def _unwinds(marker):
    Path(marker).write_text("started")
    try:
        time.sleep(60)
    finally:  # where a worker closes its engine
        Path(marker).write_text("closed")


def _stuck_with_a_child(pid_file):
    """A worker blocked where no signal handler runs (as in a hung engine's call), with a child that ignores
    SIGTERM (as an engine does)."""
    child = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, "
                              "signal.SIG_IGN); print(flush=True); time.sleep(60)"], stdout=subprocess.PIPE)
    child.stdout.readline()
    Path(pid_file).write_text(json.dumps([os.getpid(), child.pid]))
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    time.sleep(60)


def _wait_for(path: Path, timeout_s: float = 30.0):
    deadline = time.monotonic() + timeout_s
    while not path.exists() or not path.read_text():
        assert time.monotonic() < deadline, f"{path} not written in {timeout_s} s"
        time.sleep(0.05)


def test_stop_pool_unwinds_each_worker(tmp_path):
    marker = tmp_path / "closed"
    pool = multiprocessing.Pool(1, initializer=exit_on_sigterm)
    pool.apply_async(_unwinds, (str(marker),))
    _wait_for(marker)
    t0 = time.monotonic()
    stop_pool(pool, grace_s=20)
    assert time.monotonic() - t0 < 10 and marker.read_text() == "closed"


@linux_only
def test_stop_pool_kills_a_stuck_worker_and_its_child(tmp_path):
    pid_file = tmp_path / "pids"
    pool = multiprocessing.Pool(1, initializer=exit_on_sigterm)
    pool.apply_async(_stuck_with_a_child, (str(pid_file),))
    _wait_for(pid_file)
    worker, child = json.loads(pid_file.read_text())
    t0 = time.monotonic()
    stop_pool(pool, grace_s=1)
    assert time.monotonic() - t0 < 10
    time.sleep(0.2)
    assert not _alive(worker) and not _alive(child)


# --- the commands that start engines --------------------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serves(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return json.loads(response.read())["real_world"]
    except OSError:
        return False


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    pytest.importorskip("vizdoom", reason="the commands under test start ViZDoom engines")
    from tests.play_fixtures import tiny_play_world

    return tiny_play_world(tmp_path_factory.mktemp("shutdown"))


@linux_only
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "Ctrl-C"])
def test_play_closes_its_real_world_on_sigterm_as_on_ctrl_c(world, tmp_path, sig):
    port = _free_port()
    proc = start(["play.py", "--checkpoint_dir", world["model"], "--data_dir", world["data"], "--device", "cpu",
                  "--num_threads", "1", "--port", port], tmp_path / "play.log")
    status = stop_and_check(proc, tmp_path / "play.log", engines=1, sig=sig,
                            ready=lambda: _serves(f"http://127.0.0.1:{port}/state"))
    if sig == signal.SIGTERM:  # the shell's status of a terminated command (Ctrl-C's is uvicorn's business)
        assert status == EXIT_STATUS, (tmp_path / "play.log").read_text()


@linux_only
def test_renderer_stops_its_workers_and_their_engines_on_sigterm(tmp_path):
    pytest.importorskip("vizdoom", reason="the renderer starts ViZDoom engines")
    out = tmp_path / "raw"
    proc = start(["-m", "sample_world.render", "--output_dir", out, "--train_maps", "MAP01", "MAP02",
                  "--val_maps", "MAP01", "--train_episodes", "6", "--episode_len", "4000", "--workers", "2"],
                 tmp_path / "render.log")
    assert stop_and_check(proc, tmp_path / "render.log", engines=2) == EXIT_STATUS
    assert not (out / "train.npz").exists() and not (out / "sample_world.json").exists()
