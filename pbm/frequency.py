"""Feeder-noise filtering of the blender: transfer functions and variance reduction ratios.

Between table switches the PBM is linear and time-invariant, dN/dt = G_n N + b F(t), with
G_n the (n, n) compartment block of :func:`pbm.model.generator_matrix`, b a feeder's inlet
distribution (:func:`pbm.model.feed_distribution`, one particle/s) and the outlet flux of
that feeder's species q(t) = c . N(t), c the last slice's forward rates (the OUT
accumulator row of the generator). The transfer function from the feeder's rate to its
outlet flux is

    H(s) = c (s I - G_n)^{-1} b,        H(0) = 1 (all that is fed leaves),

and H(i 2 pi f) is the Fourier transform of the residence-time distribution E(t) of
particles fed by that feeder, so an RTD (the DEM's) gives the same quantity
(:func:`transfer_function_from_rtd`).

Variance reduction ratio (Danckwerts 1953; Weinekoetter & Reh 1995). Feeder A's rate
F_A(1 + e(t)) fluctuates, feeder B's F_B is steady, C = F_A / (F_A + F_B). Composition of
what enters: C_in = F_A(1+e) / (F_A(1+e) + F_B), linearised
dC_in = C (1 - C) e. Composition of what leaves: C_out = q_A / (q_A + q_B) with q_B = F_B
exactly (B is steady and the system linear), so
dC_out = (F_B dq_A - F_A dq_B) / (F_A + F_B)^2 = C (1 - C) dq_A / F_A, and dq_A / F_A has
spectrum H_A(f) e(f). The factor C (1 - C) cancels in the ratio:

    VRR(f) = var(dC_in) / var(dC_out) = 1 / |H_A(f)|^2           (a sinusoid of frequency f)
    VRR    = int S(f) df / int S(f) |H_A(f)|^2 df                   (noise of spectrum S)

Noise of feeder B gives the same with H_B (dC_out = -C (1 - C) dq_B / F_B). Noise spectra
here are first order, S(f) = 1 / (1 + (2 pi f tau)^2) (white for tau = 0), band-limited to
[0, f_max] -- by default the Nyquist frequency 1 / (2 noise_interval_s) of a feeder whose
rate is set once per noise interval.

The stationary system of a time-varying table is that of one window or of the mean
generator over the windows starting at or after a time (:func:`stationary_system`): the
mean of generators is itself a generator (it conserves particles), the blender's mean
rates; it is an approximation of a table whose rates drift, exact for a steady one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm, schur

from coupling.errors import ConfigError, TableError
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.feed import resolve_feed
from pbm.fill import fill_reference, law_for, linearised
from pbm.model import feed_distribution, filled_table, generator_matrix, n_populations

#: Correlation times [s] of the first-order feeder noises studied (0: white noise).
NOISE_TAUS_S = (0.0, 1.0, 5.0, 20.0)
FEEDERS = ("A", "B")
# Samples per period of the time-domain check: sin and cos are then exactly orthogonal.
_SAMPLES_PER_PERIOD = 64


@dataclass(frozen=True)
class StationarySystem:
    """dN/dt = generator N + feed F(t) for one time-invariant window, and what reaches the
    outlet composition.

    ``generator`` (m, m) [1/s]: the compartment block; ``feed`` (m, 2): the inlet
    distribution of one particle/s of A (column 0) and B (column 1); ``outlet`` (2, m):
    row f, applied to the state, is feeder f's transfer to the outlet composition (per unit
    of its rate, normalised as its own outlet flux): for the linear PBM both rows are the
    compartments' discharge rates; under the fill law (:func:`pbm.fill.linearised`, m =
    2n: both species, since a feeder's noise moves the fill and so the other species' flow
    too) row A is dq_A - (F_A / F_B) dq_B and row B is dq_B - (F_B / F_A) dq_A.
    ``windows``: the table windows averaged. ``steady_holdup`` [particles]: under the fill
    law, the hold-up of the steady state it is linearised about (None for the linear PBM,
    whose hold-up is Little's law on ``generator``).
    """

    generator: np.ndarray
    feed: np.ndarray
    outlet: np.ndarray
    windows: np.ndarray
    steady_holdup: float | None = None

    def feed_column(self, feeder: str) -> np.ndarray:
        """The inlet distribution of ``feeder`` ("A" or "B")."""
        if feeder not in FEEDERS:
            raise ConfigError(f"unknown feeder {feeder!r}; valid: {', '.join(map(repr, FEEDERS))}")
        return self.feed[:, FEEDERS.index(feeder)]

    def outlet_row(self, feeder: str) -> np.ndarray:
        """The outlet functional of ``feeder``'s transfer (see the class)."""
        self.feed_column(feeder)  # names a bad feeder
        return self.outlet[FEEDERS.index(feeder)]


def stationary_system(
    table: VelocityTable, config: PbmConfig | None = None, window: int | None = None, t_start_s: float = 0.0
) -> StationarySystem:
    """The time-invariant system of window ``window`` of ``table``, or (``window`` None) of
    the mean generator over the windows that start at or after ``t_start_s`` [s].

    ``config`` (default :class:`PbmConfig`) gives the rate mode and the feed weights; the
    table is filled where its fields are missing (:func:`pbm.model.filled_table`) as
    :func:`pbm.simulate.simulate` does. Raises ConfigError for a window index outside
    0..K-1 or a ``t_start_s`` after the last window's start.
    """
    config, _ = resolve_feed(config, table)  # the run's simulate() names any override
    k_count = table.n_windows
    if window is not None:
        if isinstance(window, bool) or int(window) != window or not 0 <= window < k_count:
            raise ConfigError(f"window must be an integer in 0..{k_count - 1} (the table's windows), got {window!r}")
        windows = np.array([int(window)])
    else:
        if not math.isfinite(t_start_s):
            raise ConfigError(f"t_start_s must be a finite time [s], got {t_start_s}")
        windows = np.nonzero(table.t >= t_start_s)[0]
        if windows.size == 0:
            raise ConfigError(
                f"t_start_s = {t_start_s} s is after the last window's start {table.t[-1]} s; "
                f"valid: t_start_s <= {table.t[-1]} s"
            )
    if config.rate_law == "fill":
        return _fill_law_system(table, config, windows)
    filled, _ = filled_table(table, config.rates)
    n = n_populations(table, config.rates)  # NX*NY, times K phases in mode "phases"
    g = generator_matrix(filled, windows, config.rates).mean(axis=0)
    return StationarySystem(
        generator=g[:n, :n].copy(),
        feed=feed_distribution(table, config.feed_weights_a, config.feed_weights_b, config.rates),
        # Row n is the OUT accumulator: its entries are the compartments' discharge rates.
        outlet=np.stack([g[n, :n], g[n, :n]]),
        windows=windows,
    )


def _fill_law_system(table: VelocityTable, config: PbmConfig, windows: np.ndarray) -> StationarySystem:
    """The fill-law PBM linearised about its steady state at the config's feed rates
    (:func:`pbm.fill.linearised`); the law's reference is the table's steady windows."""
    rates = np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s])
    if not np.all(rates > 0):
        raise ConfigError(
            f"the fill law's frequency response needs both feed rates > 0 (the composition's response mixes "
            f"them), got A = {rates[0]:g}, B = {rates[1]:g} particles/s"
        )
    feed = feed_distribution(table, config.feed_weights_a, config.feed_weights_b, config.rates)
    lin = linearised(fill_reference(table, config.rates), law_for(table, config), feed, rates)
    rows = np.stack(
        [lin.outlet[0] - rates[0] / rates[1] * lin.outlet[1], lin.outlet[1] - rates[1] / rates[0] * lin.outlet[0]]
    )
    return StationarySystem(lin.generator, lin.feed, rows, windows, float(lin.species.sum()))


