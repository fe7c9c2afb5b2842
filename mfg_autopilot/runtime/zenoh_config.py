"""Zenoh settings, built once at the command line and passed down as a value; opening a session; a router.

Every process that talks Zenoh (a vehicle's controller, ``mfg_autopilot.runtime.router``) opens its
session here, from a :class:`ZenohSettings` (:meth:`ZenohSettings.add_cli_args` / :meth:`from_args`).
"""

from __future__ import annotations

import argparse
import json
import threading
from dataclasses import dataclass
from typing import Callable

import zenoh

from mfg_autopilot.runtime.wire import ExchangeError

__all__ = ["ZENOH_MODES", "ZenohSettings", "open_session", "run_router"]

ZENOH_MODES = ("peer", "client", "router")


# --------------------------------------------------------------------------------------
# Settings: built once at the command line, passed down as a value
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ZenohSettings:
    """How to open the Zenoh session.

    ``config_file`` (a zenoh json5 config) is applied first; the fields below then override it:
    ``mode`` and ``multicast_scouting`` always, ``connect`` / ``listen`` when non-empty. With
    no config file and no ``listen``, peers and clients listen on ``tcp/127.0.0.1:0``
    (loopback only); routers keep zenoh's default (``tcp/[::]:7447``).
    """

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    multicast_scouting: bool = False

    def __post_init__(self) -> None:
        if self.mode not in ZENOH_MODES:
            raise ValueError(f"zenoh mode must be one of {ZENOH_MODES}, got {self.mode!r}")
        for ep in (*self.connect, *self.listen):
            if "/" not in ep:
                raise ValueError(f"zenoh endpoint must look like tcp/HOST:PORT, got {ep!r}")

    @staticmethod
    def add_cli_args(parser: argparse.ArgumentParser) -> None:
        g = parser.add_argument_group("zenoh")
        g.add_argument("--zenoh-mode", choices=ZENOH_MODES, default="peer",
                       help="session mode (default: peer)")
        g.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
        g.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable; "
                            "default for peers: tcp/127.0.0.1:0)")
        g.add_argument("--zenoh-config", default=None, metavar="FILE",
                       help="zenoh json5 config file, applied before the flags above")
        g.add_argument("--zenoh-multicast-scouting", action="store_true",
                       help="enable multicast scouting (off by default: it leaves loopback)")

    @staticmethod
    def from_args(ns: argparse.Namespace) -> "ZenohSettings":
        return ZenohSettings(
            mode=ns.zenoh_mode,
            connect=tuple(ns.zenoh_connect or ()),
            listen=tuple(ns.zenoh_listen or ()),
            config_file=ns.zenoh_config,
            multicast_scouting=bool(getattr(ns, "zenoh_multicast_scouting", False)),
        )

    def to_config(self) -> zenoh.Config:
        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        elif self.config_file is None and self.mode != "router":
            conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
        return conf


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a zenoh session; the caller must close it (``with open_session(s) as z:``)."""
    try:
        return zenoh.open(settings.to_config())
    except Exception as e:  # zenoh.ZError and config errors
        raise ExchangeError(f"cannot open zenoh session ({settings.mode}, connect="
                            f"{list(settings.connect)}, listen={list(settings.listen)}): {e}") from e


def run_router(settings: ZenohSettings, stop: threading.Event,
               on_ready: Callable[[], None] | None = None) -> None:
    """Run a zenoh session (normally ``mode="router"``) until ``stop`` is set, then close it."""
    session = open_session(settings)
    try:
        if on_ready is not None:
            on_ready()
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
