"""Test-session set-up shared by every test module."""

from __future__ import annotations

import pytest

import _net


@pytest.fixture(autouse=True, scope="session")
def _process_logs_under_pytest_tmp(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The stderr logs of processes a test spawns without a folder of its own go under pytest's temporary tree
    (kept for the last few runs, then pruned by pytest) instead of one ``/tmp/e2e-*`` folder per process, forever."""
    _net.LOG_ROOT = tmp_path_factory.mktemp("proc-logs")
