"""Hidden mobility phases fitted to every particle's compartment sequence (EM / Baum-Welch).

The measured-rate chain (:mod:`dem.rates`) is Markov on compartments alone, and the DEM's
particles are not: the ones that stay long keep staying (slow bed), the fast ones keep
running (the stream over the bed). Here each particle also carries a hidden phase h =
0..K-1 and the chain is Markov on (compartment, phase): :class:`coupling.phases.PhaseTransport`,
a generator Q with phase-dependent nearest-neighbour rates, phase switching inside each
compartment and an entry-phase distribution per feeder. K = 1 is the measured-rate chain.

Data: :class:`dem.tracking.CompartmentSequences`, every particle's compartment at every
dump (interval Delta) from its first sight until it passes the weir (absorbing) or the
record ends (censored: its likelihood is that of the part seen).

Likelihood. With P = expm(Q Delta), a particle's sequence c_0, c_1, ..., c_T has
probability sum over phase paths of pi(h_0) prod_t P[(c_{t-1}, h_{t-1}), (c_t, h_t)]: a
hidden Markov model whose observation pins the compartment, so the forward-backward
recursion runs over the K phases only, K^2 per particle-step (a general HMM on the
S*K states would cost (S*K)^2). It is vectorised over particles: sequences sorted by
length, step t of all particles still followed is one gather of their (K, K) blocks of P
and one batched product.

EM. E-step: forward-backward gives, for every compartment pair seen between dumps, the
expected number of (c, h) -> (c', h') transitions over one interval (soft counts C) and
the posterior entry phase. M-step: the entry distribution is the mean posterior entry
phase per feeder; Q maximises sum_ab C_ab log P_ab(Q), which is exactly the likelihood of
a discretely observed chain that :func:`dem.rates.fit_pattern` maximises (L-BFGS with the
exact gradient through expm's Frechet derivative, capped at :data:`PHASE_MAX_RATE_X_INTERVAL` / Delta), here on the
(compartment, phase) states, warm-started from the previous iteration. It need not be
maximised: a generalised EM only has to increase it at each M-step. The default M-step
(``PhaseSettings.m_step = "em"``) makes a few updates of the classic EM of a discretely observed
continuous-time chain instead: each rate becomes the expected number of its jumps over the
expected time spent in its source state, both read off the same Frechet derivative that
gives dem.rates its gradient (:func:`dem.phases.estimator._ctmc_em_steps`), one derivative per update. On the
validation run's first 20 s (10 x 10, K = 2, 1.4e5 particle-steps) it reached the
L-BFGS M-step's log-likelihood (20 L-BFGS iterations per M-step) in half the EM
iterations and a tenth of the time per iteration (0.86 s against ~4.7 s); on 10 x 1 both
end at the same likelihood in 32 iterations, 6 s against 26 s. The fit stops when the
log-likelihood gains less than ``PhaseSettings.tol`` nats per particle-step.

Cost (:mod:`dem.phases.kernels`): numba-compiled, the E-step is not the cost; the matrix
exponentials of the M-step are. Continuous time, not a discrete chain at the dump interval
(:mod:`dem.phases.discrete`): the PBM needs a generator, and the discrete chain's
projected logarithm does not keep its RTD. The generator is the model.

Identifiability. Phases have no names: any relabelling fits equally well. After the fit
they are ordered by mobility, slowest first (:func:`coupling.phases.mobility`: forward
axial rate weighted by the expected time each phase spends in each compartment). Starts:
start 0 splits the K = 1 rates into phases whose rates are the K = 1 rates times
geometrically spaced factors (0.3 ... 3), switching at 0.2 /s and a uniform entry; the
others draw the factors, the switching rates and the entry at random (seeded). Every
start is run to convergence and the best kept; the spread of their log-likelihoods is
reported (:attr:`PhaseFit.start_log_likelihoods`).

The package, by role: :mod:`~dem.phases.data` (the sequences as fit-ready arrays,
:class:`PhaseData`; synthetic sequences), :mod:`~dem.phases.kernels` (forward-backward,
the CK tallies), :mod:`~dem.phases.settings` (:class:`PhaseSettings`, one default per
knob), :mod:`~dem.phases.estimator` (``PhaseEstimator(settings).fit(data).fetch_model()``
is a :class:`PhaseFit`; ``data`` one run or a list of runs fitted jointly),
:mod:`~dem.phases.chain` and :mod:`~dem.phases.diagnostics` (what a chain predicts; the
CK test, implied timescales, held-out log-likelihood), :mod:`~dem.phases.discrete` (the
discrete-time alternative), :mod:`~dem.phases.sizes` (size classes, dead zone) and
:mod:`~dem.phases.assembly` (the model into the velocity table, the choice of K, the
records).
"""