def transfer_function(
    table: VelocityTable,
    config: PbmConfig | None,
    frequencies_hz,
    window: int | None = None,
    feeder: str = "A",
    t_start_s: float = 0.0,
) -> np.ndarray:
    """H(i 2 pi f) from ``feeder``'s rate to its outlet flux, at ``frequencies_hz`` [Hz, >= 0].

    The system is :func:`stationary_system` (``window``, else the mean generator over the
    windows from ``t_start_s``). Returns a complex array shaped like ``frequencies_hz``;
    H(0) = 1 when every compartment drains to the outlet. Raises ConfigError for a negative
    or non-finite frequency or an unknown feeder, TableError when the generator is singular
    at a requested frequency (at f = 0: particles that can never leave).
    """
    system = stationary_system(table, config, window, t_start_s)
    return system_response(system, frequencies_hz, feeder)


def system_response(system: StationarySystem, frequencies_hz, feeder: str = "A") -> np.ndarray:
    """:func:`transfer_function` of an already built :class:`StationarySystem`."""
    freqs = _frequencies(frequencies_hz)
    b = system.feed_column(feeder)
    omegas = 2 * np.pi * freqs.ravel()
    # One real Schur form G = U T U^T, then a back substitution per frequency through its
    # 1 x 1 and 2 x 2 diagonal blocks: (i w I - G)^{-1} b = U (i w I - T)^{-1} U^T b.
    # Orthogonal, so as stable as an LU per frequency at a fraction of its cost; an
    # eigendecomposition would be cheaper still, but advection-dominated generators are
    # nearly defective (a chain of equal tanks is a Jordan block) and their eigenvectors
    # too ill-conditioned to trust. The real form costs half the complex one (5 against 10
    # ms at 100 states), and its blocks are solved in place rather than converted.
    t, u = schur(system.generator, output="real")
    rhs = u.T @ b
    left = system.outlet_row(feeder) @ u
    eigenvalues = _quasi_triangular_eigenvalues(t)
    gaps = np.abs(1j * omegas[:, None] - eigenvalues[None, :])
    singular = np.min(gaps, axis=1) <= 1e-13 * max(1.0, np.abs(eigenvalues).max())
    if singular.any():
        raise TableError(
            f"sI - G is singular at {freqs.ravel()[np.argmax(singular)]} Hz for windows {system.windows.tolist()}: "
            "some compartment never drains to the outlet"
        )
    return _responses(t, rhs, left, omegas).reshape(freqs.shape)


