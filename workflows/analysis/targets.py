"""The transport targets, checked on a comparison's ``summary.json``.

``pbmdem targets [results/reduced-*/summary.json]`` prints one line per target
with the number behind it and PASS / FAIL, and exits 1 if any fails. Every figure comes
from the summary that ``make full-comparison`` (``pbmdem compare``) writes:

* pooled RTD from >= 10 000 particles, >= 95 % of them recovered;
* the ``phases`` PBM (transport with memory): steady hold-up of every axial slice within
  10 % of the DEM's and the total inside its 95 % interval; mean residence time and RTD
  variance inside the DEM's 95 % intervals; RTD overlap >= 0.9 and inside its noise band;
  mean and variance change < 5 % between NX and 2 NX; refitted on the first half of the
  steady entries, the second half's pooled mean and variance inside their intervals;
* the VRR of feeder A for white noise and first-order noise of tau = 5 s and 20 s inside
  the DEM's 95 % intervals (feeder B's, and tau = 1 s, are printed as information);
* post-processing, and the phase fit within it, <= 5 % of the DEM's wall time.

The outlet RSD and Lacey index (composition) are printed for every mode, as information.

The ``measured`` and ``velocity`` PBMs are printed beside it for the same quantities;
their lines are information, not targets. A summary without the phase model (DEM results
made before the compartment sequences were recorded) fails the phases targets.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from dem.summary import DemSummary

#: the sections :func:`check` reads, each a JSON object when present
SECTIONS = ("dem_summary", "vrr", "nx_sensitivity", "memory", "provenance")


def read_summary(path: str | Path) -> dict[str, Any]:
    """The comparison summary in ``path`` as :func:`check` reads it: a JSON object whose
    ``agreement`` is a list of objects, each with a text ``key`` (and ``quantity``), numbers
    (or null: NaN) where the targets read numbers and true/false (or null: a mode that did
    not run) where they read verdicts, and whose other
    sections are objects. Raises ConfigError naming the file and the first field that is
    not so (a hand-edited or truncated file, another program's JSON)."""
    try:
        summary = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"{path}: not a readable summary ({exc})") from None

    def refuse(where: str, value: Any, valid: str) -> ConfigError:
        return ConfigError(
            f"{path}: {where} is {json.dumps(value)[:60]}; {valid} is valid (a summary.json of pbmdem compare)"
        )

    if not isinstance(summary, dict):
        raise refuse("the summary", summary, "a JSON object")
    for name in SECTIONS:
        if summary.get(name) is not None and not isinstance(summary[name], dict):
            raise refuse(f"'{name}'", summary[name], "an object")
    rows = summary.get("agreement")
    if rows is None:
        return summary
    if not isinstance(rows, list):
        raise refuse("'agreement'", rows, "a list of rows (objects)")
    for n, row in enumerate(rows):
        where = f"agreement[{n}]"
        if not isinstance(row, dict):
            raise refuse(where, row, "an object")
        for field, value in row.items():
            if field in ("key", "quantity"):
                ok, valid = isinstance(value, str), "a text"
            elif field.startswith("inside_"):  # null: the mode did not run
                ok, valid = value is None or isinstance(value, bool), "true, false or null"
            elif field == "dem" or field.startswith(("pbm_", "dem_ci_", "noise_")):  # null: NaN, as JSON writes it
                ok = value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
                valid = "a number or null"
            else:
                continue
            if not ok:
                raise refuse(f"{where}.{field}", value, valid)
        if "key" not in row:
            raise refuse(f"{where}.key", None, "a text")
    return summary


def checked(summary: dict[str, Any], source: str | Path) -> list[tuple[str, str, bool | None]]:
    """:func:`check` of a summary from :func:`read_summary`; a part nested deeper than it
    looks at that is not what a comparison writes (a VRR record without its interval, a
    hold-up of 0) raises ConfigError naming ``source`` and the part, not a traceback."""
    try:
        return check(summary)
    except (KeyError, TypeError, AttributeError, ValueError, IndexError, ZeroDivisionError) as exc:
        what = f"missing {exc}" if isinstance(exc, KeyError) else f"{type(exc).__name__}: {exc}"
        raise ConfigError(f"{source}: not a summary of pbmdem compare ({what})") from None


def _rows(summary: dict) -> dict[str, dict]:
    return {row["key"]: row for row in summary.get("agreement") or []}


#: (feeder, noise correlation times [s]) of the VRR target; the others are information
VRR_TARGET = ("A", (0.0, 5.0, 20.0))


def _vrr_lines(summary: dict, mode: str, target: bool | None) -> list[tuple[str, str, bool | None]]:
    """The feeder-noise VRR of ``mode`` against the DEM's intervals, per feeder: a target
    line for :data:`VRR_TARGET`, information for the rest."""
    feeders = (((summary.get("vrr") or {}).get("pbm") or {}).get(mode) or {}).get("feeders") or {}
    out = []
    for feeder, record in sorted(feeders.items()):
        noise = record.get("noise") or []
        for part in ("target", "other"):
            chosen = [
                n for n in noise if (feeder == VRR_TARGET[0] and n["tau_s"] in VRR_TARGET[1]) == (part == "target")
            ]
            if not chosen:
                continue
            numbers = ", ".join(
                f"tau {n['tau_s']:g} s: {n['vrr']:.2f} vs DEM [{n['dem']['low']:.2f}, {n['dem']['high']:.2f}]"
                for n in chosen
            )
            passed = all(bool(n["inside"]) for n in chosen)
            out.append(
                (
                    f"{mode}: VRR of feeder {feeder} inside the DEM intervals"
                    + ("" if part == "target" else " (information)"),
                    numbers,
                    passed if (target and part == "target") else None,
                )
            )
    return out


