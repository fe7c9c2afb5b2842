"""A Zenoh router (or any session mode) as a process: ``python -m mfg_autopilot.runtime.router``.

Stands in for ``zenohd`` where it is not installed: vehicles in client mode connect to it,
and routers on several hosts join separate networks (docs/zenoh.md). Prints ``ready`` on
stdout once the session is open; runs until SIGTERM / SIGINT, then closes the session.

    python -m mfg_autopilot.runtime.router --zenoh-listen tcp/0.0.0.0:7447
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from mfg_autopilot.runtime.exchange import ExchangeError, ZenohSettings, run_router


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mfg_autopilot.runtime.router",
                                     description=__doc__.splitlines()[0])
    ZenohSettings.add_cli_args(parser)
    parser.set_defaults(zenoh_mode="router")
    settings = ZenohSettings.from_args(parser.parse_args(argv))
    stop = threading.Event()

    def on_ready() -> None:
        # installed after the session is open: opening it may replace signal handlers
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
        print("ready", flush=True)

    try:
        run_router(settings, stop, on_ready=on_ready)
    except ExchangeError as e:
        print(f"zenoh_router: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
