"""Transport with memory, measured: hidden-phase chains fitted to a DEM run's compartment
sequences, and the PBM built on each, against the DEM's RTD and hold-up.

``phase_study(results, ...)`` returns a :class:`PhaseStudy`; :func:`markdown` renders it. Needs DEM
results made with the compartment sequences (``pbmdem dem post`` or ``dem run`` from this
version on; the sequences are stored in the results file, so no dumps are needed).

For every grid (NX x NY, a coarsening of the run's) and number of phases K:

1. fit on every particle first seen after the steady-state time (:class:`dem.phases.PhaseEstimator`,
   the product's :class:`dem.phases.PhaseSettings` unless the command line says otherwise);
2. held out: fit on those first seen in the first half of that period, score the second
   half (log-likelihood per particle-step: higher is better; comparable across K on the
   same grid only);
3. Chapman-Kolmogorov test of the full fit at 1, 2, 5 and 10 s (:class:`dem.phases.CkTest`);
4. the PBM in mode "phases" on a table carrying the model, fed like the DEM
   (:func:`workflows.pipeline.pbm_config_for`): the pooled RTD over the DEM's entry window
   and horizon (:func:`pbm.rtd.pooled_rtd`) and the steady hold-up per axial slice
   (:func:`pbm.simulate.simulate`), against the DEM's values and 95 % intervals.

The DEM's targets come from a results summary (``target``, default the run's own): a
fresh run too short for its own pooled RTD is judged against a complete run of the same
deck.

Reproduce (a run directory with its dumps, ``runs/<key>``)::

    pbmdem dem post --preset validation --dumps 'runs/<key>/dumps/dump.*.txt' --out-file dem.h5
    pbmdem study phases --results dem.h5 --grids 10x1,10x10 --ks 1,2,3

and for NX = 20 the same post-processing with ``[dem.tables] nx = 20`` in a ``--config``
file, then ``--grids 20x1``. ``--stagnant R`` makes phase 0 of every K >= 2 a dead zone
(:attr:`dem.phases.PhaseSettings.stagnant_exit_max_per_s`, at one over R times the run's Little's-law
mean residence time: a particle parked there stays R residence times or more; R = 1 bare).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coupling.cache import try_load_entry
from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.jsonable import write_json
from coupling.tables import make_table
from dem import phases
from dem.post import DemResults
from dem.summary import DemSummary, Estimate
from pbm.rtd import pooled_rtd
from pbm.simulate import simulate
from workflows.analysis.agreement import steady_outputs
from workflows.config import Config
from workflows.pipeline.results import config_of, pbm_config_for


@dataclass(frozen=True)
class Interval:
    value: float
    low: float
    high: float

    def inside(self, x: float) -> bool:
        return bool(self.low <= x <= self.high)


@dataclass(frozen=True)
class DemTarget:
    """The DEM's pooled RTD (mean [s], variance [s^2]), its entry window and horizon [s],
    the steady hold-up per axial slice and in total [particles], each with its 95 %
    interval; ``source`` says which results they come from."""

    mean_s: Interval
    variance_s2: Interval
    entry_window_s: tuple[float, float]
    horizon_s: float
    holdup_by_slice: tuple[Interval, ...]
    holdup: Interval
    steady_time_s: float
    source: str
    little_mean_residence_time_s: float = float("nan")


def _interval(estimate: Estimate) -> Interval:
    return Interval(float(estimate.value), float(estimate.low), float(estimate.high))


def dem_target(summary: DemSummary, source: str) -> DemTarget:
    """:class:`DemTarget` from a DEM results summary; ConfigError naming ``source`` when
    the run has no pooled RTD or no steady hold-up to judge against."""
    steady = summary.steady
    if not summary.has_pooled_rtd or "holdup" not in steady or "holdup_by_slice" not in steady:
        raise ConfigError(
            f"{source}: the DEM run has no pooled RTD or no steady hold-up to judge the models against; "
            "give --target a complete run of the same deck"
        )
    pooled, by_slice = summary.pooled_rtd, steady["holdup_by_slice"]
    return DemTarget(
        mean_s=_interval(pooled.mean_residence_time_s),
        variance_s2=_interval(pooled.rtd_variance_s2),
        entry_window_s=tuple(float(v) for v in pooled.entry_window_s),
        horizon_s=float(pooled.horizon_s),
        holdup_by_slice=tuple(
            Interval(v, lo, hi) for v, lo, hi in zip(by_slice["value"], by_slice["low"], by_slice["high"])
        ),
        holdup=_interval(Estimate.from_record(steady["holdup"])),
        steady_time_s=float(summary.steady_state_time_s),
        source=source,
        little_mean_residence_time_s=float(steady.get("little_mean_residence_time_s", {}).get("value", float("nan"))),
    )


@dataclass(frozen=True)
class ModelResult:
    """One (grid, K): the fit, its held-out score, its CK test and its PBM's numbers.

    ``slice_error``: PBM / DEM - 1 per axial slice; ``timescales_s``: the three longest
    implied timescales; ``start_spread``: best minus worst final log-likelihood over the
    starts [nats]; ``entry``: entry-phase distribution (rows A, B), phases slowest first."""

    grid: tuple[int, int]
    n_phases: int
    n_parameters: int
    log_likelihood_per_step: float
    held_out_per_step: float
    ck_max_z: float
    ck_max_abs_error: float
    ck_passed: bool
    mean_s: float
    variance_s2: float
    recovered_fraction: float
    holdup: float
    slice_error: tuple[float, ...]
    timescales_s: tuple[float, ...]
    fit_wall_s: float
    iterations: int
    converged: bool
    start_spread: float
    entry: tuple[tuple[float, ...], ...]
    #: with a stagnant phase (``--stagnant``): its share of the hold-up, the rate at which
    #: it is left (weighted by where it holds particles) [1/s] and the slices holding most
    stagnant_share: float = float("nan")
    stagnant_exit_per_s: float = float("nan")
    stagnant_slices: tuple[int, ...] = ()

    def worst_slice_error(self) -> float:
        return float(max(self.slice_error, key=abs))


@dataclass(frozen=True)
class PhaseStudy:
    target: DemTarget
    results: tuple[ModelResult, ...]
    fit_window_s: tuple[float, float]
    n_particles: int
    n_steps: int
    dem_wall_time_s: float
    parked: ParkedTracers | None = None


def phase_table(model, length_m: float, diameter_m: float, t_end_s: float, window_s: float = 5.0):
    """A time-invariant table on the model's grid that carries only the phase model (its
    velocities are never read in mode "phases")."""
    return make_table(
        np.arange(0.0, t_end_s, window_s),
        np.linspace(0.0, length_m, model.nx + 1),
        np.linspace(-diameter_m / 2, diameter_m / 2, model.ny + 1),
        0.0,
        0.0,
        0.0,
        0.0,
        window_s=window_s,
    ).replace(phases=model)


def pbm_numbers(model, config: Config, target: DemTarget) -> dict[str, Any]:
    """The PBM (mode "phases") on ``model``: pooled RTD over the target's entry window and
    horizon, steady hold-up per slice as the comparison takes it (the mean after the
    PBM's own steady-state time, :func:`workflows.analysis.agreement.steady_outputs`: one rule,
    each side on its own curve). A chain that fills more slowly than the DEM is still short
    of its stationary hold-up at the DEM's steady time."""
    g = config.dem.geometry
    t_end = target.entry_window_s[1] + target.horizon_s + 5.0
    table = phase_table(model, float(g.length_m), float(g.diameter_m), t_end)
    pbm_config = pbm_config_for(config, table, None).model_copy(update={"rates": "phases", "duration_s": t_end})
    rtd = pooled_rtd(table, pbm_config, target.entry_window_s, target.horizon_s)
    result = simulate(table, pbm_config)
    by_slice = result.counts[steady_outputs(result)].sum(axis=(1, 3)).mean(axis=0)
    return {
        "mean_s": rtd.mean_s,
        "variance_s2": rtd.variance_s2,
        "recovered_fraction": rtd.recovered_fraction,
        "density_per_s": rtd.recovered_density_per_s,
        "by_slice": by_slice,
        "holdup": float(by_slice.sum()),
    }


