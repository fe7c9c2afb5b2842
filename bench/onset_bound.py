"""The closest any controller can keep the UAV right behind a vehicle that fails into Hold (mfg_swarm/limits.py).

    .venv/bin/python bench/onset_bound.py [--v 4] [--a-max 2] [--a-brake 2] [--jerk 4]

Prints, for the Hold's braking (at once: ``sim --hold-jerk 0``; built up at PX4's MPC_JERK_AUTO: the default), the
reaction delay (0 to two of the default controller's 0.5 s control periods) and the gap to the failed vehicle
in the lane (the 1.41 m lattice of paper / crossing / swap4 / circle, the 1.4 m cruise of the spread dense pad, 2 m),
the largest smallest distance over any acceleration of norm a_max (best constant direction and best piecewise-constant
one), against half the start spacing that issue 18 asks for; then, per reaction delay, the smallest gap in the lane
at which half the 1.41 m spacing can be kept (``gap_needed_m``); then, behind PX4's Hold in the 1.41 m lattice, the
best clearance per reaction delay up to 1.2 s, the longest delay that keeps half the spacing and the longest that
keeps the 0.1 m collision distance (``longest_delay_s``), and what that leaves a controller sampling every 0.5 s: it
reacts up to its detection's age + 0.5 s after a failure at an arbitrary instant.
"""

from __future__ import annotations

import argparse

import numpy as np

from mfg_swarm.limits import _best_constant_m, follower_best_clearance_m, gap_needed_m, longest_delay_s


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--v", type=float, default=4.0, help="stream speed, m/s")
    ap.add_argument("--a-max", type=float, default=2.0, help="the follower's acceleration limit, m/s^2")
    ap.add_argument("--a-brake", type=float, default=2.0, help="the failed vehicle's braking in Hold, m/s^2")
    ap.add_argument("--jerk", type=float, default=4.0, help="PX4's Hold builds its braking up at this, m/s^3 (MPC_JERK_AUTO)")
    a = ap.parse_args(argv)
    print("| Hold's braking | gap in the lane (m) | delay (s) | best constant direction: clearance (m), direction (deg) | best piecewise (m) | half the 1.41 m spacing |")
    print("|---|---|---|---|---|---|")
    for jerk in (None, a.jerk):
        hold = "at once" if jerk is None else f"{jerk:g} m/s^3"
        for gap in (np.sqrt(2.0), 2.0):
            for delay in (0.0, 0.25, 0.5, 1.0):
                r = follower_best_clearance_m(v_m_s=a.v, gap_m=gap, delay_s=delay, a_brake_m_s2=a.a_brake,
                                              a_max_m_s2=a.a_max, jerk_m_s3=jerk)
                print(f"| {hold} | {gap:.2f} | {delay:.2f} | {r['constant_m']:.3f}, {r['direction_deg']:.0f} | {r['piecewise_m']:.3f} | "
                      f"{'kept' if r['piecewise_m'] >= np.sqrt(2.0) / 2 else 'not reachable'} |")
    print()
    print("| reaction delay (s) | gap in the lane needed for half the 1.41 m spacing, Hold at once (m) | the same, PX4's Hold (m) |")
    print("|---|---|---|")
    for delay in (0.5, 1.0, 1.5):
        g = [gap_needed_m(np.sqrt(2.0) / 2, delay, v_m_s=a.v, a_brake_m_s2=a.a_brake, a_max_m_s2=a.a_max, jerk_m_s3=j)
             for j in (None, a.jerk)]
        print(f"| {delay:.1f} | {g[0]:.2f} | {g[1]:.2f} |")
    print()
    gap, period = np.sqrt(2.0), 0.5
    print("| reaction delay (s) | best clearance behind PX4's Hold, 1.41 m gap (m) |")
    print("|---|---|")
    for delay in np.arange(0.5, 1.201, 0.1):
        c = _best_constant_m(gap, round(delay, 2), a.v, a.a_brake, a.a_max, a.jerk, 0.05, 8.0)
        print(f"| {delay:.1f} | {c:.3f} |")
    print()
    for name, clearance in (("half the 1.41 m spacing", gap / 2), ("the 0.1 m collision distance", 0.1)):
        d = longest_delay_s(clearance, gap, v_m_s=a.v, a_brake_m_s2=a.a_brake, a_max_m_s2=a.a_max, jerk_m_s3=a.jerk)
        tau = d - period
        lost = 0.5 * a.jerk * tau * tau if tau <= a.a_brake / a.jerk else (
            0.5 * a.a_brake ** 2 / a.jerk + a.a_brake * (tau - a.a_brake / a.jerk))
        print(f"- {name}: reaction within {d:.2f} s of the failure; sampling every {period} s, the Hold must be flagged "
              f"once it has lasted {tau:.2f} s (it has lost {lost:.3f} m/s of its speed then)")


if __name__ == "__main__":
    main()