def _quasi_triangular_eigenvalues(t: np.ndarray) -> np.ndarray:
    """The eigenvalues of a real Schur form: its 1 x 1 diagonal blocks, and the conjugate
    pair of each 2 x 2 block (a non-zero subdiagonal entry)."""
    n = t.shape[0]
    out = np.empty(n, dtype=complex)
    i = 0
    while i < n:
        if i + 1 < n and t[i + 1, i] != 0.0:
            half_trace = 0.5 * (t[i, i] + t[i + 1, i + 1])
            det = t[i, i] * t[i + 1, i + 1] - t[i, i + 1] * t[i + 1, i]
            root = np.sqrt(complex(half_trace * half_trace - det))
            out[i], out[i + 1] = half_trace + root, half_trace - root
            i += 2
        else:
            out[i] = t[i, i]
            i += 1
    return out


def _responses_reference(t, rhs, left, omegas):
    """:func:`_responses` in numpy (its reference in the tests): a dense solve per frequency."""
    eye = np.eye(t.shape[0])
    return np.array([left @ np.linalg.solve(1j * w * eye - t, rhs) for w in omegas])


def _responses(t, rhs, left, omegas):
    """left . (i w I - T)^{-1} rhs for every w in ``omegas``, T real quasi-upper-triangular
    (a real Schur form): back substitution from the last row up, every frequency of a row
    at once, a 1 x 1 diagonal block by division and a 2 x 2 block by Cramer's rule. In
    numpy: at 100 states and 201 frequencies it took 1.7 ms against 7.5 for the Schur form
    before it (a scratch timing); a compiled loop took 0.7 ms but half a second to import and load, more than
    a design search's hundred responses gain from it."""
    n = t.shape[0]
    s = 1j * np.asarray(omegas, dtype=float)
    x = np.zeros((n, s.size), dtype=complex)
    i = n - 1
    while i >= 0:
        if i > 0 and t[i, i - 1] != 0.0:
            top = i - 1
            acc = rhs[i] + t[i, i + 1 :] @ x[i + 1 :]
            acc2 = rhs[top] + t[top, i + 1 :] @ x[i + 1 :]
            # [[s - a, -b], [-c, s - d]] [x_top, x_i] = [acc2, acc]
            a, b, c, d = t[top, top], t[top, i], t[i, top], t[i, i]
            det = (s - a) * (s - d) - b * c
            x[top] = ((s - d) * acc2 + b * acc) / det
            x[i] = ((s - a) * acc + c * acc2) / det
            i = top - 1
        else:
            x[i] = (rhs[i] + t[i, i + 1 :] @ x[i + 1 :]) / (s - t[i, i])
            i -= 1
    return left @ x


