"""Write a per-vehicle Zenoh access-control set for one swarm: a router config, its credentials
file, one client config per vehicle and one for an observer, with fresh random passwords.

    python examples/zenoh_acl/make_acl.py --swarm demo --n 4 --router tcp/10.0.0.1:7447 --out acl/

Unlike the shared-user example (router.json5 / vehicle.json5 in this folder), vehicle i logs in
as ``vehicle<i>`` and may only put ``mfg/<swarm>/state/<i>``, hold ``mfg/<swarm>/alive/<i>`` and
answer on ``mfg/<swarm>/init/<i>``: a vehicle whose credentials leak cannot speak for another
vehicle. Every vehicle and the observer may listen to all of ``mfg/<swarm>/**``. Secrets are
written owner-only (0600). Run the router with

    python -m mfg_autopilot.runtime.router --zenoh-config acl/router.json5

and vehicle i with ``--zenoh-mode client --zenoh-config acl/vehicle<i>.json5``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import secrets
from pathlib import Path

LISTEN_INGRESS = ["declare_subscriber", "query", "liveliness_query", "declare_liveliness_subscriber"]
HEAR_EGRESS = ["put", "delete", "reply", "liveliness_token", "query", "declare_subscriber",
               "declare_queryable", "liveliness_query", "declare_liveliness_subscriber"]


def router_config(swarm: str, n: int, listen: str, creds_path: str, router_password: str) -> dict:
    own = f"mfg/{swarm}"
    rules = [
        {"id": "listen", "permission": "allow", "flows": ["ingress"], "messages": LISTEN_INGRESS,
         "key_exprs": [f"{own}/**"]},
        {"id": "hear", "permission": "allow", "flows": ["egress"], "messages": HEAR_EGRESS,
         "key_exprs": [f"{own}/**"]},
    ]
    subjects = [{"id": "observer", "usernames": ["observer"]}]
    policies = [{"id": "observer", "rules": ["listen", "hear"], "subjects": ["observer"]}]
    for i in range(n):
        rules += [
            {"id": f"state{i}", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
             "key_exprs": [f"{own}/state/{i}"]},
            {"id": f"alive{i}", "permission": "allow", "flows": ["ingress"],
             "messages": ["liveliness_token"], "key_exprs": [f"{own}/alive/{i}"]},
            {"id": f"init{i}", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_queryable", "reply"], "key_exprs": [f"{own}/init/{i}"]},
        ]
        subjects.append({"id": f"vehicle{i}", "usernames": [f"vehicle{i}"]})
        policies.append({"id": f"vehicle{i}", "subjects": [f"vehicle{i}"],
                         "rules": ["listen", "hear", f"state{i}", f"alive{i}", f"init{i}"]})
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": "router", "password": router_password,
                                          "dictionary_file": creds_path}}},
        "access_control": {"enabled": True, "default_permission": "deny", "rules": rules,
                           "subjects": subjects, "policies": policies},
    }


def client_config(router: str, user: str, password: str) -> dict:
    return {
        "mode": "client",
        "connect": {"endpoints": [router]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}},
    }


def _write(path: Path, text: str, secret: bool) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if secret else 0o644)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    if secret:
        os.chmod(path, 0o600)


def main(swarm: str, n: int, router: str, listen: str, out: Path) -> dict[str, Path]:
    """Write the set into ``out``; returns {name: path}."""
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", swarm):
        raise ValueError(f"swarm must be one key chunk ([A-Za-z0-9_.-]+), got {swarm!r}")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    out.mkdir(parents=True, exist_ok=True)
    users = {f"vehicle{i}": secrets.token_urlsafe(18) for i in range(n)}
    users["observer"] = secrets.token_urlsafe(18)
    paths = {"credentials": out / "credentials.txt", "router": out / "router.json5"}
    _write(paths["credentials"], "".join(f"{u}:{p}\n" for u, p in users.items()), secret=True)
    header = "// written by examples/zenoh_acl/make_acl.py; keep owner-only (0600)\n"
    conf = router_config(swarm, n, listen, str(paths["credentials"].resolve()),
                         secrets.token_urlsafe(18))
    _write(paths["router"], header + json.dumps(conf, indent=2) + "\n", secret=True)
    for user, password in users.items():
        paths[user] = out / f"{user}.json5"
        _write(paths[user], header + json.dumps(client_config(router, user, password), indent=2)
               + "\n", secret=True)
    return paths


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--swarm", required=True, help="swarm name (one key chunk)")
    ap.add_argument("--n", type=int, required=True, help="number of vehicles (ids 0 .. n-1)")
    ap.add_argument("--router", default="tcp/127.0.0.1:7447",
                    help="endpoint the clients connect to (default tcp/127.0.0.1:7447)")
    ap.add_argument("--listen", default=None,
                    help="endpoint the router listens on (default: the --router endpoint)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ns = ap.parse_args()
    for name, p in main(ns.swarm, ns.n, ns.router, ns.listen or ns.router, ns.out).items():
        print(f"{name}: {p}")
