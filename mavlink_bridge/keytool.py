"""``python -m mavlink_bridge.keytool``: create or check a MAVLink signing key file
(64 hex characters, mode 600; docs/security.md)."""

from __future__ import annotations

from .signing import SigningKeyError, load_signing_key, write_signing_key


def _main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m mavlink_bridge.keytool", description="MAVLink signing key files")
    ap.add_argument("--generate", metavar="FILE", help="create FILE (mode 600) with a new random key")
    ap.add_argument("--check", metavar="FILE", help="check that FILE is a usable key file")
    args = ap.parse_args(argv)
    try:
        if args.generate:
            write_signing_key(args.generate)
            print(f"wrote a new MAVLink signing key to {args.generate} (mode 600)")
        if args.check:
            load_signing_key(args.check)
            print(f"{args.check}: OK")
    except (SigningKeyError, OSError) as exc:
        print(f"error: {exc}")
        return 1
    if not (args.generate or args.check):
        ap.print_help()
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