def evaluate(
    sequences,
    config: Config,
    target: DemTarget,
    grid: tuple[int, int],
    fit_window,
    settings: phases.PhaseSettings,
    residents: bool = True,
    observed_nx: int | None = None,
    stagnant: float | None = None,
) -> ModelResult:
    """One row of the study (module docstring): the K = ``settings.n_phases`` chain fitted
    with ``settings``, observed every ``settings.lag_s``. ``residents``: fit also
    to the moves of the particles already inside when the window opens
    (:func:`dem.phases.prepare`); the held-out particles are only those that enter in the
    second half, the held-out fit one start of the same settings. The held-out score and
    the CK test read the same observations, the CK test at 1, 2, 5 and 10 s.
    ``observed_nx``: fit the chain on ``grid`` (NY = 1) to the observations on this many
    axial slices (:attr:`dem.phases.PhaseSettings.refine`); it is scored and CK-tested on
    its own grid. ``stagnant`` = R: phase 0 of a K >= 2 chain is a dead zone left at most
    once per R of the target's Little's-law mean residence times."""
    t0, t1 = fit_window
    lag = settings.lag_dumps(sequences.interval_s)
    data = phases.prepare(sequences, (t0, t1), grid, residents=residents, lag=lag)
    observed, refine = grid, 1
    if observed_nx is not None:
        if grid[1] != 1 or observed_nx < 1 or grid[0] % observed_nx:
            raise ConfigError(f"--observed-nx {observed_nx}: must divide the grid's NX {grid[0]}, with NY = 1")
        observed, refine = (observed_nx, 1), grid[0] // observed_nx
    settings = dataclasses.replace(settings, refine=refine)
    if stagnant is not None and settings.n_phases >= 2:
        if not target.little_mean_residence_time_s > 0:
            raise ConfigError(f"{target.source}: no Little's-law mean residence time to bound a stagnant phase by")
        exit_max = 1.0 / (stagnant * target.little_mean_residence_time_s)
        settings = dataclasses.replace(settings, stagnant_exit_max_per_s=exit_max)
    fit_data = data if refine == 1 else phases.prepare(sequences, (t0, t1), observed, residents=residents, lag=lag)
    wall0 = time.perf_counter()
    fit = phases.PhaseEstimator(settings).fit(fit_data).fetch_model()
    wall = time.perf_counter() - wall0
    middle = 0.5 * (t0 + t1)
    train = phases.prepare(sequences, (t0, middle), observed, residents=residents, lag=lag)
    test = phases.prepare(sequences, (middle, t1), grid, lag=lag)
    held = phases.PhaseEstimator(dataclasses.replace(settings, starts=1)).fit(train).fetch_model()
    ck = fit.chapman_kolmogorov(data, tuple(max(1, round(v / data.interval_s)) for v in (1.0, 2.0, 5.0, 10.0)))
    pbm = pbm_numbers(fit.transport, config, target)
    # slice hold-ups: the DEM's are on 10 slices; a coarser or finer PBM grid is compared
    # after summing onto the coarser of the two
    dem_slices = np.array([s.value for s in target.holdup_by_slice])
    pbm_slices = pbm["by_slice"]
    n = min(dem_slices.size, pbm_slices.size)
    dem_c = dem_slices.reshape(n, -1).sum(axis=1)
    pbm_c = pbm_slices.reshape(n, -1).sum(axis=1)
    lls = fit.start_log_likelihoods
    stagnant_numbers = {} if settings.stagnant_exit_max_per_s is None else _stagnant_numbers(fit)
    return ModelResult(
        grid=grid,
        n_phases=settings.n_phases,
        n_parameters=fit.n_parameters(),
        log_likelihood_per_step=fit.log_likelihood / data.n_steps,
        held_out_per_step=held.score(test) / test.n_steps,
        ck_max_z=ck.max_z(),
        ck_max_abs_error=ck.max_abs_error(),
        ck_passed=ck.passed,
        mean_s=pbm["mean_s"],
        variance_s2=pbm["variance_s2"],
        recovered_fraction=pbm["recovered_fraction"],
        holdup=pbm["holdup"],
        slice_error=tuple(float(v) for v in pbm_c / dem_c - 1.0),
        timescales_s=tuple(float(v) for v in fit.implied_timescales(3)),
        fit_wall_s=wall,
        iterations=fit.iterations,
        converged=fit.converged,
        start_spread=float(max(lls) - min(lls)),
        entry=tuple(tuple(float(v) for v in row) for row in fit.entry_distribution()),
        **stagnant_numbers,
    )