def _out_of_sample_line(summary: dict) -> tuple[str, str, bool]:
    """The phase model refitted on the first half of the steady entries against the DEM's
    RTD of the second half (``memory.out_of_sample``); a summary without it fails, saying why."""
    name = (
        "phases: out of sample (refitted on the first half), the second half's mean and variance inside its intervals"
    )
    memory = summary.get("memory") or {}
    held = memory.get("out_of_sample")
    if not held:
        return name, memory.get("out_of_sample_note") or "no out-of-sample check in the summary", False
    m, v = held["dem_mean_s"], held["dem_variance_s2"]
    numbers = (
        f"mean {held['pbm_mean_s']:.2f} vs DEM {m['value']:.2f} [{m['low']:.2f}, {m['high']:.2f}], "
        f"variance {held['pbm_variance_s2']:.4g} vs DEM {v['value']:.4g} [{v['low']:.4g}, {v['high']:.4g}]"
    )
    return name, numbers, bool(held["mean_inside"]) and bool(held["variance_inside"])


def check(summary: dict) -> list[tuple[str, str, bool | None]]:
    """(target, the numbers, passed) for every target; passed None = information only."""
    rows = _rows(summary)
    dem = DemSummary.from_record(summary.get("dem_summary") or {})
    pooled = dem.pooled_rtd
    out: list[tuple[str, str, bool | None]] = []
    n = pooled.n_entered if pooled is not None else 0
    rec = pooled.recovered_fraction.value if pooled is not None and pooled.recovered_fraction else math.nan
    out.append(
        (
            "pooled RTD from >= 10 000 particles, >= 95 % recovered",
            f"{n} entered, {rec:.3f} recovered",
            n >= 10_000 and rec >= 0.95,
        )
    )
    for mode, target in (("phases", True), ("measured", None), ("velocity", None)):
        if not any(f"pbm_{mode}" in r for r in rows.values()):
            out.append(
                (
                    f"{mode}: the PBM ran in this mode",
                    "no such column in the agreement table",
                    False if target else None,
                )
            )
            continue
        slices = [r for k, r in rows.items() if k.startswith("holdup_slice_")]
        if slices:
            errors = [r[f"pbm_{mode}"] / r["dem"] - 1 for r in slices]
            worst = max(errors, key=abs)
            out.append(
                (
                    f"{mode}: every slice's hold-up within 10 % of the DEM",
                    "errors " + ", ".join(f"{e:+.0%}" for e in errors),
                    (abs(worst) <= 0.10) if target else None,
                )
            )
        for key in ("mean_residence_time_s", "rtd_variance_s2", "holdup"):
            r = rows.get(key)
            if r:
                out.append(
                    (
                        f"{mode}: {r['quantity']} inside the DEM interval",
                        f"{r[f'pbm_{mode}']:.4g} vs DEM {r['dem']:.4g} [{r['dem_ci_low']:.4g}, {r['dem_ci_high']:.4g}]",
                        bool(r[f"inside_{mode}"]) if target else None,
                    )
                )
        r = rows.get("rtd_overlap")
        if r:
            value, low = r[f"pbm_{mode}"], r.get(f"noise_low_{mode}", math.nan)
            out.append(
                (
                    f"{mode}: RTD overlap >= 0.9 and inside its noise band",
                    f"{value:.3f} (noise band low {low:.3f}, median {r.get(f'noise_median_{mode}', math.nan):.3f})",
                    (value >= 0.9 and value >= low) if target else None,
                )
            )
        for key in ("rsd_outlet", "lacey_outlet"):
            r = rows.get(key)
            if r:
                out.append(
                    (
                        f"{mode}: {r['quantity']} inside the DEM interval",
                        f"{r[f'pbm_{mode}']:.3f} vs DEM {r['dem']:.3f} [{r['dem_ci_low']:.3f}, {r['dem_ci_high']:.3f}]",
                        None,
                    )
                )
        out.extend(_vrr_lines(summary, mode, target))
        sens = (summary.get("nx_sensitivity") or {}).get(mode)
        if sens:
            nx = summary["nx_sensitivity"]["nx"]
            out.append(
                (
                    f"{mode}: mean and variance change < 5 % from NX = {nx[0]} to {nx[1]}",
                    f"mean {sens['change_mean']:+.1%}, variance {sens['change_variance']:+.1%}",
                    (abs(sens["change_mean"]) < 0.05 and abs(sens["change_variance"]) < 0.05) if target else None,
                )
            )
    if any("pbm_phases" in r for r in rows.values()):
        out.append(_out_of_sample_line(summary))
    prov = summary.get("provenance") or {}
    dem_s, post_s = prov.get("dem_wall_time_s"), prov.get("dem_postprocess_time_s")
    if dem_s and post_s:
        out.append(
            (
                "post-processing <= 5 % of the DEM wall time",
                f"{post_s:.1f} s / {dem_s:.0f} s = {post_s / dem_s:.2%}",
                post_s / dem_s <= 0.05,
            )
        )
    fit_s = (dem.extra.get("phase_fit") or {}).get("wall_time_s")
    if dem_s and fit_s:
        out.append(
            (
                "phase fit <= 5 % of the DEM wall time",
                f"{fit_s:.1f} s / {dem_s:.0f} s = {fit_s / dem_s:.2%}",
                fit_s / dem_s <= 0.05,
            )
        )
    return out