from dem.phases.assembly import (
    GAIN_BLOCKS,
    PHASE_GAIN_MIN,
    PHASES_FINE,
    axial_part,
    choose_phases,
    fit_record,
    fits_record,
    moving_phases,
    phases_per_kind,
    steady_transverse,
    table_with_phases,
    with_transverse,
)
from dem.phases.chain import check_grid, initial_distribution, mean_residence_time, steady_occupancy
from dem.phases.data import (
    FEEDERS,
    PhaseData,
    as_runs,
    coarsen,
    first_compartments,
    first_seen_in,
    prepare,
    sequences_from_padded,
    simulate_sequences,
    steady_window,
)
from dem.phases.diagnostics import CkTest, chapman_kolmogorov, implied_timescales, log_likelihood
from dem.phases.discrete import DiscretePhaseFit, fit_discrete, generator_from_transition
from dem.phases.estimator import PhaseEstimator, PhaseFit, one_phase, refined
from dem.phases.kernels import Expectations, forward_backward
from dem.phases.settings import (
    PHASE_LAG_S,
    PHASE_M_STEP_ITERATIONS,
    PHASE_MAX_ITERATIONS,
    PHASE_MAX_RATE_X_INTERVAL,
    PHASE_STARTS,
    PHASE_TOL,
    PHASES,
    ZONE_RESIDENCES,
    PhaseSettings,
)
from dem.phases.sizes import (
    MAX_CLASSES,
    MIN_KIND_PARTICLES,
    MIN_KIND_SHARE,
    QUANTILE_CLASSES,
    SAME_DIAMETER_M,
    kinds_by_size,
    little_residence_time,
    size_classes,
    zone_held_to_little,
)

__all__ = [
    "CkTest",
    "DiscretePhaseFit",
    "Expectations",
    "FEEDERS",
    "GAIN_BLOCKS",
    "MAX_CLASSES",
    "MIN_KIND_PARTICLES",
    "MIN_KIND_SHARE",
    "PHASES",
    "PHASES_FINE",
    "PHASE_GAIN_MIN",
    "PHASE_LAG_S",
    "PHASE_MAX_ITERATIONS",
    "PHASE_MAX_RATE_X_INTERVAL",
    "PHASE_M_STEP_ITERATIONS",
    "PHASE_STARTS",
    "PHASE_TOL",
    "PhaseData",
    "PhaseEstimator",
    "PhaseFit",
    "PhaseSettings",
    "QUANTILE_CLASSES",
    "SAME_DIAMETER_M",
    "ZONE_RESIDENCES",
    "as_runs",
    "axial_part",
    "chapman_kolmogorov",
    "check_grid",
    "choose_phases",
    "coarsen",
    "first_compartments",
    "first_seen_in",
    "fit_discrete",
    "fit_record",
    "fits_record",
    "forward_backward",
    "generator_from_transition",
    "implied_timescales",
    "initial_distribution",
    "kinds_by_size",
    "little_residence_time",
    "log_likelihood",
    "mean_residence_time",
    "moving_phases",
    "one_phase",
    "phases_per_kind",
    "prepare",
    "refined",
    "sequences_from_padded",
    "simulate_sequences",
    "size_classes",
    "steady_occupancy",
    "steady_transverse",
    "steady_window",
    "table_with_phases",
    "with_transverse",
    "zone_held_to_little",
]