def transfer_function_from_rtd(t_s, E_per_s, frequencies_hz) -> np.ndarray:
    """H(i 2 pi f) = int E(t) exp(-i 2 pi f t) dt of a residence-time density ``E_per_s`` [1/s].

    ``t_s`` [s] is either

    * K equally spaced points where E was sampled (a smooth E sampled finely): the
      rectangle rule sum E_k dt exp(-i w t_k), spectrally accurate for an E that vanishes
      smoothly at both ends; or
    * the K + 1 edges of K histogram bins of mean densities E_k (the DEM's and the PBM's
      pooled RTDs): a bin mean is a sample of E smoothed by a box of the bin's width w_k,
      whose transform is sinc(w w_k / 2), so the binning is undone,
      sum E_k w_k exp(-i w c_k) / sinc(w w_k / 2) with c_k the bin centres -- otherwise the
      bins themselves would read as attenuation (2 % at a tenth of the Nyquist frequency).

    Either way the data carry nothing above the Nyquist frequency 1 / (2 dt), or
    1 / (2 max w_k), and are accurate only where |H| there is negligible beside |H(f)|
    (aliasing): a frequency beyond the Nyquist frequency raises ConfigError, as do mismatched lengths and
    unordered times. H(0) is the integral of E given: normalise a truncated E first.
    """
    t = np.asarray(t_s, dtype=float)
    e = np.asarray(E_per_s, dtype=float)
    freqs = _frequencies(frequencies_hz)
    if e.ndim != 1 or e.size == 0 or not np.all(np.isfinite(e)):
        raise ConfigError(f"E_per_s must be a non-empty 1-D array of finite values, got shape {e.shape}")
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ConfigError(f"t_s must be a 1-D array of finite times [s], got shape {t.shape}")
    if t.size == e.size + 1:
        widths = np.diff(t)
        centres = 0.5 * (t[:-1] + t[1:])
        binned = True
    elif t.size == e.size:
        widths = np.diff(t)
        if e.size < 2 or not np.allclose(widths, widths[0], rtol=1e-6, atol=0.0):
            raise ConfigError(
                "t_s with as many entries as E_per_s must be at least 2 equally spaced points; "
                "give the K + 1 bin edges for unequal bins"
            )
        widths = np.full(e.size, widths[0])
        centres = t
        binned = False
    else:
        raise ConfigError(
            f"t_s has {t.size} entries and E_per_s {e.size}: give {e.size} equally spaced points or "
            f"{e.size + 1} bin edges"
        )
    if np.any(widths <= 0):
        raise ConfigError(f"t_s must increase strictly; it does not at index {int(np.argmax(widths <= 0))}")
    nyquist = 0.5 / widths.max()
    if np.any(freqs > nyquist * (1 + 1e-12)):
        raise ConfigError(
            f"frequency {freqs.max()} Hz is above the Nyquist frequency {nyquist} Hz of the RTD's "
            f"{widths.max()}-s {'bins' if binned else 'sampling'}; valid: 0..{nyquist} Hz"
        )
    omegas = 2 * np.pi * freqs.ravel()[:, None]
    kernel = np.exp(-1j * omegas * centres)
    if binned:
        # np.sinc(x) = sin(pi x) / (pi x) >= 2 / pi up to the Nyquist frequency.
        kernel /= np.sinc(omegas * widths / (2 * np.pi))
    return (kernel @ (e * widths)).reshape(freqs.shape)


def vrr_sinusoid(H) -> np.ndarray:
    """Variance reduction ratio of a sinusoidal feeder fluctuation: 1 / |H|^2 (inf where H = 0)."""
    magnitude2 = np.abs(np.asarray(H)) ** 2
    with np.errstate(divide="ignore"):
        return 1.0 / magnitude2


def noise_spectrum(frequencies_hz, tau_s: float) -> np.ndarray:
    """First-order (Ornstein-Uhlenbeck) relative spectrum 1 / (1 + (2 pi f tau)^2), up to a
    constant that cancels in the VRR; white for ``tau_s`` = 0. Raises ConfigError for a
    negative or non-finite ``tau_s``."""
    if not (math.isfinite(tau_s) and tau_s >= 0):
        raise ConfigError(f"tau_s (noise correlation time) must be a finite number >= 0 s, got {tau_s}")
    freqs = _frequencies(frequencies_hz)
    return 1.0 / (1.0 + (2 * np.pi * freqs * tau_s) ** 2)


