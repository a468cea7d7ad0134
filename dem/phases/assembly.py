"""The phase model into the velocity table: the axial chains fitted to the steady period
(one for every size, or one per size class with its dead zone), the table's measured
transverse rates in every phase, the choice of K for the grid, and what a results summary
keeps of the fits.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from coupling import phases as phase_model
from coupling.phases import PhaseTransport
from dem.phases.data import FEEDERS, first_seen_in, prepare, steady_window
from dem.phases.estimator import PhaseEstimator, PhaseFit
from dem.phases.settings import PHASES, PhaseSettings
from dem.phases.sizes import kinds_by_size, little_residence_time, zone_held_to_little
from dem.tracking import CompartmentSequences

#: The phases a finer grid gets when it needs them (:func:`choose_phases`).
PHASES_FINE = PHASES + 2

#: :func:`choose_phases`' bar [nats per held-out particle-step] on what two more phases must
#: add to one chain's held-out score. Measured with ``pbmdem study phases --grids NXx1
#: --ks 3,5 --starts 1``: on 10 axial slices the eight shipped runs gain 0.0023-0.0053 (their
#: RTD variance unchanged within 1-3 %, or nearer the DEM's); on 20 slices the reduced run and
#: the validation baseline gain 0.0127 and 0.0137, and K = 3 lost 11 % and 10 % of their
#: variance against 10 slices, K = 5 2.4 % and 4.5 %. The bar sits between the two groups; it
#: rests on two fine-grid runs.
PHASE_GAIN_MIN = 0.008

#: :func:`choose_phases` scores the held-out particles in this many blocks of entry time, and
#: takes the finer K only when the gain, less two standard errors over the blocks, still
#: clears half the bar.
GAIN_BLOCKS = 8


def with_transverse(axial: PhaseTransport, transverse: PhaseTransport) -> PhaseTransport:
    """The model on the table's NX x NY grid: the K-phase axial chain ``axial`` (fitted on
    the NX x 1 slices) and, in every compartment, the transverse rates of the one-phase
    model ``transverse`` on the full grid (:func:`steady_transverse`), the same in every phase.

    Axial moves and phase switching do not depend on j, so the chain lumped onto
    (slice, phase) is exactly ``axial``: the RTD and the slice hold-ups are those of the
    fit, and the transverse rates only carry particles across y (the composition). A
    phase fit on the full grid would tie the phases to the transverse cells as well: on the
    validation run's first 60 s it cost 35 s (K = 2) to 445 s (K = 3) against 3 to 38 s on
    the slices, and its RTD was further from the DEM's (variance 270 s^2 with slice
    hold-ups 19 % off at K = 2, 231 s^2 at K = 3; ``workflows/studies/phases.py``)."""
    if axial.ny != 1 or transverse.n_phases != 1 or axial.nx != transverse.nx:
        raise ValueError(
            f"expected an NX x 1 axial model and a one-phase model on NX x NY with the same NX; got "
            f"{axial.nx}x{axial.ny} (K = {axial.n_phases}) and {transverse.nx}x{transverse.ny} "
            f"(K = {transverse.n_phases})"
        )
    k, ny = axial.n_phases, transverse.ny
    rates = np.empty((k, len(phase_model.DIRECTIONS), axial.nx, ny))
    rates[:, :2] = axial.rates[:, :2]  # broadcast over j
    rates[:, 2:] = transverse.rates[0, 2:][None]
    switching = np.repeat(axial.switching, ny, axis=3)
    attrs = {
        **axial.attrs,
        "grid": [axial.nx, ny],
        "axial_grid": [axial.nx, 1],
        "transverse": "one-phase rates of the full grid, the same in every phase",
    }
    return PhaseTransport(rates, switching, axial.entry, axial.interval_s, attrs)


def steady_transverse(table, steady_time_s: float) -> PhaseTransport:
    """The one-phase transverse rates of the table's grid: its measured ``rate_y_pos`` and
    ``rate_y_neg`` (:mod:`dem.rates`, fitted to the same particles' moves window by window)
    averaged over the windows from ``steady_time_s`` on, weighted by the particles each
    window saw; a compartment measured in none of them takes its slice's mean. Its axial
    rates are 0 (:func:`with_transverse` reads only the transverse ones). A maximum-
    likelihood fit on the full grid would give the same rates at a cost that grows with the
    cube of NX * NY (201 x 201 matrix exponentials at NX = 20, minutes per fit)."""
    if not table.has_rates:
        raise ValueError("the table carries no measured rates to take the transverse rates from")
    steady = table.t >= steady_time_s - 1e-9 * table.window_s
    if not steady.any():
        raise ValueError(f"no velocity window starts after the steady-state time {steady_time_s:g} s")
    weight = (table.count_A + table.count_B)[steady]
    rates = np.zeros((1, len(phase_model.DIRECTIONS), table.nx, table.ny))
    for d, name in ((2, "rate_y_pos"), (3, "rate_y_neg")):
        values = getattr(table, name)[steady]
        known = np.isfinite(values)
        total = np.where(known, weight, 0.0).sum(axis=0)
        mean = np.where(known, values * weight, 0.0).sum(axis=0) / np.where(total > 0, total, 1.0)
        mean = np.where(total > 0, mean, np.nan)
        by_slice = np.array([np.nanmean(row) if np.isfinite(row).any() else 0.0 for row in mean])[:, None]
        rates[0, d] = np.where(np.isfinite(mean), mean, by_slice)
    return PhaseTransport(rates, np.zeros((1, 1, table.nx, table.ny)), np.ones((2, 1)), float("nan"))


def axial_part(model: PhaseTransport) -> PhaseTransport:
    """The NX x 1 chain of a :func:`with_transverse` model (its lumping onto the slices)."""
    if np.ptp(model.rates[:, :2], axis=3).max(initial=0.0) > 0 or np.ptp(model.switching, axis=3).max(initial=0.0) > 0:
        raise ValueError("the model's axial rates or switching vary across y: it does not lump onto the slices")
    rates = model.rates[:, :, :, :1].copy()
    rates[:, 2:] = 0.0
    return PhaseTransport(rates, model.switching[:, :, :, :1], model.entry, model.interval_s, dict(model.attrs))


def table_with_phases(
    table,
    sequences: CompartmentSequences,
    steady_time_s: float | None,
    n_phases: int | None = None,
    settings: PhaseSettings | None = None,
    *,
    entered_s: tuple[float, float] | None = None,
    diameters: np.ndarray | None = None,
) -> tuple:
    """``table`` (a :class:`coupling.tables.VelocityTable` on the sequences' grid) carrying
    the K = ``n_phases`` model (default ``settings.n_phases``; ``settings`` default
    :class:`PhaseSettings`, the product's) fitted to the particles first seen after ``steady_time_s``
    and to the moves after it of those already inside (:func:`prepare`'s residents: without
    them the slow particles of the last slices are missing from the window's first mean
    residence times, and the outlet slice's hold-up came out 10 % low), observed every
    ``settings.lag_s``: the phases on the axial slices, the table's measured transverse
    rates over the steady windows (:func:`steady_transverse`) in every phase
    (:func:`with_transverse`); a schema-3 table that ``pbm`` runs with ``rates =
    "phases"``. ``entered_s`` = (t0, t1): fit to the particles first seen then instead
    (and those inside at t0). ``diameters`` (one per sequence [m], NaN unknown): each
    size class (:func:`kinds_by_size` over the whole steady window, whatever ``entered_s``
    fits, :data:`MIN_KIND_PARTICLES`) gets its own K-phase chain, and the table carries their population (:func:`coupling.phases.population`,
    K per class, fed in the classes' shares among the particles entering in the window,
    feeder by feeder); one class, or none known, fits one chain as without. A class's chain
    has a dead zone beside its K moving phases (phase 0 of K + 1, left at most once per
    ``settings.zone_residences`` of the window's :func:`little_residence_time`;
    None: no zone), its size then held to the class's own
    Little's law (:func:`zone_held_to_little`). Returns
    (table, fits of the axial phases, one per class). Raises ValueError when the run has
    no steady state or no particle entered after it."""
    if (table.nx, table.ny) != (sequences.nx, sequences.ny):
        raise ValueError(f"table grid {table.nx}x{table.ny} differs from the sequences' {sequences.nx}x{sequences.ny}")
    settings = PhaseSettings() if settings is None else settings
    k = settings.n_phases if n_phases is None else n_phases
    run_window = steady_window(sequences, steady_time_s)
    window = run_window if entered_s is None else entered_s
    kinds = _size_kinds(sequences, diameters, run_window)
    one = len(kinds) == 1
    if one or settings.zone_residences is None:
        fit_settings = dataclasses.replace(settings, n_phases=k)
    else:
        exit_max = 1.0 / (settings.zone_residences * little_residence_time(sequences, window))
        fit_settings = dataclasses.replace(settings, n_phases=k + 1, stagnant_exit_max_per_s=exit_max)
    lag = settings.lag_dumps(sequences.interval_s)
    fits = tuple(_fit_kind(sequences if one else sequences.subset(rows), window, lag, fit_settings) for rows in kinds)
    axial = fits[0].transport if one else _population(fits, kinds, sequences, window, diameters, k)
    transverse = steady_transverse(table, window[0]) if sequences.ny > 1 else None
    model = axial if transverse is None else with_transverse(axial, transverse)
    return table.replace(phases=model), fits


def _size_kinds(
    sequences: CompartmentSequences, diameters: np.ndarray | None, run_window: tuple[float, float]
) -> list[np.ndarray]:
    """The sequences' rows of each size class (:func:`kinds_by_size`), or all of them in one
    when no diameter is known."""
    if diameters is None or not np.isfinite(np.asarray(diameters, float)).any():
        return [np.arange(sequences.n_particles)]
    # The run's classes, whatever part of it is fitted: counted on a half window, the
    # feed x0.5 run's three classes fell below MIN_KIND_PARTICLES and merged into one
    # chain without a zone, whose mean was 2.6 s above both halves' DEM.
    return kinds_by_size(sequences, diameters, run_window)


def _fit_kind(part: CompartmentSequences, window: tuple[float, float], lag: int, settings: PhaseSettings) -> PhaseFit:
    """The axial chain of one kind's sequences ``part``: fitted to those first seen in
    ``window`` and its residents, observed every ``lag`` dumps; a dead zone
    (``settings.stagnant_exit_max_per_s``) then held to the kind's Little's law."""
    axial_data = prepare(part, window, grid=(part.nx, 1), lag=lag, residents=True)
    fitted = PhaseEstimator(settings).fit(axial_data).fetch_model()
    if settings.stagnant_exit_max_per_s is None:
        return fitted
    held = zone_held_to_little(fitted.transport, axial_data, little_residence_time(part, window))
    return dataclasses.replace(fitted, transport=held)


def _population(
    fits: tuple[PhaseFit, ...],
    kinds: list[np.ndarray],
    sequences: CompartmentSequences,
    window: tuple[float, float],
    diameters: np.ndarray,
    moving: int,
) -> PhaseTransport:
    """The kinds' chains side by side (:func:`coupling.phases.population`), feeder f's feed
    entering kind m in the share of kind m among feeder f's particles first seen in
    ``window``; its attributes name the kinds' mean diameters and phases."""
    entering = first_seen_in(sequences, window)
    shares = np.array(
        [[np.sum(entering[rows] & (sequences.component[rows] == f)) for rows in kinds] for f in FEEDERS], float
    )
    axial = phase_model.population([f.transport for f in fits], shares)
    sizes = [float(np.nanmean(np.asarray(diameters, float)[rows])) for rows in kinds]
    return dataclasses.replace(
        axial,
        attrs={**axial.attrs, "diameters_m": sizes, "phases_per_kind": fits[0].n_phases, "moving_phases": moving},
    )


def choose_phases(
    sequences: CompartmentSequences, steady_time_s: float | None, settings: PhaseSettings | None = None
) -> tuple[int, float]:
    """(K, gain): the moving phases per chain for the sequences' axial grid, and the held-out
    gain behind the choice. One chain of :data:`PHASES` and one of :data:`PHASES_FINE` phases
    are fitted to the particles that entered in the first half of the steady window's
    entries (with its residents, as :func:`table_with_phases` fits) and scored on those that
    entered in the second;
    :data:`PHASES_FINE` when it gains at least :data:`PHASE_GAIN_MIN` per particle-step.
    A finer grid resolves more of the blades' short-range exchange, and the phases that
    carry the long memory are then too few. The fits are ``settings``' (default
    :class:`PhaseSettings`) from one start. Raises ValueError when a half holds too few
    particles to fit."""
    settings = PhaseSettings() if settings is None else settings
    t0, t1 = steady_window(sequences, steady_time_s)
    first_seen = sequences.snapshot_t[sequences.start]
    entered = first_seen[(first_seen > t0) & (first_seen <= t1)]
    if entered.size == 0:
        raise ValueError(f"no particle entered in ({t0:g}, {t1:g}] s to choose the phases on")
    middle = 0.5 * (t0 + float(entered.max()))  # the entries' halves
    grid = (sequences.nx, 1)
    lag = settings.lag_dumps(sequences.interval_s)
    # the held-out particles in blocks of entry time: the gain per block, paired, so that a
    # gain the held-out data cannot tell from noise (a small run) keeps the default
    edges = np.linspace(middle, float(entered.max()), GAIN_BLOCKS + 1)
    blocks = [prepare(sequences, (a, b), grid=grid, lag=lag) for a, b in zip(edges[:-1], edges[1:])]
    blocks = [block for block in blocks if block.n_steps]
    if not blocks:
        raise ValueError("no particle entered in the second half of the steady window to score the phases on")
    train = prepare(sequences, (t0, middle), grid=grid, lag=lag, residents=True)
    fits = {
        k: PhaseEstimator(dataclasses.replace(settings, n_phases=k, starts=1)).fit(train).fetch_model()
        for k in (PHASES, PHASES_FINE)
    }
    gains = [(fits[PHASES_FINE].score(block) - fits[PHASES].score(block)) / block.n_steps for block in blocks]
    gains_a, weights = np.asarray(gains), np.asarray([block.n_steps for block in blocks], float)
    gain = float(np.average(gains_a, weights=weights))
    if gains_a.size < 2:
        return PHASES, gain
    spread = float(np.sqrt(np.average((gains_a - gain) ** 2, weights=weights) / (gains_a.size - 1)))
    clear = gain - 2.0 * spread >= PHASE_GAIN_MIN / 2
    return (PHASES_FINE if gain >= PHASE_GAIN_MIN and clear else PHASES), gain


def phases_per_kind(model: PhaseTransport) -> int:
    """The phases of each kind of a population (:func:`table_with_phases` by size), or all
    of a model fitted as one chain."""
    return int(model.attrs.get("phases_per_kind", model.n_phases))


def moving_phases(model: PhaseTransport) -> int:
    """The K that :func:`table_with_phases` was asked for to fit ``model``, so that a refit
    fits the same way: a chain per size class has its dead zone beside the K."""
    return int(model.attrs.get("moving_phases", phases_per_kind(model)))


def fits_record(fits: tuple[PhaseFit, ...], model: PhaseTransport) -> dict:
    """What a results summary keeps of :func:`table_with_phases`' fits: one fit's record
    (:func:`fit_record`), or for a chain per size class the classes' records with their
    diameters, and the totals (phases, wall time) beside them."""
    if len(fits) == 1:
        return fit_record(fits[0])
    return {
        "n_phases": model.n_phases,
        "phases_per_kind": fits[0].n_phases,
        "grid": [model.nx, 1],
        "observed_grid": [model.nx, 1],
        "iterations": int(sum(f.iterations for f in fits)),
        "wall_time_s": float(sum(f.wall_time_s for f in fits)),
        "by_size": [{"diameter_m": d, **fit_record(f)} for d, f in zip(model.attrs.get("diameters_m", []), fits)],
    }


def fit_record(fit: PhaseFit) -> dict:
    """What a results summary keeps of a phase fit (the model itself lives in the table)."""
    model = fit.transport
    return {
        "n_phases": fit.n_phases,
        "grid": [model.nx, model.ny],
        "observed_grid": list(model.attrs.get("observed_grid", [model.nx, model.ny])),
        "log_likelihood": fit.log_likelihood,
        "n_particles": fit.n_particles,
        "n_steps": fit.n_steps,
        "iterations": fit.iterations,
        "converged": fit.converged,
        "start_log_likelihoods": list(fit.start_log_likelihoods),
        "wall_time_s": fit.wall_time_s,
        "entry_phase_A": model.entry[0].tolist(),
        "entry_phase_B": model.entry[1].tolist(),
        "implied_timescales_s": fit.implied_timescales().tolist(),
        **{
            key: float(model.attrs[key])
            for key in ("stagnant_exit_max_per_s", "zone_entry_scale")
            if key in model.attrs
        },
    }
