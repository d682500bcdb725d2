"""Command lines run as `python -m module` / `python script.py` would run them, many in one interpreter: the
imports are most of a small command's time, and the `__main__` wiring is what the tests of bad input check."""
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# Runs each (name, module or script, argv) as `python -m module argv` / `python script argv` would, in one
# interpreter: stdout and stderr captured per command, its exit status from SystemExit ("crash" for any other
# exception, whose traceback then lands in its stderr).
RUNNER = """
import contextlib, io, json, runpy, sys, traceback, warnings
warnings.filterwarnings('ignore', message='.*found in sys.modules after import of package')  # an earlier command's
results = {}
for name, target, argv in json.loads(sys.argv[1]):
    err, out = io.StringIO(), io.StringIO()
    sys.argv = [target, *argv]
    code = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            if target.endswith('.py'):
                runpy.run_path(target, run_name='__main__')
            else:
                runpy.run_module(target, run_name='__main__', alter_sys=True)
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) or stop.code is None else 1
            if isinstance(stop.code, str):
                err.write(stop.code + '\\n')
        except BaseException:
            code = 'crash'
            traceback.print_exc(file=err)
    results[name] = {'returncode': code, 'stdout': out.getvalue(), 'stderr': err.getvalue()}
print(json.dumps(results))
"""


def run_as_main(commands: dict, cwd=REPO, env=None) -> dict:
    """{name: (module or script path, argv)} -> {name: CompletedProcess of running it as __main__}, all in one
    interpreter started in `cwd` with `env`."""
    batch = [(name, str(target), [str(a) for a in argv]) for name, (target, argv) in commands.items()]
    proc = subprocess.run([sys.executable, "-c", RUNNER, json.dumps(batch)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    return {name: subprocess.CompletedProcess(commands[name], r["returncode"], r["stdout"], r["stderr"])
            for name, r in zip(commands, results.values())}
