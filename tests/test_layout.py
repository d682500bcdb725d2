"""The package boundaries: each package imports only the packages below it in pipeline order; genie/ (the network)
reaches only common/; nothing imports the play server but play.py; flags are parsed only in entry points."""
import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# package -> the project packages it may import (itself included), in pipeline order
ALLOWED = {
    "common": {"common"},
    "data": {"common", "data"},
    "magvit2": {"common", "data", "magvit2"},
    "genie": {"common", "genie"},
    "lam": {"common", "data", "magvit2", "lam"},
    "training": {"common", "data", "genie", "training"},
    "sample_world": {"common", "data", "magvit2", "sample_world"},
    "envs": {"common", "data", "magvit2", "genie", "training", "sample_world", "envs"},
    "evaluation": {"common", "data", "magvit2", "genie", "training", "sample_world", "envs", "evaluation"},
    "play_server": {"common", "envs", "play_server"},
}
PACKAGES = set(ALLOWED)
# what the network must load without: the environments, the web server, the simulator, the command line
NOT_IN_GENIE = {"gymnasium", "fastapi", "uvicorn", "starlette", "vizdoom", "argparse", "tqdm"}


def imports(path: Path) -> set:
    """The top-level names of every module `path` imports (at module level or inside functions)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def top_level(names: set) -> set:
    return {name.split(".")[0] for name in names}


def project_modules():
    """Every Python file of the project's packages and root scripts (not tests or benchmarks)."""
    for path in sorted(REPO.glob("*.py")):
        yield path
    for package in sorted(PACKAGES):
        yield from sorted((REPO / package).rglob("*.py"))


def is_entry_point(path: Path) -> bool:
    return "if __name__ == \"__main__\":" in path.read_text()


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_no_package_imports_a_higher_layer(package):
    for path in sorted((REPO / package).rglob("*.py")):
        higher = top_level(imports(path)) & PACKAGES - ALLOWED[package]
        assert not higher, f"{path.relative_to(REPO)} imports {sorted(higher)}"


def test_the_network_needs_nothing_of_the_pipeline():
    """genie/ holds what loading, training-forward and sampling the weights needs, and nothing else: no
    environment, server, simulator, command line or progress bar."""
    for path in sorted((REPO / "genie").rglob("*.py")):
        found = top_level(imports(path)) & NOT_IN_GENIE
        assert not found, f"{path.relative_to(REPO)} imports {sorted(found)}"


def test_nothing_imports_the_play_server_but_play_py():
    for path in project_modules():
        if path.parent.name != "play_server" and path.name != "play.py":
            assert "play_server" not in top_level(imports(path)), f"{path.relative_to(REPO)} imports play_server"


def test_flags_are_parsed_only_in_entry_points():
    """argparse (and the modules that define flags, `cli.py`) belong to entry points: a library function takes
    dataclasses and values, never a parsed command line."""
    for path in project_modules():
        if is_entry_point(path) or path.name == "cli.py":
            continue
        found = {name for name in imports(path) if name == "argparse" or name.endswith(".cli")}
        assert not found, f"{path.relative_to(REPO)} is no entry point but imports {sorted(found)}"


def test_the_layout_check_finds_what_it_looks_for(tmp_path):
    """The checks above read imports anywhere in a file, in both forms."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    import argparse\n    from evaluation.cli import eval_config\n"
                     "from play_server.app import build_app\n")
    assert imports(probe) == {"argparse", "evaluation.cli", "play_server.app"}
    assert top_level(imports(probe)) & PACKAGES == {"evaluation", "play_server"}
    assert not is_entry_point(probe)


SCRIPTS = ["train.py", "evaluate.py", "visualize.py", "generate.py", "diagnose.py", "play.py", "magvit2/train.py",
           "magvit2/tokenize_frames.py", "magvit2/lpips_weights.py", "sample_world/build.py", "sample_world/render.py",
           "lam/train.py", "lam/label.py", "data/verify.py"]


def test_every_script_answers_help():
    """--help parses every entry point's flags without running anything (one interpreter, to stay quick)."""
    code = ("import runpy, sys\n"
            "for script in sys.argv[1:]:\n"
            "    sys.argv = [script, '--help']\n"
            "    try:\n"
            "        runpy.run_path(script, run_name='__main__')\n"
            "    except SystemExit as e:\n"
            "        assert e.code == 0, (script, e.code)\n"
            "    else:\n"
            "        raise AssertionError(f'{script} --help did not exit')\n")
    proc = subprocess.run([sys.executable, "-c", code, *SCRIPTS], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count("usage:") == len(SCRIPTS)
    assert "debug" not in proc.stdout.lower()


@pytest.mark.parametrize("script", ["run_sample.sh", "run_gpu.sh", "build.sh"])
def test_every_shell_job_answers_help_without_running(script, tmp_path):
    """--help prints the script's header (what it does, its variables) and runs nothing, even from elsewhere."""
    proc = subprocess.run(["bash", str(REPO / script), "--help"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PY": "/nonexistent/python"})
    assert proc.returncode == 0, proc.stderr
    header = [line for line in (REPO / script).read_text().splitlines()[1:6] if line.startswith("#")]
    assert header and header[0].lstrip("# ") in proc.stdout
    assert "#!" not in proc.stdout and "set -euo" not in proc.stdout and not list(tmp_path.iterdir())


def test_no_world_trains_on_a_scored_map():
    """The default world's training maps, which run_gpu.sh's default spells out, share none with the validation
    split's held-out map or with any set of unseen maps that build.sh --unseen makes: those sets exist to score maps
    no run trained on. Validation's other walks are on training maps."""
    from sample_world.render import HELDOUT_MAPS, TRAIN_MAPS, VAL_MAPS

    gpu_maps = re.search(r'^GPU_TRAIN_MAPS="([^"]+)"$', (REPO / "run_gpu.sh").read_text(), re.M).group(1).split()
    build = (REPO / "build.sh").read_text()
    table = build[build.index("<<'SETS'\n") + len("<<'SETS'\n"):build.index("\nSETS\n")].splitlines()
    unseen = {name: line.split()[2:] for line in table for name in line.split()[:1]}
    assert set(unseen) == {"unseen", "unseen2", "unseen3"}
    assert len(gpu_maps) == len(set(gpu_maps)) == 16 and gpu_maps == list(TRAIN_MAPS)
    for name, maps in unseen.items():
        assert not set(TRAIN_MAPS) & set(maps), f"the default world trains on {name}'s maps"
    assert not set(TRAIN_MAPS) & set(HELDOUT_MAPS)
    assert set(VAL_MAPS) - set(HELDOUT_MAPS) <= set(TRAIN_MAPS) and set(HELDOUT_MAPS) <= set(VAL_MAPS)


def test_the_network_loads_without_the_data_side_or_inference():
    """genie.model (the network and its loss) reads in one sitting: importing it loads neither the data packages nor
    the collator, the sampler or the inference code."""
    code = "import sys, genie.model; print(' '.join(sorted(sys.modules)))"
    loaded = set(subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True,
                                env={**os.environ, "PYTHONPATH": str(REPO)}).stdout.split())
    assert "genie.model" in loaded and "genie.transformer" in loaded
    for module in ("data", "magvit2", "training.masking", "training.action_streams", "genie.sampling", "genie.inference",
                   "genie.reference"):
        assert module not in loaded, f"importing genie.model loads {module}"
