"""Per-anchor range biases as states of the EKF and the UKF.

The filters' state is extended with one constant bias per anchor, ``x_e = (x, b)``: the
dynamics ``x' = A x + B u``, ``b' = w_b`` (a random walk of intensity ``bias_walk``,
zero for constant biases) and the measurement of anchor ``h`` in the norm space of
:class:`~quadobs.estimators.kalman.OutputModel`,

.. math::

    h_h(x_e) = |p - a_h| + b_h, \\qquad
    \\frac{\\partial h_h}{\\partial x_e} = \\Big[\\frac{(p - a_h)^\\top}{|p - a_h|},\\ 0,\\ e_h^\\top\\Big],

which is :class:`~quadobs.core.measurements.RangeModel` with ``bias="state"``: its
:meth:`~quadobs.core.measurements.RangeModel.extra_states` give the biases' prior.
Everything else (exact held-input prediction, Joseph update, robust rules) is the
filters' own.

Start-up. Linearising ``|p - a_h|`` at an estimate ``e`` metres off errs by up to
``e^2 / (2 |p - a_h|)``: from 20 m off the first corrections point the wrong way, the
velocity takes metres per second of the error, and free bias states take the rest (a bias
of 1.8 m for an anchor whose bias is -0.14 m). Two rules keep the start-up error out of them:

* **Fix.** When the prior position is wider than the error of a multilateration of one
  round of ranges (:func:`fix_std`, ``sqrt(sigma^2 + sigma_b^2)`` from the stated range
  noise and the biases' prior), the filter waits for one range from every anchor (or two
  rounds' worth of ranges, when one is silent) and sets
  its position to their least-squares multilateration
  (:func:`~quadobs.estimators.robust.multilateration`: differences of the quadratic
  outputs are linear in the position), its position covariance to ``fix_std^2 I`` (its
  correlations dropped). The ranges the fix is made of (those that completed the round, or
  the grid step's or the time's batch that did) are not corrected by again: the fix's
  covariance is that of an error made of their noise, and a correction by them would take
  that noise as independent of it and count it twice (the covariance halved in the linear
  case, :mod:`quadobs.estimators.startup`); the ranges that follow are corrected from there.
  (The UKF needs the covariance too: sigma points spread over a 10 m prior straddle the
  anchors.)
* **Consider until consistent.** The biases' rows of the gain are held at zero (a Schmidt,
  or consider, update: their covariance and cross-covariances are carried, so the position
  knows how uncertain they are) until the normalised innovations of the last two rounds of
  anchors (``2 q`` ranges: ``2 q`` scalar corrections, or two joint ones of ``q`` ranges)
  sum below the gate's ``P`` quantile of ``chi^2`` of their degrees of freedom (39.25 for
  ``q = 8``, ``P = 0.999``; :class:`NisWindow`): the vehicle's state then explains the ranges within
  the biases' prior, and the biases are opened. A lock-out's re-initialisation puts the
  biases back to their prior mean and closes them again.

State of sight. Under an :class:`~quadobs.estimators.robust.ExcessMixture` each range's prior
probability of a blocked path comes from a per-anchor two-state chain on the filter's own
bias estimate (``sight_model="chain"``, the default), or, from the biases' opening, from each
anchor's joint posterior of its bias and its state of sight
(``sight_model="grid"``: :class:`~quadobs.estimators.robust.BiasSightGrid`, started where the
chain was). With the chain, ``onset_test`` (off by default) takes several clear chains turned
blocked within one round of the anchors as a position error, their joint onset being the
product of each chain's own Markov prior (:meth:`_VehicleBlock._onset`). ``steady_test`` (off
by default; on in the replay's ``ekf-bias-imu-nlos``) takes a block of an anchor's ranges read
blocked whose spread is the noise's, not an excess's, for its bias state's error: a bias
estimated low reads its clear anchor as blocked, and the chain then keeps the ranges from
correcting it (:meth:`_VehicleBlock._steady`); and the other way, a block of its ranges in
line of sight steadily short, which a bias estimated high rejects as outliers
(:meth:`_VehicleBlock._steady_short`).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from quadobs.core.measurements import Measurement, RangeModel
from quadobs.core.quantiles import chi2_cdf, chi2_ppf
from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError
from quadobs.estimators.constants import ConstantStates
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.robust import (
    BiasSightGrid,
    ChiSquareGate,
    ExcessMixture,
    LockOut,
    chi2_threshold,
    multilateration,
)

__all__ = [
    "BiasedExtendedKalmanFilter",
    "BiasedRangeOutputModel",
    "BiasedUnscentedKalmanFilter",
    "biased_models",
    "extended_system",
    "steady_block",
    "steady_offset",
]


def extended_system(system: QuadraticSystem, linear: bool = False) -> QuadraticSystem:
    """``system`` with one constant state per output appended: ``A_e = blockdiag(A, 0)``,
    ``B_e = (B, 0)``, ``C_e,h = blockdiag(C_h, 0)``, ``d_e,h = (d_h, 0)``; with ``linear``,
    ``d_e,h = (d_h, e_h)`` (``e_h`` the unit vector): output ``h``'s constant enters it
    linearly."""
    n, q = system.n, system.q
    A = np.zeros((n + q, n + q))
    A[:n, :n] = system.A
    B = np.vstack([system.B, np.zeros((q, system.p))])
    C = np.zeros((q, n + q, n + q))
    C[:, :n, :n] = system.C
    d = np.hstack([system.d, np.eye(q) if linear else np.zeros((q, q))])
    return QuadraticSystem(A, B, C, d)


class BiasedRangeOutputModel(OutputModel):
    """The norm-space range model with each output's bias read from the extended state.

    Built by :func:`biased_models`; ``system`` is the :func:`extended_system`, ``offsets``
    the anchors' ``|a_h|^2 / 2``.
    """

    def predict(self, x: np.ndarray) -> np.ndarray:
        q = self.system.q
        return super().predict(x) + x[..., -q:]

    def linearize(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = self.system.q
        s, J = super().linearize(x)
        J = J.copy()
        J[:, -q:] += np.eye(q)
        return s + x[-q:], J


def biased_models(
    system: QuadraticSystem,
    dt: float,
    sigma: float,
    input_std: float,
    P0: np.ndarray,
    model: RangeModel,
    bias_walk: float = 0.0,
    bias_std: float | None = None,
) -> tuple[HeldInputModel, BiasedRangeOutputModel, np.ndarray]:
    """The dynamics, measurement model and prior of a filter with bias states.

    Parameters
    ----------
    system : QuadraticSystem
        A range system (:func:`quadobs.core.system.vehicle_system`).
    dt, sigma, input_std : float
        Physics step (s), range noise (m), accelerometer noise (m/s^2).
    P0 : ndarray (n, n)
        The prior of ``x``.
    model : RangeModel
        With ``bias="state"``: its extra states give the biases' prior.
    bias_walk : float
        Random-walk intensity of the biases (m^2/s).
    bias_std : float, optional
        The biases' prior standard deviation (m), where the hardware states their spread;
        default: the model's extra states' prior.
    """
    extra = model.extra_states()
    if len(extra) != system.q:
        raise QuadobsError(
            f"model: expected one bias state per output ({system.q}), got {len(extra)} "
            "(RangeModel(bias='state'))"
        )
    ext = extended_system(system)
    n, q = system.n, system.q
    V = np.zeros((n + q, n + q))
    V[n:, n:] = bias_walk * np.eye(q)
    dynamics = HeldInputModel(ext, dt, V=V, input_covariance=input_std**2)
    offsets = 0.5 * np.einsum("hi,hi->h", system.d, system.d)
    outputs = BiasedRangeOutputModel(ext, sigma**2 * np.eye(q), offsets=offsets)
    Pe = np.zeros((n + q, n + q))
    Pe[:n, :n] = P0
    prior = [e.prior_std if bias_std is None else bias_std for e in extra]
    if not all(math.isfinite(v) and v > 0.0 for v in prior):
        raise QuadobsError(f"bias_std: expected a positive number of metres, got {bias_std!r}")
    Pe[n:, n:] = np.diag(np.square(prior))
    return dynamics, outputs, Pe


def fix_std(R: np.ndarray, P_bias: np.ndarray) -> float:
    """The error to expect of a multilateration of one round of ranges: the range noise and the
    biases' prior together, ``sqrt(max_h R_hh + max_h P_bias,hh)`` (m); a prior position wider
    than this is replaced by the multilateration (the module docstring's "Start-up")."""
    return math.sqrt(float(np.max(np.diag(R))) + float(np.max(np.diag(P_bias), initial=0.0)))


@functools.lru_cache(maxsize=8)
def steady_block(probability: float) -> tuple[int, float, float]:
    """The steady-offset test's block ``N``, the median of ``chi^2(N - 1)`` and ``z`` (``z^2``
    the ``probability`` quantile of ``chi^2(1)``): ``N`` the fewest ranges (from 3) at which
    ``chi^2(N - 1)`` scaled by 2 (an excess as spread as the noise) falls at or below that
    median with probability at most ``1 - probability`` (51 at 0.999)."""
    z = math.sqrt(chi2_threshold(probability, 1))
    for n in range(3, 1000):
        median = chi2_ppf(0.5, n - 1)
        if chi2_cdf(median / 2.0, n - 1) <= 1.0 - probability:
            return n, median, z
    raise QuadobsError(f"steady test: no block for the probability {probability}")


def steady_offset(
    block: np.ndarray,
    probability: float,
    counts: bool,
    nu: float,
    R: float,
    sign: float,
    per_range: bool = False,
) -> float | None:
    """One range of the steady-offset test (:meth:`_VehicleBlock._steady`): added to ``block``
    (its count and the sums of ``1 / R``, ``nu / R``, ``nu^2 / R``, in place) where it
    ``counts``, else the block restarted. At ``N`` ranges (:func:`steady_block`) the block is
    tested and restarted: its mean ``hat delta`` is returned where the spread ``Q`` is at most
    the median of ``chi^2(N - 1)`` and ``sign * hat delta`` exceeds ``z / sqrt(sum 1 / R)``
    (the mean's bound), or with ``per_range`` ``z sqrt(N / sum 1 / R)`` (one range's bound:
    an offset its gate rejects), else None."""
    if not counts:
        if block[0]:
            block[:] = 0.0
        return None
    w = 1.0 / R
    block[0] += 1.0
    block[1] += w
    block[2] += w * nu
    block[3] += w * nu * nu
    n, median, z = steady_block(probability)
    if block[0] < n:
        return None
    delta = float(block[2] / block[1])
    spread = block[3] - block[2] * delta
    bound = z * math.sqrt(n if per_range else 1.0)
    steady = spread <= median and sign * delta * math.sqrt(block[1]) > bound
    block[:] = 0.0
    return delta if steady else None


def _gate_probability(rule) -> float:
    """The probability of the filter's gate, else the default gate's (0.999)."""
    return float(getattr(rule, "probability", ChiSquareGate().probability))


def _sight_model(name: str) -> str:
    """``"chain"`` or ``"grid"``: how an :class:`~quadobs.estimators.robust.ExcessMixture`
    filter keeps each anchor's state of sight (:class:`_VehicleBlock`)."""
    if name not in ("chain", "grid"):
        raise QuadobsError(f"sight_model: expected 'chain' or 'grid', got {name!r}")
    return name


class NisWindow:
    """The latest NIS values of a filter, each with its degrees of freedom, covering ``length``
    degrees of freedom in all, and the test that their sum is consistent.

    A correction by ``k`` outputs together adds one NIS of ``k`` degrees of freedom; the window
    keeps the fewest latest values whose degrees of freedom sum to at least ``length`` (``length``
    scalar ranges, or as many ranges in joint corrections). Under the model the sum of
    independent NIS values of ``k_i`` degrees of freedom follows ``chi^2(sum_i k_i)``, so
    :meth:`consistent` tests ``sum_i NIS_i <= chi^2_probability(sum_i k_i)``.

    Parameters
    ----------
    length : int
        Degrees of freedom the window covers (``2q``: two rounds of ``q`` anchors).
    probability : float
        The quantile of the test.
    """

    def __init__(self, length: int, probability: float) -> None:
        self.length = int(length)
        self.probability = float(probability)
        self._values: deque = deque()
        self.dof = 0
        self._thresholds: dict[int, float] = {}

    def __len__(self) -> int:
        return len(self._values)

    def threshold(self, dof: int) -> float:
        """``chi^2_probability(dof)`` (cached by ``dof``)."""
        hit = self._thresholds.get(dof)
        if hit is None:
            hit = self._thresholds[dof] = chi2_threshold(self.probability, dof)
        return hit

    def append(self, nis: float, dof: int) -> None:
        """Add one NIS of ``dof`` degrees of freedom, dropping the oldest ones no longer needed."""
        w = self._values
        w.append((nis, int(dof)))
        self.dof += int(dof)
        while self.dof - w[0][1] >= self.length:
            self.dof -= w.popleft()[1]

    def consistent(self) -> bool:
        """Whether the window covers ``length`` degrees of freedom and its sum is within
        ``chi^2_probability(dof)``."""
        if self.dof < self.length:
            return False
        return sum(v for v, _ in self._values) <= self.threshold(self.dof)

    def clear(self) -> None:
        """Empty the window."""
        self._values.clear()
        self.dof = 0


class _VehicleBlock(ConstantStates):
    """Reports the vehicle's state ``x`` (the first ``n`` entries), keeps the biases apart,
    and starts the biases only once the vehicle's state is known (the module docstring's
    "Start-up").

    Attributes
    ----------
    fixes : list of float
        Times (s) at which the position was set by multilateration.
    opened_at : list of float
        Times (s) at which the bias states were opened (after the start or a re-initialisation).
    held : int
        Corrections whose bias rows of the gain were held at zero.
    steady_offsets : list of float
        Times (s) at which the steady-offset test (:attr:`steady_test`) took a block of an
        anchor's ranges (read blocked, or in line of sight and short) for its bias's error.
    """

    vehicle_n: int = 0
    sight_model: str = "chain"
    #: At the start-up's fix, one joint correction by its round of ranges linearised at the
    #: multilateration (:meth:`_correct_at_fix`) instead of the fix's covariance ``fix_std^2 I``.
    fix_correction: bool = False
    sight: BiasSightGrid | None = None
    #: The Markov onset test (:meth:`_onset`; off by default: measured on part of the flights
    #: only, ``docs/error-sources.md``) and its window (s; 0: one round of the anchors).
    onset_test: bool = False
    onset_window: float = 0.0
    _onset_pending: bool = False
    #: The steady-offset test (:meth:`_steady`, :meth:`_steady_short`): a block of ranges read
    #: blocked whose spread is the noise's, not the excess's, or of ranges in line of sight
    #: steadily short, taken as the anchor's bias error. It reads the chain, so it does nothing
    #: with ``sight_model="grid"``.
    steady_test: bool = False
    _steady_pending: tuple[int, float] | None = None
    fix_pending: bool = False
    fix_abandoned: float | None = None
    biases_open: bool = True
    open_threshold: float = 0.0
    held: int = 0
    fixes: list
    opened_at: list
    onsets: list
    steady_offsets: list
    _bias_prior: np.ndarray
    _fix_var: float
    _waited: int
    _nis_window: NisWindow
    # the filter's own (the class this one is mixed into); declared for the type checker only
    _x: np.ndarray
    _P: np.ndarray
    _P0: np.ndarray
    dynamics: HeldInputModel
    _latest: np.ndarray
    _time: float
    nis: float
    nis_dof: int
    corrections: int
    rejected: int
    robust: object
    gate: float | None
    lockout: LockOut
    outputs: OutputModel
    if TYPE_CHECKING:

        def _settle(self) -> None: ...
        def _model_of(self, m: Measurement) -> RangeModel: ...

    def _start_block(self, vehicle_n: int, probability: float) -> None:
        """Set the start-up state: a fix pending when the prior position is wider than a
        multilateration's error, the biases closed until the innovations say the vehicle's
        state is known (window of two rounds of anchors, ``chi^2`` at ``probability``)."""
        self.vehicle_n = k = int(vehicle_n)
        q = self._x.shape[0] - k
        self._bias_prior = self._x[k:].copy()
        self.fixes, self.opened_at, self.held = [], [], 0
        self._set_fix_spread()
        self._waited = 0
        self.biases_open = False
        self._nis_window = NisWindow(2 * q, probability)
        self._anchor = -1
        self._nlos = np.zeros(q)  # each anchor's chain starts in line of sight
        self._nlos_time = np.full(q, self._time)
        self._onset_at = np.full(q, -math.inf)  # when each chain turned blocked (onset test)
        self._onset_pre = np.zeros(q)  # its posterior before it turned
        self._onset_nu = np.zeros(q)  # the innovation that turned it
        self._onset_fire = np.zeros(q, dtype=bool)
        self._onset_pending = False
        self.onsets = []
        # each anchor's block of ranges read blocked (the steady-offset test): count, sums of
        # 1 / R, nu / R and nu^2 / R
        self._block = np.zeros((q, 4))
        self._short = np.zeros((q, 4))  # and of ranges in line of sight (the other way)
        self._steady_pending = None
        self.steady_offsets = []
        self.sight = None  # the ExcessMixture's BiasSightGrid, from the biases' opening
        self.open_threshold = self._nis_window.threshold(2 * q)

    def _set_fix_spread(self) -> None:
        """Whether a fix is pending (the prior position wider than a multilateration's error)
        and the fix's variance, from the biases' covariance."""
        k = self.vehicle_n
        d = int(self.outputs.system.p)  # the position block: as many entries as inputs
        prior_std = math.sqrt(float(np.max(np.diag(self._P)[:d])))
        std = fix_std(self.outputs.R, self._P[k:, k:])
        self.fix_pending = prior_std > std
        self._fix_var = std * std

    def _shape_gain(self, K: np.ndarray, nu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """The biases' rows of the gain held at zero until they are open (a consider update)."""
        if self.biases_open:
            return K
        self.held += 1
        K = K.copy()
        K[self.vehicle_n :] = 0.0
        return K

    def _gain(self, nu: np.ndarray, S: np.ndarray, R: np.ndarray, cross: np.ndarray):
        """With an :class:`~quadobs.estimators.robust.ExcessMixture` rule, a range's update
        corrected by its expected non-line-of-sight excess: ``x += K (nu - E[e | nu])`` with
        ``K = cross S^-1`` (as the bias rows are shaped), and ``(S, R)`` grown by
        ``Var[e | nu]`` for the covariance (the exact collapse of the Gaussian sum); the NIS
        is that of the corrected innovation. The range's prior probability of a blocked path
        comes from :attr:`sight_model` (the module docstring). The filter's ``gate``, where it
        has one, judges that NIS as it judges any correction's: a range beyond it is rejected
        and leaves the state of sight as it was. Any other rule: the filter's own."""
        rule, h = self.robust, self._anchor
        if not isinstance(rule, ExcessMixture) or h < 0 or nu.shape[0] != 1:
            return super()._gain(nu, S, R, cross)  # type: ignore[misc]
        k = self.vehicle_n
        if self.sight is None and self.biases_open and self.sight_model == "grid":
            std = np.sqrt(np.diag(self._P)[k:])
            self.sight = BiasSightGrid(rule, self._x[k:], std, start=self._nlos)
            self.sight.time[:] = self._nlos_time
        if self.sight is None:
            nlos = rule.prior(self._nlos[h], self._time - self._nlos_time[h])
        else:
            nlos = self.sight.predict(h, self._time)
        post = rule.posterior(float(nu[0]), float(S[0, 0]), nlos)
        if post is not None and self.gate is not None:  # the filter's own gate on the NIS
            if (nu[0] - post[0]) ** 2 / (S[0, 0] + post[1]) > self.gate:
                post = None
        if self.steady_test and self.sight is None:  # a bias too high: short and clear ranges
            clear = nu[0] < 0.0 if post is None else post[2] < 0.5
            self._steady_short(rule, h, clear, float(nu[0]), float(R[0, 0]))
        if post is None:
            nis = float(nu[0] ** 2 / S[0, 0]) if S[0, 0] > 0.0 else math.inf
            self.nis, self.nis_dof = nis, 1
            self.rejected += 1
            self._watch(False, nu)
            return None
        shift, var, p_nlos = post
        if self.sight is None:
            if self.onset_test:
                self._onset(rule, h, nlos, p_nlos, float(nu[0]))
            if self.steady_test:
                self._steady(rule, h, p_nlos, float(nu[0]), float(R[0, 0]))
            self._nlos[h], self._nlos_time[h] = p_nlos, self._time
        else:
            # the anchor's (bias, sight) posterior takes the range less the predicted distance,
            # of the variance of the position and the noise: S less the bias's part of it
            j = k + h
            S_p = float(S[0, 0] - 2.0 * cross[j, 0] + self._P[j, j])
            R_h = float(R[0, 0])
            self.sight.update(h, float(nu[0]) + float(self._x[j]), max(S_p, R_h), R_h)
        nu_e = nu - shift
        self.nis, self.nis_dof = float(nu_e[0] ** 2 / (S[0, 0] + var)), 1
        self.corrections += 1
        self._watch(True, nu)
        K_opt = np.linalg.solve(S, cross.T).T
        K = self._shape_gain(K_opt, nu_e, S)
        self._x = self._x + K @ nu_e
        return K, S + var, R + var, False

    def _onset(self, rule: ExcessMixture, h: int, prior: float, post: float, nu: float) -> None:
        """The Markov onset test on anchor ``h``'s range: its chain turned blocked
        (``prior < 1/2 <= post``). A clear chain turns within ``w`` seconds with probability
        ``pi_j(w) = nlos + (c_j - nlos) exp(-w / memory)`` (:meth:`ExcessMixture.prior` from
        its posterior ``c_j`` before it turned), independently of the others; so the other
        anchors ``G`` that turned within ``w`` before it and are still read blocked have the
        joint probability ``prod_{j in G} pi_j(w)``. Below the gate's ``1 - P`` the joint
        onset is taken as a state error: :meth:`_onset_release` after the update.

        The window ``w`` is one round of the anchors (1.5 of anchor ``h``'s interval between
        its ranges), over which a position error reaches every anchor's next range, unless
        :attr:`onset_window` states one. With ranges every 0.08 s per anchor, ``nlos = 1/2``
        and a 10 s memory, ``pi_j = 0.006``: three clear chains turned within one round
        (``0.006^2``) are a state error at ``P = 0.999``, two (0.006) are not."""
        if post < 0.5:
            self._onset_at[h] = -math.inf
            return
        if prior >= 0.5 or not math.isfinite(self._nlos_time[h]):
            return
        self._onset_at[h], self._onset_pre[h], self._onset_nu[h] = self._time, self._nlos[h], nu
        # the window: one round of the anchors (1.5 of this anchor's interval), over which a
        # position error reaches every anchor's next range; or the stated one
        w = self.onset_window or 1.5 * (self._time - float(self._nlos_time[h]))
        joint, fire = 1.0, self._onset_fire
        fire[:] = False
        for j in range(self._nlos.shape[0]):
            if j != h and self._time - self._onset_at[j] <= w and self._nlos[j] >= 0.5:
                joint *= rule.prior(float(self._onset_pre[j]), w)
                fire[j] = True
        if fire.any() and joint < 1.0 - rule.probability:
            fire[h] = True
            self._onset_pending = True

    def _onset_release(self) -> None:
        """The joint onset taken as a position error: the position's covariance grown by the
        mean square of the onsets' innovations, ``P_pp += mean(nu_j^2) I``, and each of those
        chains re-read at its clear state (its posterior before it turned)."""
        self._onset_pending = False
        fire = self._onset_fire
        s2 = float(np.mean(self._onset_nu[fire] ** 2))
        for i in range(int(self.outputs.system.p)):
            self._P[i, i] += s2
        self._nlos[fire] = self._onset_pre[fire]
        self._onset_at[fire] = -math.inf
        self.onsets.append(self._time)

    def _steady(self, rule: ExcessMixture, h: int, post: float, nu: float, R: float) -> None:
        """The steady-offset test on anchor ``h``'s ranges read blocked (``post >= 1/2``), from
        the biases' opening, in blocks of ``N`` consecutive ones (a range read clear, or any
        while the biases are closed, restarts the block; a rejected range does not count).

        Behind an obstacle the innovations are ``e_i + n_i``, the excess drawn afresh for each
        range; a bias state ``delta`` low gives ``delta + n_i`` instead, as steady as the noise
        ``n_i`` of variance ``R_i``. Over a block, with the weighted mean
        ``hat delta = sum(nu_i / R_i) / sum(1 / R_i)``, the spread
        ``Q = sum((nu_i - hat delta)^2 / R_i)`` is ``chi^2(N - 1)`` under a bias error (more
        where the position's error moves within the block). The block is taken as one
        (:meth:`_steady_release` after the update) where ``Q`` is at most the median of
        ``chi^2(N - 1)`` and ``hat delta`` exceeds ``z / sqrt(sum 1 / R_i)`` (``z^2`` the
        ``chi^2(1)`` quantile at the rule's ``P``). Neither needs the excess's law: ``N``
        (:func:`steady_block`) is the fewest ranges at which an excess as spread as the noise
        (``Q`` twice the noise's on average) passes with probability at most ``1 - P`` per
        block. A bias error passes a block with probability about 1/2."""
        counts = post >= 0.5 and self.biases_open
        delta = steady_offset(self._block[h], rule.probability, counts, nu, R, 1.0)
        if delta is not None:
            self._steady_pending = (h, delta)

    def _steady_short(self, rule: ExcessMixture, h: int, clear: bool, nu: float, R: float) -> None:
        """The same test, the other way, on anchor ``h``'s ranges in line of sight (``clear``:
        read clear, or rejected as shorter than line of sight; a range read blocked or
        rejected as too long restarts the block). A bias state too high (an excess taken into
        it that has ended) makes its anchor's ranges short: beyond the gate most are rejected,
        and nothing corrects it. A block as steady as the noise with ``hat delta`` below
        ``-z sqrt(N / sum 1 / R_i)`` (beyond the gate of one range of the mean noise: an
        offset the mixture would reject) is taken as its error; a smaller one the accepted
        ranges correct."""
        counts = clear and self.biases_open
        delta = steady_offset(self._short[h], rule.probability, counts, nu, R, -1.0, True)
        if delta is not None:
            self._steady_pending = (h, delta)

    def _steady_release(self) -> None:
        """The block's mean ``hat delta`` taken as the bias error of its anchor ``h`` (low where
        positive, high where negative): the bias's variance grown by ``hat delta^2`` (process
        noise on ``b_h`` alone), its chain read clear (and out of the onset test's record)."""
        assert self._steady_pending is not None
        (h, delta), self._steady_pending = self._steady_pending, None
        j = self.vehicle_n + h
        self._P[j, j] += delta * delta
        self._nlos[h], self._nlos_time[h] = 0.0, self._time
        self._onset_at[h] = -math.inf
        self.steady_offsets.append(self._time)

    def _update(self, z: np.ndarray, idx, R: np.ndarray) -> None:
        """A correction of the range outputs ``idx``; one range's anchor is kept for
        :meth:`_gain` (any other measurement, a TDOA, has none: ``-1``)."""
        one = not isinstance(idx, slice) and len(idx) == 1
        self._anchor = int(idx[0]) if one else -1
        try:
            super()._update(z, idx, R)  # type: ignore[misc]
        finally:
            self._anchor = -1
            if self._steady_pending is not None:
                self._steady_release()
        if self._onset_pending:
            self._onset_release()

    def _correct_measurement(self, m: Measurement) -> None:
        if self.fix_pending and m.kind == "range":
            h, yh, _ = self._model_of(m).quadratic_output(m)
            self._latest[h] = yh
            self._waited += 1
            if self._wait_or_fix():
                return
        super()._correct_measurement(m)  # type: ignore[misc]

    def correct_outputs(self, y: np.ndarray) -> None:
        if self.fix_pending:
            y = np.asarray(y, dtype=float)
            present = ~np.isnan(y)
            self._latest[present] = y[present]
            self._waited += int(np.count_nonzero(present))
            if self._wait_or_fix():
                return
        super().correct_outputs(y)  # type: ignore[misc]

    def _wait_or_fix(self) -> bool:
        """:meth:`_try_fix` on the ranges just kept; ``True`` when they are not to be corrected
        by: still waiting, or the position just set by a fix made of them (a correction by them
        would count their noise twice: the module docstring's "Start-up"; the step's NIS is
        then NaN). ``False`` when the fix was given up: the ranges are corrected as they are."""
        before = len(self.fixes)
        if not self._try_fix():
            return True
        if len(self.fixes) == before:
            return False
        self.nis, self.nis_dof = float("nan"), 0
        return True

    def correct_many(self, measurements) -> None:
        """Ranges of one time (:meth:`~quadobs.estimators.kalman._GaussianFilter.correct_many`):
        while the fix is pending they are kept for it together, as :meth:`correct_outputs` keeps
        a grid step's, and, once it is made, corrected by jointly; until then nothing is corrected."""
        measurements = list(measurements)
        if self.fix_pending and len(measurements) > 1:
            kept = []
            for m in measurements:
                self._check_measurement(m)  # type: ignore[attr-defined]
                if m.kind != "range":
                    break
                kept.append(self._model_of(m).quadratic_output(m))
            else:
                for h, yh, _ in kept:
                    self._latest[h] = yh
                self._waited += len(kept)
                if self._wait_or_fix():
                    return
        super().correct_many(measurements)  # type: ignore[misc]

    def _try_fix(self) -> bool:
        """The position from a multilateration once every anchor has a range, or, after two
        rounds' worth of ranges (an anchor silent), of those present; ``False`` while waiting.
        After four rounds without a multilateration (anchors in too few directions) the fix is
        given up and the prior kept."""
        q = self._latest.shape[0]
        if np.isnan(self._latest).any() and self._waited < 2 * q:
            return False
        system = self.outputs.system
        rho2 = np.maximum(2.0 * self._latest + np.sum(system.d * system.d, axis=1), 0.0)
        v = self._fix_var  # each output's variance, rho^2 s^2 + s^4 / 2: the weighted fix
        fixed = multilateration(system.C, system.d, self._latest, variances=rho2 * v + 0.5 * v * v)
        if fixed is None:
            if self._waited < 4 * q:
                return False
            self.fix_pending = False
            self.fix_abandoned = self._time  # reported without a fix (startup.not_started)
            return True
        cols = fixed[0]
        self._settle()
        if self.fix_correction and self.fix_pending:
            self._correct_at_fix(cols, fixed[1])
        else:
            self._x[cols] = fixed[1]
            self._P[cols, :] = 0.0
            self._P[:, cols] = 0.0
            self._P[cols, cols] = self._fix_var
        self.fix_pending = False
        self.fixes.append(self._time)
        return True

    def _correct_at_fix(self, cols, p_fix: np.ndarray) -> None:
        """One joint correction by the kept round of ranges from the prior ``(x0, P0)``,
        linearised at the multilateration ``x_i`` (``x0`` with its position replaced by
        ``p_fix``): the first iterate of an iterated EKF (Gauss-Newton on the posterior) started
        at the fix,

        .. math::

            x^+ = x_0 + K \\big(z - h(x_i) - H (x_0 - x_i)\\big), \\qquad
            P^+ = (I - K H) P_0 (I - K H)^\\top + K R K^\\top,

        ``H = dh/dx`` at ``x_i``, ``K = P_0 H^\\top (H P_0 H^\\top + R)^{-1}`` with its bias rows
        held at zero while the biases are closed (the Joseph form is the covariance of any
        gain: the consider update). The ranges enter once, and the position's covariance with
        the biases is what they say (the multilateration's error is the biases' pattern
        ``-U^+ b``), where the fix's ``fix_std^2 I`` drops it."""
        idx = np.flatnonzero(~np.isnan(self._latest))
        out = self.outputs
        x_i = self._x.copy()
        x_i[cols] = p_fix
        s, J = out.linearize(x_i)
        H, R = J[idx], out.R[np.ix_(idx, idx)]
        nu = out.measure(self._latest[idx], idx) - s[idx] - H @ (self._x - x_i)
        PHt = self._P @ H.T
        K = np.linalg.solve(H @ PHt + R, PHt.T).T
        if not self.biases_open:
            K[self.vehicle_n :] = 0.0
        self._x = self._x + K @ nu
        IKH = np.eye(self._x.shape[0]) - K @ H
        self._P = IKH @ self._P @ IKH.T + K @ R @ K.T

    def _watch(self, accepted: bool, nu: np.ndarray) -> None:
        """The opening test on the NIS window, then the lock-out; a re-initialisation also puts
        the biases back to their prior mean, closes them, and gives the multilaterated position
        the covariance of a fix (the innovation-sized one of the re-initialisation bounds the
        error of the estimate it replaces, and spreads the UKF's sigma points over metres)."""
        if not self.biases_open:
            w = self._nis_window
            w.append(self.nis, self.nis_dof)
            if w.consistent():
                self.biases_open = True
                self.opened_at.append(self._time)
        before = len(self.lockout.resets)
        super()._watch(accepted, nu)  # type: ignore[misc]
        if len(self.lockout.resets) > before:
            self._x[self.vehicle_n :] = self._bias_prior
            self.sight = None
            self._nlos[:], self._nlos_time[:] = 0.0, self._time
            self._onset_at[:] = -math.inf
            self._block[:] = 0.0
            self._short[:] = 0.0
            self._steady_pending = None
            self.biases_open = False
            self._nis_window.clear()
            self._try_fix()  # the position covariance of a fix, as at the start

    @property
    def x_hat(self) -> np.ndarray:
        return self._x[: self.vehicle_n].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        self._settle()
        k = self.vehicle_n
        return self._P[:k, :k].copy()

    @property
    def biases(self) -> np.ndarray:
        """The estimated per-anchor biases ``(q,)`` (m)."""
        return self._x[self.vehicle_n :].copy()

    @property
    def constant_states(self) -> np.ndarray:
        """The indices of the states past the vehicle's that no process noise moves (each
        anchor's bias, and its offset where held; :mod:`quadobs.estimators.constants`)."""
        V = np.asarray(self.dynamics.V)
        k = self.vehicle_n
        return np.array([i for i in range(k, V.shape[0]) if not np.any(V[i])], dtype=np.int64)

    def _started_constants(self) -> None:
        """After a start of the constants (:mod:`quadobs.estimators.constants`): the biases'
        prior that a re-initialisation returns to, and the start-up fix's spread, which the
        biases' covariance sets (a tighter prior of the biases makes a multilateration's error
        smaller, so a prior position may now be wider than it and a fix be taken)."""
        self._bias_prior = self._x[self.vehicle_n :].copy()
        self._set_fix_spread()


class BiasedExtendedKalmanFilter(_VehicleBlock, ExtendedKalmanFilter):
    """:class:`~quadobs.estimators.kalman.ExtendedKalmanFilter` on ``(x, b)`` (:func:`biased_models`);
    :attr:`x_hat` is ``x``, :attr:`biases` is ``b``."""

    name = "ekf-bias"

    def __init__(
        self, dynamics, outputs, *, vehicle_n: int, sight_model: str = "chain", **kw
    ) -> None:
        super().__init__(dynamics, outputs, **kw)
        self.sight_model = _sight_model(sight_model)
        self._start_block(vehicle_n, _gate_probability(self.robust))


class BiasedUnscentedKalmanFilter(_VehicleBlock, UnscentedKalmanFilter):
    """:class:`~quadobs.estimators.kalman.UnscentedKalmanFilter` on ``(x, b)`` (:func:`biased_models`)."""

    name = "ukf-bias"

    def __init__(
        self, dynamics, outputs, *, vehicle_n: int, sight_model: str = "chain", **kw
    ) -> None:
        super().__init__(dynamics, outputs, **kw)
        self.sight_model = _sight_model(sight_model)
        self._start_block(vehicle_n, _gate_probability(self.robust))
