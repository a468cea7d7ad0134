"""One PBM run: velocity table + configuration -> CQA time series, RTD and a summary.

:func:`simulate` is the API the pipeline calls; :class:`PbmResult` is what it returns
(:func:`pbm.outputs.write_outputs` writes it to files). The CQAs are computed by
:mod:`coupling.metrics`, the same functions the DEM side calls.

Time convention of the series: output k sits at ``t_k = k * output_interval_s``
(k = 1..K). Rates and C_A are averages over the interval (t_{k-1}, t_k] -- exact, from the
accumulated discharge -- and counts, hold-ups and RSDs are values at the instant t_k.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from coupling.blas import single_threaded_blas
from coupling.errors import ConfigError
from coupling.metrics import TIMESERIES_COLUMNS, SteadyStateRule, outflow_fraction_a, residence_moments, rsd
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.feed import FeedOverride, resolve_feed
from pbm.fill import FillLaw, config_schedule
from pbm.model import N_ACCUMULATORS, collapse_phases, feed_distribution, filled_table, n_phases, n_populations
from pbm.solver import TIME_TOLERANCE_S, Propagators, Schedule, breakpoints, march, multiples
from pbm.summary import PbmSummary, nested_tuples

if TYPE_CHECKING:
    import pandas as pd

BDF_ATOL_PARTICLES = 1e-9


@dataclass(frozen=True)
class PbmResult:
    """Everything one PBM run produces. Units in the field docs; arrays are numpy.

    Series over output times (shape (K,)): ``times`` [s]; ``outflow_A``, ``outflow_B``
    [particles/s, mean over (t_{k-1}, t_k]]; ``C_A`` [-, flux-weighted A fraction of the
    outflow over the interval, NaN while nothing leaves]; ``rsd_outlet`` (across the last
    slice), ``rsd_blender`` (across all compartments) [-, NaN when undefined];
    ``holdup_A``, ``holdup_B`` [particles]; ``fed_A``, ``fed_B``, ``discharged_A``,
    ``discharged_B`` [particles, cumulative since t = 0].
    ``counts`` (K, 2, NX, NY): A and B particles per compartment at each output time.
    ``rsd_by_slice_final`` (NX,): RSD across each axial slice at the end, inlet -> outlet;
    ``x_centres`` (NX,) [m] for plotting it.
    RTD: ``rtd_t`` [s, residence-time bin centres], ``rtd_E`` [1/s] (tracer discharged in
    the bin / tracer fed / bin width), ``rtd_pulse_s`` [s] the pulse time.
    ``summary``: the run's scalars, :class:`pbm.summary.PbmSummary` (its ``record()`` is
    the JSON-ready dict).
    ``schedule``: under ``rate_law`` = "fill", the generators the run marched on (its bulk
    solved once; :func:`pbm.rtd.pooled_rtd` of the same run takes it); None otherwise.
    ``feed_overrides``: the configuration's feed rates that differ from the table's
    operating point (:func:`pbm.feed.resolve_feed`), each named by its ``message``.
    """

    times: np.ndarray
    outflow_A: np.ndarray
    outflow_B: np.ndarray
    C_A: np.ndarray
    rsd_outlet: np.ndarray
    rsd_blender: np.ndarray
    holdup_A: np.ndarray
    holdup_B: np.ndarray
    fed_A: np.ndarray
    fed_B: np.ndarray
    discharged_A: np.ndarray
    discharged_B: np.ndarray
    counts: np.ndarray
    rsd_by_slice_final: np.ndarray
    x_centres: np.ndarray
    rtd_t: np.ndarray
    rtd_E: np.ndarray
    rtd_pulse_s: float
    summary: PbmSummary
    schedule: Schedule | None = None
    #: the configured feed rates that contradict the table's operating point (pbm.feed)
    feed_overrides: tuple[FeedOverride, ...] = ()

    def timeseries(self) -> pd.DataFrame:
        """The CQA series in :data:`coupling.metrics.TIMESERIES_COLUMNS`."""
        import pandas as pd  # here: a caller of the solver alone need not import it

        values = (
            self.times,
            self.outflow_A,
            self.outflow_B,
            self.C_A,
            self.rsd_outlet,
            self.rsd_blender,
            self.holdup_A,
            self.holdup_B,
        )
        return pd.DataFrame(dict(zip(TIMESERIES_COLUMNS, values)))

    def rtd(self) -> pd.DataFrame:
        """E(t): ``t_s`` (bin centres since the pulse) and ``E_per_s``."""
        import pandas as pd

        return pd.DataFrame({"t_s": self.rtd_t, "E_per_s": self.rtd_E})


def noise_factors(config: PbmConfig, n_intervals: int, members: int = 1, sigma: float | None = None) -> np.ndarray:
    """(n_intervals, members, 2) multiplicative factors of the A and B feed rates, one row
    per noise interval: N(1, sigma) clipped at 0, from one generator seeded
    ``config.seed`` and drawn member after member, so member m's factors do not depend on
    how many members follow it, and member 0 is the single run with that seed (one stream
    rather than a generator per member: seeding 10 000 generators took longer than the
    ensemble's propagation). All ones when sigma is 0.
    """
    sigma = config.noise_sigma if sigma is None else sigma
    if sigma == 0:
        return np.ones((n_intervals, members, 2))
    draws = np.random.default_rng(config.seed).standard_normal((members, n_intervals, 2))
    # in place and returned as a transposed view: at 10 000 members and 1-s intervals each
    # temporary is 42 MB of fresh pages, and faulting them in took longer than the
    # unit responses' whole march (same numbers: sigma x, then + 1, then the clip)
    draws *= sigma
    draws += 1.0
    np.maximum(draws, 0.0, out=draws)
    return draws.transpose(1, 0, 2)


def feed_factors(config: PbmConfig, n_intervals: int, members: int = 1, sigma: float | None = None) -> np.ndarray:
    """(n_intervals, members, 2) factors of the A and B feed rates per interval: the noise
    of :func:`noise_factors` times feeder A's step (``config.feed_step_factor_a`` from
    ``config.feed_step_s`` on)."""
    factors = noise_factors(config, n_intervals, members, sigma)
    if config.feed_step_s is not None:
        first = round(config.feed_step_s / config.noise_interval_s)
        factors[first:, :, 0] *= config.feed_step_factor_a
    return factors


def noise_intervals(config: PbmConfig, t_end: float) -> int:
    """How many feed intervals (``config.noise_interval_s``) a run to ``t_end`` spans."""
    return max(1, math.ceil(t_end / config.noise_interval_s - 1e-9))


def cumulative_feed(times: np.ndarray, rate_per_s: float, factors: np.ndarray, interval_s: float) -> np.ndarray:
    """Particles fed by ``times`` [s] at ``rate_per_s`` x the piecewise-constant factors."""
    edges = interval_s * np.arange(factors.size + 1)
    fed_at_edges = np.concatenate([[0.0], np.cumsum(factors * interval_s)])
    k = np.clip(np.floor(np.asarray(times) / interval_s + 1e-9).astype(int), 0, factors.size - 1)
    return rate_per_s * (fed_at_edges[k] + factors[k] * (np.asarray(times) - edges[k]))


def check_run(table: VelocityTable, config: PbmConfig) -> float:
    """Validate what the configuration asks of this table; return the end time [s]."""
    t_end = table.t_end if config.duration_s is None else config.duration_s
    if t_end < config.output_interval_s - TIME_TOLERANCE_S:
        raise ConfigError(
            f"duration {t_end} s is shorter than output_interval_s = {config.output_interval_s} s; "
            "at least one output interval is needed"
        )
    if t_end / config.output_interval_s > 1e6:
        raise ConfigError(
            f"duration {t_end} s / output_interval_s {config.output_interval_s} s asks for more than "
            "1e6 outputs; raise output_interval_s"
        )
    return float(t_end)


@single_threaded_blas()
def simulate(
    table: VelocityTable,
    config: PbmConfig | None = None,
    rtd_pulse_s: float | None = None,
    initial_counts: np.ndarray | None = None,
    steady: SteadyStateRule = SteadyStateRule(),
) -> PbmResult:
    """Run the compartment PBM driven by ``table`` and return its CQAs.

    ``config`` defaults to :class:`PbmConfig`; its feed left None is the table's
    operating point's (:func:`pbm.feed.resolve_feed`; the paper's on a table without one). ``rtd_pulse_s`` [s]
    overrides ``config.rtd_pulse_s``; when both are None the tracer pulse is fed at the
    steady state that ``steady`` detects on the total hold-up (the rule the DEM is judged
    by, :class:`coupling.metrics.SteadyStateRule`; if it
    is never detected, at the output time of least relative hold-up change, or at 0 for a
    run shorter than two steady windows -- ``summary.rtd_pulse_rule`` says which).
    ``initial_counts`` (2, NX, NY) [particles]: A and B already in the blender at t = 0
    (default empty).

    With ``config.rate_law`` = "fill" the axial rates follow each slice's hold-up
    (:mod:`pbm.fill`): the table's steady rates scaled by the law of
    ``config.fill_exponents``, by default fitted to the table's own windows.

    ``config.rates`` chooses the transfer rates (:func:`pbm.model.transfer_rates`); the fields
    it reads are filled where missing by :func:`pbm.model.filled_table` (velocities of
    compartment-windows without enough samples, or unmeasured rates). The tracer pulse holds as many particles
    as the nominal feed delivers in one second (1 if the feed is 0), distributed over the
    inlet like the nominal total feed; E(t) is normalised by it, so the amount is moot.

    ``summary``: a :class:`pbm.summary.PbmSummary`. The steps, in order:
    :func:`prepare_run` (validate, feed, rates, initial state), :func:`march_run` (A, B
    and the tracer pulse), :func:`tracer_rtd`, :func:`cqa_series`,
    :func:`steady_span_means`, :func:`run_summary`. Raises
    ConfigError for settings this table cannot satisfy (rates = "measured" on a table
    without measured rates), TableError for an empty table.
    """
    wall0 = time.perf_counter()
    config, overrides = resolve_feed(config, table)
    setup = prepare_run(table, config, rtd_pulse_s, initial_counts, steady)
    marched = march_run(setup, steady)
    rtd_t, rtd_E, moments = tracer_rtd(setup, marched)
    series = cqa_series(setup, marched)
    outflow, c_a = steady_span_means(setup.out_times, series.discharged, marched.steady_time, setup.t_end, steady)
    summary = run_summary(setup, marched, series, moments, outflow, c_a, time.perf_counter() - wall0)
    return PbmResult(
        times=setup.out_times,
        outflow_A=series.increments[:, 0] / config.output_interval_s,
        outflow_B=series.increments[:, 1] / config.output_interval_s,
        C_A=outflow_fraction_a(series.increments[:, 0], series.increments[:, 1]),
        rsd_outlet=series.rsd_outlet,
        rsd_blender=series.rsd_blender,
        holdup_A=series.holdup[:, 0],
        holdup_B=series.holdup[:, 1],
        fed_A=series.fed[:, 0],
        fed_B=series.fed[:, 1],
        discharged_A=series.discharged[:, 0].copy(),
        discharged_B=series.discharged[:, 1].copy(),
        counts=series.counts,
        rsd_by_slice_final=series.rsd_slices,
        x_centres=0.5 * (table.x_edges[:-1] + table.x_edges[1:]),
        rtd_t=rtd_t,
        rtd_E=rtd_E,
        rtd_pulse_s=float(marched.pulse),
        summary=summary,
        schedule=setup.schedule,
        feed_overrides=overrides,
    )


@dataclass(frozen=True)
class RunSetup:
    """A run validated and ready to march (:func:`prepare_run`).

    ``t_end`` [s]; ``pulse`` [s] the requested tracer pulse (None: at the steady state);
    ``filled_mask``: the compartment-windows filled in the fields the rates read; ``n``
    populations (NX * NY, times the phases in mode "phases", ``k_phases``); ``z0`` (m, 2)
    the augmented initial state of A and B (m = n + accumulators); ``out_times`` [s];
    ``factors`` (intervals, 2) the feed factors and ``rates`` (2,) [1/s] the nominal
    feed; the tracer pulse's ``tracer_amount`` [particles] and (m,) ``tracer_vector``;
    ``schedule`` and its fill ``law`` (None under the table's rates); ``props`` the
    propagators.
    """

    table: VelocityTable
    config: PbmConfig
    t_end: float
    pulse: float | None
    filled_mask: np.ndarray
    n: int
    k_phases: int
    z0: np.ndarray
    out_times: np.ndarray
    factors: np.ndarray
    rates: np.ndarray
    tracer_amount: float
    tracer_vector: np.ndarray
    schedule: Schedule | None
    law: FillLaw | None
    props: Propagators


def prepare_run(
    table: VelocityTable,
    config: PbmConfig,
    rtd_pulse_s: float | None,
    initial_counts: np.ndarray | None,
    steady: SteadyStateRule,
) -> RunSetup:
    """Validate the run :func:`simulate` is asked for and build what it marches on."""
    t_end = check_run(table, config)
    pulse = config.rtd_pulse_s if rtd_pulse_s is None else float(rtd_pulse_s)
    if pulse is not None and not (0.0 <= pulse < t_end):
        raise ConfigError(f"RTD pulse time {pulse} s must lie in [0, {t_end}) s, the simulated time")
    filled, filled_mask = filled_table(table, config.rates)
    feed = feed_distribution(table, config.feed_weights_a, config.feed_weights_b, config.rates)
    # populations: NX*NY compartments, times K phases in mode "phases" (collapsed in cqa_series)
    n, k_phases = n_populations(table, config.rates), n_phases(table, config.rates)
    m = n + N_ACCUMULATORS
    z0 = initial_state(table, config.rates, initial_counts, n, m)
    factors = feed_factors(config, noise_intervals(config, t_end))[:, 0]
    rates = np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s])
    tracer_amount, tracer_vector = tracer_pulse(feed, rates, m)
    schedule, law = config_schedule(table, config, feed, factors, t_end, z0[:n, 0] + z0[:n, 1], steady)
    return RunSetup(
        table=table,
        config=config,
        t_end=t_end,
        pulse=pulse,
        filled_mask=filled_mask,
        n=n,
        k_phases=k_phases,
        z0=z0,
        out_times=multiples(config.output_interval_s, config.output_interval_s, t_end),
        factors=factors,
        rates=rates,
        tracer_amount=tracer_amount,
        tracer_vector=tracer_vector,
        schedule=schedule,
        law=law,
        props=Propagators(filled, feed, config.rates, config.kernel, schedule),
    )


def initial_state(table: VelocityTable, rates: str, initial_counts: np.ndarray | None, n: int, m: int) -> np.ndarray:
    """(m, 2) augmented state of A and B at t = 0: ``initial_counts`` (2, NX, NY)
    [particles] on the populations (empty when None), nothing accumulated."""
    z0 = np.zeros((m, 2))
    if initial_counts is not None:
        init = np.asarray(initial_counts, dtype=float)
        if init.shape != (2, table.nx, table.ny) or not np.all(np.isfinite(init)) or np.any(init < 0):
            raise ConfigError(
                f"initial_counts must be finite, >= 0 and shaped (2, NX, NY) = (2, {table.nx}, {table.ny}); "
                f"got shape {init.shape}"
            )
        z0[:n, 0] = initial_populations(init[0], table, rates, 0)
        z0[:n, 1] = initial_populations(init[1], table, rates, 1)
    return z0


@dataclass(frozen=True)
class Marched:
    """The marched states (:func:`march_run`): ``main`` (K, m, >= 2) at the output times
    (columns A, B); ``steady_time`` [s] on the total hold-up (None if never steady); the
    tracer ``pulse`` [s] and the ``rule`` that placed it; the RTD's ``bins`` [s, edges];
    ``tracer_t`` [s] and ``tracer`` (T, m, 1) the tracer's states at those times."""

    main: np.ndarray
    steady_time: float | None
    pulse: float
    rule: str
    bins: np.ndarray
    tracer_t: np.ndarray
    tracer: np.ndarray


def march_run(setup: RunSetup, steady: SteadyStateRule) -> Marched:
    """March A, B and the tracer. A given pulse rides along with A and B in one march; at
    the steady state (:func:`_choose_pulse`) it needs A and B's hold-up first, so the
    tracer is marched after them, from the pulse."""
    config, n, out_times = setup.config, setup.n, setup.out_times

    def run(t_start, columns, pulse_at, record):
        z0 = _initial_columns(setup.z0, columns)
        return _run_columns(
            setup.props,
            config,
            t_start,
            setup.t_end,
            columns,
            z0,
            setup.factors,
            setup.rates,
            record,
            pulse_at,
            setup.tracer_vector,
        )

    pulse = setup.pulse
    if pulse is not None:
        bins = _bin_edges(pulse, config.rtd_bin_s, setup.t_end)
        rec_t, rec_z = run(0.0, (0, 1, 2), pulse, np.concatenate([out_times, bins]))
        main_z = _select(rec_t, rec_z, out_times)
        holdup_total = main_z[:, :n, 0].sum(axis=1) + main_z[:, :n, 1].sum(axis=1)
        tracer_t, tracer = rec_t, rec_z[:, :, 2:3]
        rule = "given"
        steady_time = steady.time(out_times, holdup_total)
    else:
        rec_t, rec_z = run(0.0, (0, 1), None, out_times)
        main_z = _select(rec_t, rec_z, out_times)
        holdup_total = main_z[:, :n, 0].sum(axis=1) + main_z[:, :n, 1].sum(axis=1)
        steady_time = steady.time(out_times, holdup_total)
        pulse, rule = _choose_pulse(out_times, holdup_total, steady_time, steady)
        bins = _bin_edges(pulse, config.rtd_bin_s, setup.t_end)
        tracer_t, tracer = run(pulse, (2,), pulse, bins)
    return Marched(main_z, steady_time, pulse, rule, bins, tracer_t, tracer)


def _initial_columns(z0: np.ndarray, columns) -> np.ndarray:
    """The initial state of each marched column: A's and B's from ``z0``, the tracer's 0."""
    z = np.zeros((z0.shape[0], len(columns)))
    for col, species in enumerate(columns):
        if species in (0, 1):
            z[:, col] = z0[:, species]
    return z


def tracer_rtd(setup: RunSetup, marched: Marched) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """``(rtd_t, rtd_E, moments)``: E(t) [1/s] at the bin centres [s] from the tracer
    discharged at the bin edges, and the exact moments (:func:`rtd_moments`) from the
    tracer's final state."""
    n, bin_s = setup.n, setup.config.rtd_bin_s
    tracer_at_bins = _select(marched.tracer_t, marched.tracer, marched.bins)[:, n, 0]
    rtd_E = np.diff(tracer_at_bins) / (setup.tracer_amount * bin_s)
    rtd_t = bin_s * (np.arange(rtd_E.size) + 0.5)
    final_tracer = marched.tracer[-1, :, 0]
    moments = rtd_moments(
        setup.tracer_amount,
        final_tracer[:n].sum(),
        final_tracer[n + 1],
        final_tracer[n + 2],
        setup.t_end - marched.pulse,
    )
    return rtd_t, rtd_E, moments


@dataclass(frozen=True)
class Series:
    """The CQA series at the output times (:func:`cqa_series`): ``counts`` (K, 2, NX, NY),
    ``discharged`` (K, 2) and ``fed`` (K, 2) [particles, cumulative], ``increments`` (K, 2)
    discharged per interval, ``holdup`` (K, 2), ``rsd_outlet`` and ``rsd_blender`` (K,),
    ``rsd_slices`` (NX,) at the end."""

    counts: np.ndarray
    discharged: np.ndarray
    increments: np.ndarray
    fed: np.ndarray
    holdup: np.ndarray
    rsd_outlet: np.ndarray
    rsd_blender: np.ndarray
    rsd_slices: np.ndarray


def cqa_series(setup: RunSetup, marched: Marched) -> Series:
    """The CQA series of A and B (:mod:`coupling.metrics`), phases collapsed."""
    table, config, n, out_times = setup.table, setup.config, setup.n, setup.out_times
    main_z = marched.main
    counts = (
        collapse_phases(main_z[:, :n, :2], setup.k_phases, axis=1)
        .transpose(0, 2, 1)
        .reshape(out_times.size, 2, table.nx, table.ny)
    )
    discharged = main_z[:, n, :2]
    increments = np.diff(np.vstack([np.zeros(2), discharged]), axis=0)
    fed = np.stack(
        [cumulative_feed(out_times, setup.rates[s], setup.factors[:, s], config.noise_interval_s) for s in (0, 1)], 1
    )
    cells = table.nx * table.ny
    return Series(
        counts=counts,
        discharged=discharged,
        increments=increments,
        fed=fed,
        holdup=counts.sum(axis=(2, 3)),
        rsd_outlet=rsd(counts[:, 0, -1, :], counts[:, 1, -1, :], axis=1),
        rsd_blender=rsd(
            counts[:, 0].reshape(out_times.size, cells), counts[:, 1].reshape(out_times.size, cells), axis=1
        ),
        rsd_slices=rsd(counts[-1, 0], counts[-1, 1], axis=1),
    )


def steady_span_means(
    out_times: np.ndarray,
    discharged: np.ndarray,
    steady_time: float | None,
    t_end: float,
    steady: SteadyStateRule,
) -> tuple[float, float]:
    """``(outflow [1/s], C_A)`` from the steady-state time to the end, exact from the
    discharge ``discharged`` (K, 2) accumulated over the span, which starts at the output
    time nearest the steady state (the last ``steady.window_s`` if none was found, or it
    falls at the end). C_A by :func:`coupling.metrics.outflow_fraction_a`."""
    if steady_time is not None and steady_time < t_end - TIME_TOLERANCE_S:
        span_start = steady_time
    else:
        span_start = max(0.0, out_times[-1] - steady.window_s)
    if span_start <= TIME_TOLERANCE_S:
        span_start, d_start = 0.0, np.zeros(2)
    else:
        start_idx = int(np.argmin(np.abs(out_times - span_start)))
        span_start, d_start = float(out_times[start_idx]), discharged[start_idx]
    span = out_times[-1] - span_start
    d_span = discharged[-1] - d_start
    outflow = float(d_span.sum() / span) if span > 0 else float("nan")
    return outflow, float(outflow_fraction_a(d_span[0], d_span[1]))


def run_summary(
    setup: RunSetup,
    marched: Marched,
    series: Series,
    moments: dict[str, float],
    steady_outflow_per_s: float,
    steady_c_a: float,
    wall_time_s: float,
) -> PbmSummary:
    """The run's :class:`pbm.summary.PbmSummary` from its steps' results."""
    config, law, holdup = setup.config, setup.law, series.holdup
    return PbmSummary(
        mean_residence_time_s=moments["mean_s"],
        rtd_variance_s2=moments["variance_s2"],
        rtd_recovered_fraction=moments["recovered_fraction"],
        steady_outflow_per_s=steady_outflow_per_s,
        steady_C_A=steady_c_a,
        final_rsd_outlet=float(series.rsd_outlet[-1]),
        final_rsd_blender=float(series.rsd_blender[-1]),
        final_rsd_by_slice=tuple(float(v) for v in series.rsd_slices),
        holdup_final=float(holdup[-1].sum()),
        holdup_final_A=float(holdup[-1, 0]),
        holdup_final_B=float(holdup[-1, 1]),
        steady_state_time_s=marched.steady_time,
        rtd_pulse_s=float(marched.pulse),
        rtd_pulse_rule=marched.rule,
        filled_compartment_windows=int(setup.filled_mask.sum()),
        nx=setup.table.nx,
        ny=setup.table.ny,
        duration_s=setup.t_end,
        method=config.method,
        rate_law=config.rate_law,
        fill_law_form=None if law is None else law.form,
        fill_exponents=None if law is None else nested_tuples(law.beta.tolist()),
        wall_time_s=wall_time_s,
    )


def initial_populations(counts: np.ndarray, table: VelocityTable, rates: str, feeder: int) -> np.ndarray:
    """The population entries of ``counts`` (NX, NY) particles already in the blender: the
    counts themselves, or in mode "phases" split over the phases like that feeder's entry
    (the phases of particles fed earlier are not known; the feed's is the one stated)."""
    flat = np.asarray(counts, dtype=float).ravel()
    if rates != "phases":
        return flat
    return (flat[:, None] * table.phases.entry[feeder][None, :]).ravel()


def recovered_moments(amount, held, int1, int2, elapsed_s):
    """Raw moments of the residence time of the tracer recovered within ``elapsed_s``.

    From the tracer's hold-up at the end ``held`` = H(T), and its time integrals since the
    pulse ``int1`` = int_0^T H dtau and ``int2`` = int_0^T int1 dtau, with T = ``elapsed_s``
    since the pulse and the outflow q = -dH/dtau. Integration by parts gives
    int tau q = int1 - T H(T) and int tau^2 q = 2 (T int1 - int2) - T^2 H(T). Returns
    ``(recovered, m1, m2)`` = (int q, int tau q, int tau^2 q) over [0, T]; element-wise
    for arrays (one pulse per entry).
    """
    recovered = amount - held
    m1 = int1 - elapsed_s * held
    m2 = 2.0 * (elapsed_s * int1 - int2) - elapsed_s**2 * held
    return recovered, m1, m2


def rtd_moments(amount: float, held: float, int1: float, int2: float, elapsed_s: float) -> dict[str, float]:
    """Mean and variance of the residence time of the recovered tracer, exactly
    (:func:`recovered_moments`). Moments are conditional on recovery by the end, like the
    DEM's tagged particles that left.
    """
    recovered, m1, m2 = recovered_moments(amount, held, int1, int2, elapsed_s)
    # never a negative time or variance: round-off moments of a tracer that did not leave are NaN
    return residence_moments(amount, recovered, m1, m2)


def tracer_pulse(feed: np.ndarray, rates: np.ndarray, m: int) -> tuple[float, np.ndarray]:
    """``(amount, vector)``: a tracer pulse of as many particles as the feed ``rates`` (A, B)
    deliver in one second (1 if they are 0), spread over the inlet like the total feed;
    ``vector`` is its (m,) augmented state."""
    total = rates.sum()
    shape = feed @ rates / total if total > 0 else feed.mean(axis=1)
    amount = float(total) if total > 0 else 1.0
    vector = np.zeros(m)
    vector[: feed.shape[0]] = amount * shape
    return amount, vector


def _bin_edges(pulse: float, bin_s: float, t_end: float) -> np.ndarray:
    count = int(np.floor((t_end - pulse) / bin_s + 1e-9))
    return pulse + bin_s * np.arange(count + 1)


def _choose_pulse(times, holdup, steady_time, steady: SteadyStateRule) -> tuple[float, str]:
    if steady_time is not None:
        return steady_time, "steady state detected"
    change = steady.relative_change(times, holdup)
    if np.all(np.isnan(change)):
        return 0.0, "run shorter than two steady windows: pulse at t = 0"
    return float(times[np.nanargmin(change)]), "steady state not detected: pulse at least relative hold-up change"


def _run_columns(props, config, t_start, t_end, columns, z0, factors, rates, record_times, pulse_at, tracer_vector):
    """March the columns (species 0 = A, 1 = B, 2 = tracer) and record every breakpoint."""
    noise = config.noise_sigma > 0
    step = config.feed_step_s is not None
    switch_sets = [props.schedule.t]
    if noise:
        switch_sets.append(multiples(config.noise_interval_s, t_start, t_end))
    if step:
        switch_sets.append(np.array([config.feed_step_s]))
    extra = [] if pulse_at is None else [[pulse_at]]
    times = breakpoints(t_start, t_end, record_times, *switch_sets, *extra)
    mids = 0.5 * (times[:-1] + times[1:])
    feed_key = np.floor(mids / config.noise_interval_s).astype(int) if noise or step else np.zeros(mids.size, int)
    feed_key = np.clip(feed_key, 0, factors.shape[0] - 1)
    c = len(columns)
    injections = {}
    if pulse_at is not None:
        b = int(np.argmin(np.abs(times - pulse_at)))
        inj = np.zeros((props.n_states, c))
        inj[:, columns.index(2)] = tracer_vector
        injections[b] = inj

    def feed_rates(key: int) -> np.ndarray:
        r = np.zeros((2, c))
        for col, species in enumerate(columns):
            if species in (0, 1):
                r[species, col] = rates[species] * factors[key, species]
        return r

    out = np.empty((times.size, props.n_states, c))
    out[0] = z0 + injections.get(0, 0.0)
    for b, z in march(
        props,
        times,
        z0,
        feed_rates,
        feed_key,
        injections,
        method=config.method,
        rtol=config.bdf_rtol,
        atol=BDF_ATOL_PARTICLES,
    ):
        out[b] = z
    return times, out


def _select(times: np.ndarray, states: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    idx = np.searchsorted(times, np.asarray(wanted) - TIME_TOLERANCE_S)
    return states[np.clip(idx, 0, times.size - 1)]