def _stagnant_numbers(fit) -> dict[str, Any]:
    """:class:`ModelResult`'s stagnant fields of a fit whose phase 0 is stagnant."""
    held = fit.occupancy[0].sum(axis=1)  # (NX,) time the stagnant phase holds per slice
    leave = fit.transport.switching[0].sum(axis=0).sum(axis=1) / fit.transport.ny  # (NX,) mean over y
    return {
        "stagnant_share": float(held.sum() / fit.occupancy.sum()),
        "stagnant_exit_per_s": float((leave * held).sum() / max(held.sum(), 1e-300)),
        "stagnant_slices": tuple(int(i) for i in np.flatnonzero(held >= 0.1 * held.max())),
    }


@dataclass(frozen=True)
class ParkedTracers:
    """The DEM's pooled-RTD tracers still inside at the horizon: how many of how many
    entered, and for each its longest stay in one axial slice without leaving it [s] and
    that slice."""

    n_entered: int
    n_beyond: int
    longest_stay_s: tuple[float, ...]
    slice_of_stay: tuple[int, ...]


def parked_tracers(
    sequences, entry_s: np.ndarray, exit_s: np.ndarray, ids: np.ndarray, entry_window_s, horizon_s: float
) -> ParkedTracers:
    """:class:`ParkedTracers` of the particles (``ids`` with their ``entry_s`` and
    ``exit_s``, NaN while inside) that entered in ``entry_window_s`` = (t0, t1] and had
    not left ``horizon_s`` later, read off their compartment ``sequences``."""
    t0, t1 = entry_window_s
    entered = (entry_s > t0) & (entry_s <= t1)
    beyond = entered & ~(exit_s - entry_s <= horizon_s)
    rows = np.flatnonzero(np.isin(sequences.ids, ids[beyond]))
    stays, where = [], []
    for states in sequences.states(rows):
        slices = states[states < sequences.n_cells] // sequences.ny
        change = np.flatnonzero(np.diff(slices) != 0)
        starts = np.concatenate([[0], change + 1])
        lengths = np.diff(np.concatenate([starts, [slices.size]]))
        longest = int(np.argmax(lengths))
        stays.append(float(lengths[longest] * sequences.interval_s))
        where.append(int(slices[starts[longest]]))
    return ParkedTracers(int(entered.sum()), int(beyond.sum()), tuple(stays), tuple(where))


