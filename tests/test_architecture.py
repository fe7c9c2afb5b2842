"""Who may import whom (STYLE.md): checked on the source, not on trust."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(pkg: str) -> dict[str, set[str]]:
    out = {}
    for f in (ROOT / pkg).rglob("*.py"):
        names = set()
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module.split(".")[0])
        out[str(f.relative_to(ROOT))] = names
    return out


def test_mock_vehicle_never_imports_the_controller():
    for f, names in _imports("mock_vehicle").items():
        assert "mfg_autopilot" not in names and "mfg_swarm" not in names, f


def test_what_runs_on_a_vehicle_needs_no_mock_and_no_launcher():
    for pkg in ("mfg_autopilot", "mavlink_bridge"):
        for f, names in _imports(pkg).items():
            assert "mock_vehicle" not in names and "mfg_swarm" not in names, f


def test_pymavlink_lives_behind_one_adapter_and_zenoh_behind_one_module():
    for pkg in ("mfg_autopilot", "mock_vehicle", "mfg_swarm"):
        for f, names in _imports(pkg).items():
            assert "pymavlink" not in names, f
            if f != "mfg_autopilot/exchange.py":
                assert "zenoh" not in names, f
    for f, names in _imports("mavlink_bridge").items():
        assert "zenoh" not in names, f


def test_numeric_core_does_no_io():
    core = ["features", "model", "costs", "learners", "meanfield", "params"]
    for mod in core:
        names = _imports("mfg_autopilot")[f"mfg_autopilot/{mod}.py"]
        assert not names & {"socket", "os", "subprocess", "zenoh", "pymavlink", "logging", "threading"}, mod


def test_numba_lives_in_the_kernel_modules_only():
    """Compiled code stays behind three modules (STYLE: one module per capability); the mock vehicle and the
    MAVLink bridge never pay numba's import."""
    kernels = {"mfg_autopilot/kernels.py", "mfg_autopilot/backstop_kernels.py", "mfg_swarm/spatial.py"}
    for pkg in ("mfg_autopilot", "mock_vehicle", "mfg_swarm", "mavlink_bridge"):
        for f, names in _imports(pkg).items():
            if f not in kernels:
                assert "numba" not in names, f
