"""Why did the escape choose what it chose? One `sim` flight, and at the given control steps the escape manoeuvre's
candidate table for one UAV (`mfg_autopilot.safety.backstop.escape_acc`): where a trace that `bench/closest_pair.py`
started goes on (docs/default_controller.md, "Where it does not hold yet"; docs/benchmarks.md, thirty-fourth round).

    .venv/bin/python bench/escape_candidates.py --scenario dense --n 1000 --seed 204 --uav 75 --steps 42,43,44 \\
        --gust --fail-vehicle 10 --fail-at 20.15 [--backstop '{"escape_effort": 0.3}'] [--top 8] [--radius-m 6]

MFG, the default preset (its BackstopParams changed by --backstop, a JSON object of fields), PX4's lag and the inner
loop as `mfg-swarm sim` flies them. At each step of --steps where the UAV's escape is active it prints the UAV's state,
its nominal command a_nom and the command the escape sent, the sensed threats within --radius-m (position relative to
the UAV, velocity, trigger, clearance, hovering, braking hypothesis), then one line per first-phase candidate a_1 (a_nom,
0, the escape directions at a_max / 2 and a_max): its component along the own velocity, and for each second phase a_2 in
(a_nom, 0, -a_1, a_1) the conflict penalty, `S` if it keeps every sensed entry escape_hard_fraction x its clearance
away (safe) or `u`, the worst entry's predicted distance over its clearance (for a threat with a tube,
BackstopParams.escape_tube_m_s2: over its clearance plus the tube's radius then) and when; then the penalty (the best
phase's), the safe penalty (the best safe phase's), the effort and the lane-side cost. Lines in the escape's order:
candidates with a safe phase first, by safe penalty + effort + side; then the rest by penalty + effort + side. The
first line is what the escape takes; the tool checks it against the command the kernel sent and says so (a mismatch
means this file's arithmetic is out of date with `kernels.escape_candidates`).

The prediction is the escape's own (relative tracks at constant velocity, threats also braking at a_max, the own
vehicle's two-phase displacement): a line says what the escape believed, not what was flown.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import sys

import numpy as np

from mfg_autopilot.guidance import controller as _controller
from mfg_autopilot.presets import preset_by_name
from mfg_autopilot.safety import backstop as _backstop
from mfg_autopilot.safety import kernels as _kernels
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate


def _prepared(escape_args: tuple, escape_kwargs: dict) -> dict:
    """The arrays kernels.escape_rows hands to kernels.escape_candidates for this escape_acc call (the call repeated
    through the kernels' Python bodies, escape_candidates recorded)."""
    got = {}
    compiled_rows, compiled_cands = _kernels.escape_rows, _kernels.escape_candidates
    names = compiled_cands.py_func.__code__.co_varnames[:compiled_cands.py_func.__code__.co_argcount]

    def record(*a):
        got.update(zip(names, a))
        return compiled_cands(*a)

    _kernels.escape_rows, _kernels.escape_candidates = compiled_rows.py_func, record
    try:
        _backstop.escape_acc(*escape_args, **escape_kwargs)
    finally:
        _kernels.escape_rows, _kernels.escape_candidates = compiled_rows, compiled_cands
    return got


def candidate_table(p: dict, row: int) -> list[dict]:
    """One dict per first-phase candidate of active row `row` (its index among the active rows), in the escape's order
    (kernels.escape_candidates: safe candidates first by safe cost, then by cost)."""
    tube, tube_max = p["tube"], p["tube_max"]

    def seg(track, e_or_j, e, a1, a2):
        # the kernel's reading of one track, with the entry's tube (kernels._segment_eff_one; none: tube[e] = 0)
        return _kernels._segment_eff_one(track, e_or_j, alpha, beta, a1[0], a1[1], a2[0], a2[1], p["clear"][e],
                                         tube[e], tube_max, t_seg)

    ents = np.flatnonzero(p["e_row"] == row)
    a_nom, v_hat, side_r = p["a_nom_r"][row], p["v_hat"][row], p["side_r"][row]
    alpha, beta, t_seg, T1 = p["alpha"], p["beta"], p["t_seg"], p["rel"].shape[1]
    out = []
    for c in range(p["cand_fixed"].shape[0] + 1):
        a1 = a_nom if c == 0 else p["cand_fixed"][c - 1]
        phases = []
        for a2 in ((a_nom, np.zeros(2), -a1, a1) if p["two_phase"] else (a1,)):
            pen_sum, safe, worst = 0.0, True, (np.inf, -1, 0.0)
            for e in ents:
                dmin, k = seg(p["rel"], e, e, a1, a2)
                j = p["b_index"][e]
                if j >= 0:
                    db, kb = seg(p["rel_b"], j, e, a1, a2)
                    if db < dmin:
                        dmin, k = db, kb
                urg = p["tau_min_s"] / max(t_seg[k], p["tau_min_s"]) if p["urgency"] else 1.0
                x = max(0.0, p["clear"][e] / max(dmin, p["d_floor_m"]) - 1.0)
                pen = p["wgt"][e] * urg * x * x
                if p["hard_fraction"] > 0.0 and dmin < p["hard_fraction"] * p["clear"][e]:
                    safe = False
                if p["conflict"][e]:
                    d_end = alpha[T1 - 1] * a1 + beta[T1 - 1] * a2
                    pen += p["keep_right"] * max(0.0, float(p["left"][e] @ d_end)) / p["keep_right_den"]
                pen_sum += pen
                if dmin / p["clear"][e] < worst[0]:
                    worst = (dmin / p["clear"][e], int(e), float(t_seg[k]))
            phases.append({"pen": pen_sum, "safe": safe and p["hard_fraction"] > 0.0, "ratio": worst[0],
                           "entry": worst[1], "t_s": worst[2]})
        d = a1 - a_nom
        along = float(d @ v_hat)
        effort = p["effort_w"] * (along * along + p["lateral_cost"] * (float(d @ d) - along * along)) / p["a_max2"]
        side = p["side_w"] * max(0.0, -float(side_r @ a1)) / p["a_max"]
        pen = min(ph["pen"] for ph in phases)
        safe_pens = [ph["pen"] for ph in phases if ph["safe"]]
        pen_safe = min(safe_pens) if safe_pens else None
        out.append({"a1": np.array(a1, dtype=float), "along": float(a1 @ v_hat), "phases": phases, "pen": pen,
                    "pen_safe": pen_safe, "effort": effort, "side": side,
                    "key": (pen_safe is None, (pen_safe if pen_safe is not None else pen) + effort + side)})
    # (a stable sort: among equal costs the earlier candidate, as the kernel's strict '<')
    return sorted(out, key=lambda r: r["key"])


def _fmt(v) -> str:
    return "(" + ", ".join(f"{x:+.2f}" for x in np.asarray(v, dtype=float)) + ")"


def report(step: int, uav: int, args: tuple, kwargs: dict, a_out: np.ndarray, active: np.ndarray, top: int,
           radius_m: float) -> bool:
    """Print the UAV's table at this step; True if the table's first line is the command the kernel sent."""
    b = inspect.signature(_backstop.escape_acc).bind(*args, **kwargs).arguments
    own, a_nom, states, owner, threat, trig, clear = (b[k] for k in ("own", "a_nom", "sensed_states", "owner", "threat",
                                                                    "trigger_m", "clear_m"))
    hover, brake, tube = b.get("hover"), b.get("brake_hyp"), b.get("tube")
    print(f"step {step} (t = {step * b['commit_s']:g} s): UAV {uav} at {_fmt(own[uav, 0:2])} m, v {_fmt(own[uav, 2:4])} m/s, "
          f"a_nom {_fmt(a_nom[uav])} -> sent {_fmt(a_out[uav])} m/s^2")
    for e in np.flatnonzero((owner == uav) & threat):
        d = states[e, 0:2] - own[uav, 0:2]
        if np.hypot(*d) <= radius_m:
            print(f"  threat at {_fmt(d)} m ({np.hypot(*d):.2f} m), v {_fmt(states[e, 2:4])} m/s, trigger {trig[e]:.2f} m, "
                  f"clearance {clear[e]:.2f} m, hovering {bool(hover[e]) if hover is not None else False}, "
                  f"braking hypothesis {bool(brake[e]) if brake is not None else True}, "
                  f"tube {bool(tube[e]) if tube is not None else False}")
    p = _prepared(args, kwargs)
    row = int(np.count_nonzero(active[:uav]))
    table = candidate_table(p, row)
    names = ("a_nom", "0", "-a1", "a1") if p["two_phase"] else ("a1",)
    for r in table[:top]:
        ph = " ".join(f"[{n}: {x['pen']:.2f}{'S' if x['safe'] else 'u'} {x['ratio']:.2f}x at {x['t_s']:.1f} s]"
                      for n, x in zip(names, r["phases"]))
        ps = "-" if r["pen_safe"] is None else f"{r['pen_safe']:.3f}"
        print(f"  a1 {_fmt(r['a1'])} along {r['along']:+.2f}: penalty {r['pen']:.3f}, safe {ps}, effort {r['effort']:.3f}, "
              f"side {r['side']:.3f} | {ph}")
    sent = np.asarray(a_out[uav], dtype=float)
    mine = table[0]["a1"]
    ok = bool(np.allclose(mine * min(1.0, p["a_max"] / max(np.linalg.norm(mine), 1e-12)), sent, atol=1e-9))
    print("  the first line is the command the kernel sent" if ok else
          f"  the kernel sent {_fmt(sent)}, not the first line: this tool's arithmetic is out of date")
    return ok


def run(argv: list[str] | None = None) -> list[dict]:
    """Fly and print; returns one dict per step reported: {step, matches}."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--n", type=int, required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--uav", type=int, required=True, help="the UAV (row) whose escape is printed")
    ap.add_argument("--steps", required=True, help="comma-separated control steps")
    ap.add_argument("--fail-vehicle", type=int, default=None)
    ap.add_argument("--fail-at", type=float, default=20.0)
    ap.add_argument("--gust", action="store_true")
    ap.add_argument("--backstop", default="{}", help="JSON object: BackstopParams fields to change")
    ap.add_argument("--top", type=int, default=8, help="candidate lines per step")
    ap.add_argument("--radius-m", type=float, default=6.0, help="threats printed within this distance")
    a = ap.parse_args(argv)
    steps = sorted({int(s) for s in a.steps.split(",")})
    base = preset_by_name("default")
    preset = dataclasses.replace(base, backstop=dataclasses.replace(base.backstop, **json.loads(a.backstop)))
    kw = {} if a.fail_vehicle is None else {"fail_vehicle": a.fail_vehicle, "fail_at_s": a.fail_at}
    cfg = SimConfig(scenario=make_scenario(a.scenario, a.n, a.seed), mode="mfg", preset=preset, seed=a.seed,
                    steps=steps[-1] + 1, gust=GustParams() if a.gust else None, **kw)
    now = {"step": -1}
    done: list[dict] = []
    act, esc = _controller.DefaultMFGController.act, _controller.escape_acc

    def act_recording(self, obs):
        now["step"] = obs.step
        return act(self, obs)

    def esc_reporting(*args, **kwargs):
        a_out, active = esc(*args, **kwargs)
        st = now["step"]
        if st in steps and active[a.uav] and all(d["step"] != st for d in done):
            done.append({"step": st, "matches": report(st, a.uav, args, kwargs, a_out, active, a.top, a.radius_m)})
        return a_out, active

    _controller.DefaultMFGController.act, _controller.escape_acc = act_recording, esc_reporting
    try:
        simulate(cfg, progress=False)
    finally:
        _controller.DefaultMFGController.act, _controller.escape_acc = act, esc
    quiet = [s for s in steps if all(d["step"] != s for d in done)]
    if quiet:
        print(f"UAV {a.uav}'s escape was not active at step(s) {', '.join(map(str, quiet))}")
    return done


if __name__ == "__main__":
    out = run()
    sys.exit(0 if all(d["matches"] for d in out) else 1)
