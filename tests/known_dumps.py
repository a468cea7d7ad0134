"""Known dumps and configs the tests share: a synthetic blender with a known flow.

The synthetic blender (L = 0.33 m, D = 0.1 m, 4 x 2 compartments, dumps every 0.5 s to
30 s): at every dump after t = 0 one A particle (y = +0.02) and one B particle (y = -0.02)
appear at the inlet. A particles cross the blender in R_A = 4 s, B particles in R_B = 6 s
(x = L (age + 0.25) / R, never on a compartment edge); each is seen once past the weir
(x = L + 0.01) at age R and is gone at the next dump. vx = 0.1 (i + 1) m/s in slice i,
vy = +0.02 (A) or -0.03 (B) m/s. The hold-up is 4 t until 4 s, 18 at 5 s and 20 from 6 s.
"""

import math

import numpy as np

from coupling.metrics import SteadyStateRule
from dem.config import DemConfig, TablesConfig
from dem.dumps import format_snapshot
from workflows.config import config_from_dict

L, D = 0.330, 0.100
DUMP_S, END_S = 0.5, 30.0


COLUMNS = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")


# Windows of 3 s: the synthetic run is 30 s long. Means over (3, 6] and (6, 9] are 18 and
# 20 (10 % apart), over (7, 10] and (4, 7]: 20 and 19.33 (3.3 %): steady at 10 s.
STEADY = SteadyStateRule(window_s=3.0, rel_tol=0.05)


R = {1: 4.0, 2: 6.0}


def config():
    return DemConfig(tables=TablesConfig(nx=4, ny=2, window_s=5.0, sample_interval_s=1.0, min_samples=1))


def write_synthetic(directory, cfg, vanish_unseen=False, lose_id=None, end_s=END_S):
    """Write the synthetic dumps; returns {id: (type, entry_s, exit_s)}.

    ``vanish_unseen``: particles are deleted before any dump sees them past the weir (as by
    an outlet face between two dumps): last seen in the last slice, then gone.
    ``lose_id``: this particle vanishes at t = 10 s in the middle of the blender (lost)."""
    dt = cfg.timestep_s
    directory.mkdir(parents=True, exist_ok=True)
    particles = {}
    n_dumps = int(round(end_s / DUMP_S))
    for k in range(1, n_dumps + 1):
        for ptype in (1, 2):
            particles[2 * k - 2 + ptype] = (ptype, k * DUMP_S)
    truth = {}
    for k in range(n_dumps + 1):
        t = k * DUMP_S
        rows = []
        for pid, (ptype, entry) in particles.items():
            age = t - entry
            if age < -1e-9:
                continue
            if lose_id == pid and t >= 10.0 - 1e-9:
                continue
            res = R[ptype]
            if age > res + 1e-9:
                continue
            if abs(age - res) < 1e-9:
                if vanish_unseen:
                    continue
                x = L + 0.01
            else:
                x = L * (age + 0.25) / res
            i = min(int(x / (L / 4)), 3)
            rows.append(
                (
                    pid,
                    ptype,
                    x,
                    0.02 if ptype == 1 else -0.02,
                    0.0,
                    0.1 * (i + 1),
                    0.02 if ptype == 1 else -0.03,
                    0.0,
                    0.003,
                )
            )
        step = int(round(t / dt))
        (directory / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, np.array(rows).reshape(-1, 9)))
    for pid, (ptype, entry) in particles.items():
        exit_s = entry + R[ptype]
        truth[pid] = (ptype, entry, exit_s if exit_s <= end_s + 1e-9 else math.nan)
    return truth


def variant(config, **sections):
    """A copy of ``config`` with some ``dem.<section>`` values changed."""
    data = config.to_dict()
    for section, values in sections.items():
        data["dem"][section].update(values)
    return config_from_dict(data)
