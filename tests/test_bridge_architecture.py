"""Import rules (STYLE "who may import whom"; issue 4): pymavlink only inside
mavlink_bridge; the mock vehicle never imports the controller; the vehicle-side code
(controller + bridge) does not need mock_vehicle; nothing below the CLI reads os.environ."""

from __future__ import annotations

import ast
import subprocess
from pathlib import Path

from _net import PYTHON

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ["mavlink_bridge", "mock_vehicle", "mfg_autopilot", "mfg_swarm"]


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def _py_files(*dirs: str):
    for d in dirs:
        yield from (REPO / d).rglob("*.py")


def test_pymavlink_is_imported_only_by_mavlink_bridge():
    offenders = [
        str(f.relative_to(REPO))
        for f in _py_files(*PACKAGES, "tests", "bench")
        if not f.is_relative_to(REPO / "mavlink_bridge") and any(m.split(".")[0] == "pymavlink" for m in _imports(f))
    ]
    assert offenders == []


def test_mock_vehicle_never_imports_the_controller():
    offenders = [str(f) for f in _py_files("mock_vehicle") if any(m.split(".")[0] == "mfg_autopilot" for m in _imports(f))]
    assert offenders == []
    code = "import sys, mock_vehicle.cli, mock_vehicle.server, mock_vehicle.vehicle; print(sorted(m for m in sys.modules if m.startswith('mfg_')))"
    out = subprocess.run([PYTHON, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_mavlink_bridge_needs_no_mock_vehicle():
    offenders = [str(f) for f in _py_files("mavlink_bridge") if any(m.split(".")[0] == "mock_vehicle" for m in _imports(f))]
    assert offenders == []


def test_no_environment_reads_below_the_cli():
    readers = []
    for f in _py_files("mavlink_bridge", "mock_vehicle"):
        if f.name == "cli.py":
            continue
        src = f.read_text()
        if "os.getenv" in src or "environ.get" in src or "environ[" in src.replace('os.environ["MAVLINK20"] = "1"', ""):
            readers.append(str(f.relative_to(REPO)))
    assert readers == []