def phase_study(
    results: str | Path,
    target: str | Path | None = None,
    grids=((10, 10), (10, 1)),
    ks=(1, 2, 3),
    settings: phases.PhaseSettings | None = None,
    fit_window_s: tuple[float, float] | None = None,
    target_override: DemTarget | None = None,
    residents: bool = True,
    log=print,
    observed_nx: int | None = None,
    stagnant: float | None = None,
) -> PhaseStudy:
    """The study on the DEM results file ``results`` (with sequences), judged against the
    DEM results ``target`` (default the same file) or ``target_override``. The fit window
    defaults to (the target's steady-state time, the last dump]. Every fit is ``settings``'
    (default the product's, :class:`dem.phases.PhaseSettings`) with K each of ``ks``."""
    settings = phases.PhaseSettings() if settings is None else settings
    variants = [dataclasses.replace(settings, n_phases=k) for k in ks]  # refused before any fit
    entry, reason = try_load_entry(Path(results))
    if entry is None:
        raise ConfigError(f"results {results}: {reason}")
    dem = DemResults.from_cache_entry(entry)
    if dem.sequences is None:
        raise ConfigError(
            f"results {results} hold no compartment sequences: post-process the run's dumps again "
            "with this version (pbmdem dem post)"
        )
    config = config_of(entry)
    if target_override is None:
        target_entry, why = (entry, None) if target is None else try_load_entry(Path(target))
        if target_entry is None:
            raise ConfigError(f"--target {target}: {why}")
        goal = dem_target(DemSummary.from_record(target_entry.summary), str(target or results))
    else:
        goal = target_override
    seq = dem.sequences
    last = float(seq.snapshot_t[-1])
    window = fit_window_s or (goal.steady_time_s, last)
    window = (float(window[0]), min(float(window[1]), last))  # a run still going ends at its last dump
    data = phases.prepare(seq, window, residents=residents, lag=settings.lag_dumps(seq.interval_s))
    out = []
    for grid in grids:
        for variant in variants:
            row = evaluate(seq, config, goal, tuple(grid), window, variant, residents, observed_nx, stagnant)
            log(
                f"{grid[0]}x{grid[1]} K={variant.n_phases}: mean {row.mean_s:.2f} s, variance {row.variance_s2:.1f} s^2, "
                f"worst slice {row.worst_slice_error():+.1%}, held-out {row.held_out_per_step:.4f}, "
                f"CK max z {row.ck_max_z:.1f}, fit {row.fit_wall_s:.0f} s"
                + (
                    f"; stagnant phase: {row.stagnant_share:.1%} of the hold-up, in slices "
                    f"{list(row.stagnant_slices)}, left at {row.stagnant_exit_per_s:.3f} /s"
                    if row.stagnant_slices
                    else ""
                )
            )
            out.append(row)
    # the run's own tracers: a --target's entry window is another run's
    pooled, records = dem.summary.pooled_rtd, dem.particles
    parked = (
        parked_tracers(
            seq,
            records["entry_t_s"].to_numpy(float),
            records["exit_t_s"].to_numpy(float),
            records["id"].to_numpy(),
            pooled.entry_window_s,
            pooled.horizon_s,
        )
        if pooled is not None and pooled.has_tracers
        else None
    )
    return PhaseStudy(
        goal,
        tuple(out),
        tuple(window),
        data.n_particles,
        data.n_steps,
        float(entry.provenance.get("wall_time_s", float("nan"))),
        parked,
    )