def noise_frequencies(f_max_hz: float, n_frequencies: int = 2001) -> np.ndarray:
    """Quadrature grid over [0, f_max_hz] for :func:`vrr_spectrum`: 0, then log-spaced from
    1e-5 f_max, so that the low frequencies where |H| falls off are as well resolved as the
    flat high band. Raises ConfigError for f_max_hz <= 0 or fewer than 3 points."""
    if not (math.isfinite(f_max_hz) and f_max_hz > 0):
        raise ConfigError(f"f_max_hz must be a finite frequency > 0 Hz, got {f_max_hz}")
    if isinstance(n_frequencies, bool) or int(n_frequencies) != n_frequencies or n_frequencies < 3:
        raise ConfigError(f"n_frequencies must be an integer >= 3, got {n_frequencies!r}")
    return np.concatenate([[0.0], np.geomspace(1e-5 * f_max_hz, f_max_hz, int(n_frequencies) - 1)])


def vrr_spectrum(frequencies_hz, H, spectrum) -> float | np.ndarray:
    """VRR = int S df / int S |H|^2 df over the grid ``frequencies_hz`` (trapezoid rule),
    for a feeder noise of spectrum ``spectrum`` and a transfer function ``H`` on that grid
    (from the PBM or an RTD); ``H`` (..., F) gives one VRR per leading index (e.g. bootstrap
    replicates), a 1-D ``H`` a float. Raises ConfigError for mismatched shapes, an unordered
    grid or a spectrum that is negative or zero everywhere."""
    freqs = _frequencies(frequencies_hz)
    h = np.asarray(H)
    s = np.asarray(spectrum, dtype=float)
    if not (freqs.ndim == 1 and h.ndim >= 1 and freqs.shape == h.shape[-1:] == s.shape and freqs.size >= 2):
        raise ConfigError(
            f"frequencies_hz and spectrum must be 1-D of one length >= 2 and H's last axis as long, got shapes "
            f"{freqs.shape}, {h.shape}, {s.shape}"
        )
    if np.any(np.diff(freqs) <= 0):
        raise ConfigError("frequencies_hz must increase strictly")
    if np.any(s < 0) or not np.all(np.isfinite(s)) or not np.any(s > 0):
        raise ConfigError("spectrum must be finite, >= 0 and positive somewhere")
    vrr = np.trapezoid(s, freqs) / np.trapezoid(s * np.abs(h) ** 2, freqs, axis=-1)
    return float(vrr) if h.ndim == 1 else vrr


def vrr_noise(
    table: VelocityTable,
    config: PbmConfig | None,
    tau_s: float,
    f_max_hz: float | None = None,
    feeder: str = "A",
    window: int | None = None,
    t_start_s: float = 0.0,
    n_frequencies: int = 2001,
) -> float:
    """VRR of first-order noise of correlation time ``tau_s`` [s] on ``feeder``, band-limited
    to [0, ``f_max_hz``] (default the Nyquist frequency 1 / (2 config.noise_interval_s)),
    through the PBM's stationary system (:func:`transfer_function`)."""
    config, _ = resolve_feed(config, table)  # the run's simulate() names any override
    f_max = 0.5 / config.noise_interval_s if f_max_hz is None else float(f_max_hz)
    freqs = noise_frequencies(f_max, n_frequencies)
    spectrum = noise_spectrum(freqs, tau_s)
    h = transfer_function(table, config, freqs, window, feeder, t_start_s)
    return vrr_spectrum(freqs, h, spectrum)


