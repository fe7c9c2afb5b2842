"""Who may import whom (STYLE.md, docs/architecture.md): import-linter holds the rules.

The contracts live in ``pyproject.toml`` (``[tool.importlinter]``). One test runs them on the
real code; the others build a fixture tree with the same package and module names (empty
modules plus the few imports the contracts expect), check that it passes, then add one
forbidden import each and check that ``lint-imports`` fails naming the broken contract. So a
contract that could never fail (a typo in a module name, a layer that matches nothing) fails here.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("mfg_autopilot", "mfg_swarm", "mock_vehicle", "mavlink_bridge")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")

# Imports the fixture tree keeps so that it passes as the real code does (the numba and pyrvo contracts'
# ignore_imports must match something; a kernel imports numba, the orca bank pyrvo).
BASE_IMPORTS = {
    "mfg_autopilot/paper/kernels.py": "import numba\n",
    "mfg_autopilot/safety/kernels.py": "import numba\n",
    "mfg_swarm/spatial.py": "import numba\n",
    "mfg_autopilot/safety/backstop.py": "from mfg_autopilot.safety import kernels\n",
    "mfg_autopilot/safety/orca.py": "import pyrvo\n",
}


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(cwd)
    return subprocess.run([str(LINT_IMPORTS), "--config", str(cwd / "pyproject.toml"), "--no-cache"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def _fixture_tree(tmp: Path) -> Path:
    """The project's packages as empty modules (same names), and its import-linter contracts."""
    for pkg in PACKAGES:
        for src in (ROOT / pkg).rglob("*.py"):
            rel = src.relative_to(ROOT)
            dst = tmp / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_text(BASE_IMPORTS.get(rel.as_posix(), ""))
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    lines = ["[tool.importlinter]", f"root_packages = {_toml(config['root_packages'])}",
             f"include_external_packages = {_toml(config['include_external_packages'])}"]
    for c in config["contracts"]:
        lines.append("\n[[tool.importlinter.contracts]]")
        lines += [f"{k} = {_toml(v)}" for k, v in c.items()]
    (tmp / "pyproject.toml").write_text("\n".join(lines) + "\n")
    return tmp


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return '"' + str(v).replace('"', '\\"') + '"'


def test_the_real_code_keeps_every_contract():
    proc = _lint(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


def test_the_fixture_tree_keeps_every_contract(tmp_path):
    proc = _lint(_fixture_tree(tmp_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("module,line,contract", [
    ("mfg_autopilot/paper/model.py", "from mfg_autopilot.guidance import planner\n", "Controller rooms"),
    ("mfg_autopilot/safety/backstop.py", "from mfg_autopilot.guidance import controller\n", "Controller rooms"),
    ("mfg_autopilot/paper/learners.py", "import mfg_autopilot.runtime.autopilot\n", "Controller rooms"),
    ("mfg_autopilot/pde/solver.py", "from mfg_autopilot.guidance import planner\n", "Controller rooms"),
    ("mock_vehicle/plant.py", "import mfg_autopilot.paper.model\n", "Packages"),
    ("mavlink_bridge/link.py", "import mfg_swarm.sim\n", "Packages"),
    ("mfg_autopilot/guidance/planner.py", "import pymavlink.mavutil\n", "pymavlink"),
    ("mock_vehicle/vehicle.py", "from pymavlink import mavutil\n", "pymavlink"),
    ("mfg_autopilot/paper/features.py", "import zenoh\n", "zenoh"),
    ("mfg_swarm/launcher.py", "import zenoh\n", "zenoh"),
    ("mfg_autopilot/paper/costs.py", "import numba\n", "numba"),
    ("mock_vehicle/plant.py", "import numba\n", "numba"),
    ("mfg_autopilot/safety/backstop.py", "import pyrvo\n", "pyrvo"),
    ("mfg_swarm/sim.py", "from pyrvo import RVOSimulator\n", "pyrvo"),
    ("mavlink_bridge/tlog.py", "import mcap.reader\n", "Foxglove and MCAP"),
    ("mfg_autopilot/runtime/autopilot.py", "import foxglove\n", "Foxglove and MCAP"),
    ("mfg_autopilot/guidance/controller.py", "import socket\n", "no I/O"),
    ("mfg_autopilot/paper/learners.py", "import logging\n", "no I/O"),
    # a lazy (function-level) import that closes a circle
    ("mfg_autopilot/safety/kernels.py", "def warm_up():\n    from mfg_autopilot.safety import backstop\n", "No import circle"),
])
def test_a_forbidden_import_breaks_its_contract(tmp_path, module, line, contract):
    tree = _fixture_tree(tmp_path)
    path = tree / module
    path.write_text(path.read_text() + line)
    proc = _lint(tree)
    assert proc.returncode != 0, proc.stdout
    broken = proc.stdout.split("Broken contracts")[-1]
    assert contract in broken, proc.stdout