def markdown(study: PhaseStudy) -> str:
    """The study as a markdown table (✓ inside the DEM's 95 % interval)."""
    g = study.target

    def mark(ok: bool) -> str:
        return "✓" if ok else "✗"

    lines = [
        f"DEM ({g.source}): mean {g.mean_s.value:.2f} s [{g.mean_s.low:.2f}, {g.mean_s.high:.2f}], variance "
        f"{g.variance_s2.value:.0f} s² [{g.variance_s2.low:.0f}, {g.variance_s2.high:.0f}], hold-up "
        f"{g.holdup.value:.0f} [{g.holdup.low:.0f}, {g.holdup.high:.0f}]; fit window {study.fit_window_s[0]:.1f}-"
        f"{study.fit_window_s[1]:.1f} s, {study.n_particles} particles, {study.n_steps} particle-steps",
        *_parked_lines(study.parked),
        "",
        "| grid | K | mean [s] | variance [s²] | hold-up | worst slice | held-out ll/step | CK max z | fit [s] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in study.results:
        lines.append(
            f"| {r.grid[0]}×{r.grid[1]} | {r.n_phases} | {r.mean_s:.2f} {mark(g.mean_s.inside(r.mean_s))} | "
            f"{r.variance_s2:.0f} {mark(g.variance_s2.inside(r.variance_s2))} | "
            f"{r.holdup:.0f} {mark(g.holdup.inside(r.holdup))} | {r.worst_slice_error():+.1%} | "
            f"{r.held_out_per_step:.4f} | {r.ck_max_z:.1f} {mark(r.ck_passed)} | {r.fit_wall_s:.0f} |"
        )
    return "\n".join(lines)


def _parked_lines(parked: ParkedTracers | None) -> list[str]:
    if parked is None or not parked.n_entered:
        return []
    line = (
        f"the run's own pooled-RTD tracers still inside at the horizon: {parked.n_beyond} of {parked.n_entered} "
        f"({parked.n_beyond / parked.n_entered:.2%})"
    )
    if parked.n_beyond:
        slices = np.bincount(parked.slice_of_stay)
        line += (
            f"; their longest stay in one slice {min(parked.longest_stay_s):.0f}-{max(parked.longest_stay_s):.0f} s, "
            "in slices " + ", ".join(f"{i} ({n})" for i, n in enumerate(slices) if n)
        )
    return [line]


def record(study: PhaseStudy) -> dict[str, Any]:
    """The study as ``phases.json`` holds it."""
    return asdict(study)


# ----------------------------------------------------------------------------- continuous vs discrete time
@dataclass(frozen=True)
class TimeComparison:
    """Continuous-time generator vs discrete-time chain at the dump interval, same data,
    grid and K: log-likelihoods per particle-step and free parameters of each; the RTD
    (mean [s], variance [s^2], within the target's horizon) of the continuous model's PBM,
    of the discrete chain itself (exact at the dump interval, exit at the mid-interval) and
    of the PBM on the discrete chain's projected logarithm (what it becomes as a generator)."""

    grid: tuple[int, int]
    n_phases: int
    continuous_ll_per_step: float
    continuous_parameters: int
    discrete_ll_per_step: float
    discrete_parameters: int
    continuous_rtd: tuple[float, float]
    discrete_rtd: tuple[float, float]
    projected_rtd: tuple[float, float]
    continuous_wall_s: float
    discrete_wall_s: float


def discrete_rtd(transition: np.ndarray, start: np.ndarray, interval_s: float, horizon_s: float) -> tuple[float, float]:
    """Mean and variance of the time to absorption of the chain ``transition`` from the
    distribution ``start`` over its transient states, truncated at ``horizon_s``."""
    v = np.append(start, 0.0)
    absorbed = [0.0]
    for _ in range(int(round(horizon_s / interval_s))):
        v = v @ transition
        absorbed.append(v[-1])
    density = np.diff(absorbed)
    t = (np.arange(density.size) + 0.5) * interval_s
    total = density.sum()
    mean = float(density @ t / total)
    return mean, float(density @ (t - mean) ** 2 / total)


def compare_time(
    results: str | Path,
    target: DemTarget,
    grid=(10, 1),
    k: int = 2,
    fit_window_s: tuple[float, float] | None = None,
    settings: phases.PhaseSettings | None = None,
) -> TimeComparison:
    """:class:`TimeComparison` on the DEM results ``results`` (with sequences), both chains
    fitted with ``settings`` (default the product's) from one start, at every dump."""
    from pbm.model import feed_distribution

    entry, reason = try_load_entry(Path(results))
    if entry is None:
        raise ConfigError(f"results {results}: {reason}")
    dem = DemResults.from_cache_entry(entry)
    config = config_of(entry)
    last = float(dem.sequences.snapshot_t[-1])
    window = fit_window_s or (target.steady_time_s, last)
    window = (float(window[0]), min(float(window[1]), last))
    data = phases.prepare(dem.sequences, window, tuple(grid), residents=True)
    wall0 = time.perf_counter()
    settings = dataclasses.replace(settings or phases.PhaseSettings(), n_phases=k, starts=1)
    cont = phases.PhaseEstimator(settings).fit(data).fetch_model()
    wall1 = time.perf_counter()
    disc = phases.fit_discrete(data, cont.transport, settings)
    wall2 = time.perf_counter()
    projected = phases.generator_from_transition(disc, data.nx, data.ny)
    g = config.dem.geometry
    t_end = target.entry_window_s[1] + target.horizon_s + 5.0
    table = phase_table(projected, float(g.length_m), float(g.diameter_m), t_end)
    pbm_config = pbm_config_for(config, table, None).model_copy(update={"rates": "phases", "duration_s": t_end})
    start_cont = pbm_numbers(cont.transport, config, target)
    start_proj = pbm_numbers(projected, config, target)
    # the discrete chain from the same inlet, in its own entry phases
    feed_d = feed_distribution(table, pbm_config.feed_weights_a, pbm_config.feed_weights_b, "phases").mean(axis=1)
    return TimeComparison(
        grid=tuple(grid),
        n_phases=k,
        continuous_ll_per_step=cont.log_likelihood / data.n_steps,
        continuous_parameters=cont.n_parameters(),
        discrete_ll_per_step=disc.log_likelihood / data.n_steps,
        discrete_parameters=disc.n_parameters,
        continuous_rtd=(start_cont["mean_s"], start_cont["variance_s2"]),
        discrete_rtd=discrete_rtd(disc.transition, feed_d, data.interval_s, target.horizon_s),
        projected_rtd=(start_proj["mean_s"], start_proj["variance_s2"]),
        continuous_wall_s=wall1 - wall0,
        discrete_wall_s=wall2 - wall1,
    )


def timescales_over_lags(
    results: str | Path,
    grid=(10, 1),
    lags=(1, 2, 5, 10),
    n_phases: int = 1,
    fit_window_s: tuple[float, float] | None = None,
    count: int = 3,
    steady_time_s: float | None = None,
    settings: phases.PhaseSettings | None = None,
) -> dict[int, tuple[float, ...]]:
    """The ``count`` longest implied timescales [s] of the K = ``n_phases`` chain fitted at
    each lag (in dumps; ``settings``, default the product's, from one start), the MSM test
    of Markovianity: a Markovian chain's are the same at every lag, a chain on states that
    forget too much speeds up (shorter timescales) at short lags. Returns lag -> timescales."""
    settings = dataclasses.replace(settings or phases.PhaseSettings(), n_phases=n_phases, starts=1)
    entry, reason = try_load_entry(Path(results))
    if entry is None:
        raise ConfigError(f"results {results}: {reason}")
    dem = DemResults.from_cache_entry(entry)
    seq = dem.sequences
    t0 = steady_time_s if steady_time_s is not None else float(dem.summary.steady_state_time_s)
    window = fit_window_s or (t0, float(seq.snapshot_t[-1]))
    out = {}
    for lag in lags:
        data = phases.prepare(seq, window, tuple(grid), lag=int(lag))
        model = phases.PhaseEstimator(settings).fit(data).fetch_model()
        out[int(lag)] = tuple(float(v) for v in model.implied_timescales(count))
    return out


HELP = "hidden-phase transport chains fitted to a DEM run's compartment sequences, and their PBMs against the DEM"


def _grids(text: str) -> tuple[tuple[int, int], ...]:
    try:
        grids = tuple(tuple(int(v) for v in g.lower().split("x")) for g in text.split(","))
    except ValueError:
        grids = ()
    if not grids or any(len(g) != 2 or min(g) < 1 for g in grids):
        raise ConfigError(f"--grids {text!r}: expected comma-separated NXxNY, e.g. 10x1,10x10")
    return grids


#: the command line's flags for the fit's settings: flag, field, type, help
SETTING_FLAGS = (
    ("--starts", "starts", int, "EM starts per fit"),
    ("--lag-s", "lag_s", float, "interval between the observations fitted [s]"),
    ("--max-rate-x-interval", "max_rate_x_interval", float, "the fit's bound on every rate x the observation interval"),
    ("--tol", "tol", float, "stop EM when a step gains less than this per particle-step [nats]"),
)


def add_arguments(parser) -> None:
    parser.add_argument("--results", required=True, help="DEM results file with compartment sequences (dem-*.h5)")
    parser.add_argument(
        "--target", default=None, help="DEM results whose pooled RTD and hold-up judge the models (default: --results)"
    )
    parser.add_argument("--grids", default="10x10,10x1", help="comma-separated NXxNY coarsenings (default %(default)s)")
    parser.add_argument("--ks", default="1,2,3", help="numbers of phases (default %(default)s)")
    product = phases.PhaseSettings()
    for flag, name, kind, text in SETTING_FLAGS:
        parser.add_argument(
            flag, type=kind, default=getattr(product, name), help=text + " (default %(default)s, the product's)"
        )
    parser.add_argument(
        "--observed-nx",
        type=int,
        default=None,
        help="fit each NXx1 grid's chain to the observations on this many slices instead (the sub-slice "
        "hidden beside the phase; must divide NX)",
    )
    parser.add_argument(
        "--stagnant",
        nargs="?",
        type=float,
        const=1.0,
        metavar="R",
        help="phase 0 of every K >= 2 a dead zone: no moves, left at most once per R mean residence times "
        "(default R = 1)",
    )
    parser.add_argument("--out", default="results/phases", help="where phases.json goes (default %(default)s)")


def settings_of(args) -> phases.PhaseSettings:
    """The product's settings with the command line's (:data:`SETTING_FLAGS`); ConfigError
    naming the flag for a value the settings refuse."""
    settings = phases.PhaseSettings()
    for flag, name, _kind, _text in SETTING_FLAGS:
        try:
            settings = dataclasses.replace(settings, **{name: getattr(args, name)})
        except ConfigError as exc:
            raise ConfigError(f"{flag} {getattr(args, name)}: {exc}") from None
    return settings


def run(args) -> int:
    try:
        ks = tuple(int(k) for k in args.ks.split(","))
    except ValueError:
        raise ConfigError(f"--ks {args.ks!r}: expected comma-separated whole numbers, e.g. 1,2,3") from None
    if not ks or min(ks) < 1:
        raise ConfigError(f"--ks {args.ks!r}: all must be >= 1")
    if args.stagnant is not None and not args.stagnant > 0:
        raise ConfigError(f"--stagnant {args.stagnant}: expected a number of mean residence times > 0, e.g. 1")
    study = phase_study(
        args.results,
        args.target,
        _grids(args.grids),
        ks,
        settings_of(args),
        observed_nx=args.observed_nx,
        stagnant=args.stagnant,
    )
    print(markdown(study))
    out = writable_directory(args.out, "--out")
    print(f"wrote {write_json(out / 'phases.json', record(study))} and {plot_study(study, out / 'phases.png')}")
    return 0


def plot_study(study: PhaseStudy, path: Path) -> Path:
    """Choosing K: per grid, the held-out log-likelihood per observation and the PBM's RTD
    variance against K, beside the DEM's 95 % interval."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6), layout="constrained")
    held, var = fig.subplots(1, 2)
    g = study.target.variance_s2
    var.axhspan(g.low, g.high, color="#bdbdbd", alpha=0.6, label="DEM, 95 %")
    for grid in dict.fromkeys(r.grid for r in study.results):
        rows = [r for r in study.results if r.grid == grid]
        ks = [r.n_phases for r in rows]
        label = f"{grid[0]}×{grid[1]}"
        held.plot(ks, [r.held_out_per_step for r in rows], "o-", label=label)
        var.plot(ks, [r.variance_s2 for r in rows], "o-", label=label)
    held.set(xlabel="phases K", ylabel="held-out log-likelihood per observation", title="second half, fit on the first")
    var.set(xlabel="phases K", ylabel="pooled RTD variance [s²]", title="the PBM's RTD against the DEM's")
    for ax in (held, var):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return path