def sinusoid_response(system: StationarySystem, frequencies_hz, feeder: str = "A", periods: int = 3) -> np.ndarray:
    """H measured in the time domain: the outlet flux of ``system`` fed sin(2 pi f t) on top
    of its steady feed, after its start-up transient, projected on sin and cos.

    The deviation from the steady state obeys dN/dt = G N + b sin(w t); the forcing is made
    autonomous by carrying (sin, cos) in the state, so the response at the sample times is
    exact matrix exponentials (no transfer function involved). The transient is left to
    decay for max(10 mean residence times, 30 / slowest decay rate) before ``periods``
    whole periods are sampled 64 times each; sin and cos are orthogonal on those samples, so
    their coefficients are H's real and imaginary parts (flux = Re H sin + Im H cos).
    Raises ConfigError for f <= 0 (no period to sample) and a bad feeder.
    """
    freqs = _frequencies(frequencies_hz)
    if np.any(freqs == 0):
        raise ConfigError("the time-domain check needs frequencies > 0 Hz; H(0) is the steady throughput")
    if isinstance(periods, bool) or int(periods) != periods or periods < 1:
        raise ConfigError(f"periods must be an integer >= 1, got {periods!r}")
    b = system.feed_column(feeder)
    g = system.generator
    n = g.shape[0]
    # Little's law at one particle/s: the steady hold-up is the mean residence time.
    mean_residence_s = float(np.linalg.solve(g, -b).sum())
    slowest_decay = float(-np.linalg.eigvals(g).real.max())
    if not slowest_decay > 0:
        raise TableError(f"the generator of windows {system.windows.tolist()} has a mode that never decays")
    settle_s = max(10.0 * mean_residence_s, 30.0 / slowest_decay)

    out = np.empty(freqs.size, dtype=complex)
    for idx, f in enumerate(freqs.ravel()):
        omega = 2 * np.pi * f
        m = np.zeros((n + 2, n + 2))
        m[:n, :n] = g
        m[:n, n] = b  # state n is sin(w t), state n + 1 is cos(w t)
        m[n, n + 1] = omega
        m[n + 1, n] = -omega
        z = np.zeros(n + 2)
        period = 1.0 / f
        # Start the sampling at a whole number of periods, so the phase at sample 0 is 0.
        cycles = math.ceil(settle_s / period)
        z[n + 1] = 1.0
        z = expm(m * (cycles * period)) @ z
        step = expm(m * (period / _SAMPLES_PER_PERIOD))
        samples = periods * _SAMPLES_PER_PERIOD
        flux = np.empty(samples)
        for k in range(samples):
            flux[k] = system.outlet_row(feeder) @ z[:n]
            z = step @ z
        phase = omega * period / _SAMPLES_PER_PERIOD * np.arange(samples)
        out[idx] = 2.0 / samples * (flux @ np.sin(phase) + 1j * (flux @ np.cos(phase)))
    return out.reshape(freqs.shape)


def sampled_ca_sd(
    system: StationarySystem,
    feed_rates,
    sigma: float,
    noise_interval_s: float,
    output_interval_s: float,
    n_frequencies: int = 4001,
) -> float:
    """Standard deviation of the outlet C_A, sampled as the flux-weighted mean over each
    output interval, when both feeders' rates are multiplied by independent factors
    N(1, sigma) redrawn every ``noise_interval_s`` (the PBM's noise ensemble), to first
    order in sigma.

    A rate held for Delta then redrawn (zero-order hold of white noise) has the one-sided
    spectrum 2 sigma^2 Delta sinc^2(f Delta); the output interval's mean filters by
    sinc^2(f T) more; each feeder's factor reaches the outlet through its H. With
    C = F_A / (F_A + F_B):

        var C_A = C^2 (1 - C)^2 sigma^2 int_0^inf 2 Delta sinc^2(f Delta) sinc^2(f T)
                  (|H_A|^2 + |H_B|^2) df.

    The integral runs to 50 / min(Delta, T) on a log grid (the integrand falls like f^-4
    beyond both: the tail left out is below 1e-6 of it). Averaged over the phase of the
    samples against the noise grid: exact for a blender slow against Delta."""
    rates = np.asarray(feed_rates, dtype=float)
    if rates.shape != (2,) or not np.all(np.isfinite(rates)) or np.any(rates < 0) or not rates.sum() > 0:
        raise ConfigError(f"feed_rates must be the two rates (A, B) >= 0 with a positive sum, got {feed_rates!r}")
    for name, value in (
        ("sigma", sigma),
        ("noise_interval_s", noise_interval_s),
        ("output_interval_s", output_interval_s),
    ):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be a finite number > 0, got {value}")
    c = rates[0] / rates.sum()
    f_max = 50.0 / min(noise_interval_s, output_interval_s)
    freqs = noise_frequencies(f_max, n_frequencies)
    gain = sum(np.abs(system_response(system, freqs, feeder)) ** 2 for feeder in FEEDERS)
    spectrum = 2 * noise_interval_s * np.sinc(freqs * noise_interval_s) ** 2 * np.sinc(freqs * output_interval_s) ** 2
    return float(c * (1 - c) * sigma * math.sqrt(np.trapezoid(spectrum * gain, freqs)))


def _frequencies(frequencies_hz) -> np.ndarray:
    freqs = np.asarray(frequencies_hz, dtype=float)
    bad = freqs[~(np.isfinite(freqs) & (freqs >= 0))]
    if bad.size:
        raise ConfigError(f"frequencies must be finite and >= 0 Hz, got {bad.ravel()[0]}")
    return freqs
