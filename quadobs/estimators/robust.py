"""Robust corrections for the Kalman filters: a chi-square gate or Huber's M-estimator, and lock-out.

UWB ranges carry outliers of metres and positive, heavy-tailed non-line-of-sight errors;
a Gaussian update takes every one of them at full weight. Two standard answers, one per
rule object, applied to an innovation ``nu (k,)`` with covariance ``S = H P H^T + R``:

* :class:`ChiSquareGate`: reject the correction when the normalised innovation squared
  ``nis = nu^T S^{-1} nu`` exceeds the ``probability`` quantile of ``chi^2`` with ``k``
  degrees of freedom, ``k`` the number of outputs in the correction (1 for a single range
  at its own time). Under the model a correct measurement is rejected with probability
  ``1 - probability``.
* :class:`Huber`: the M-estimator of Huber (1964) as a Kalman update (Karlgaard and
  Schaub's re-weighting): each standardised residual ``r_h = nu_h / sqrt(S_hh)`` gets the
  weight ``w_h = min(1, c / |r_h|)`` (quadratic loss inside ``|r| <= c``, linear outside),
  and the update uses ``R_w = W^{-1/2} R W^{-1/2}``, ``W = diag(w)``. Nothing is ever
  rejected: a range ``d`` metres off moves the estimate as one about ``c sqrt(S)`` off
  would. ``c = 1.345`` gives 95 % efficiency under Gaussian noise.

No silent lock-out. A gate that rejects everything leaves a filter predicting on its
inputs alone while it reports figures as if it ran (a filter started 50 m off with a
small prior rejects every range). :class:`LockOut` watches the corrections in time: when
more than half of those tried over the last ``timeout`` seconds were rejected (at least
:data:`LOCKOUT_MIN_TRIED` tried), the filter re-initialises: its position from a
multilateration of the latest outputs (:func:`multilateration`, where they determine it) and
its covariance (:func:`reinitialised_covariance`), and says so in ``resets``; after
``max_resets`` re-initialisations without recovering it is reported as diverged
(``diverged``: time, step and reason), never summarised as if it had run.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy import special

from quadobs.core.quantiles import chi2_ppf, norm_ppf
from quadobs.errors import QuadobsError

__all__ = [
    "LOCKOUT_END_MIN",
    "LOCKOUT_MIN_TRIED",
    "BiasSightGrid",
    "ChiSquareGate",
    "ExcessHuber",
    "ExcessMixture",
    "Huber",
    "LockOut",
    "SkewedGate",
    "chi2_threshold",
    "multilateration",
    "multilateration_covariance",
    "reinitialised_covariance",
    "reweight",
]


@lru_cache(maxsize=64)
def chi2_threshold(probability: float, dof: int) -> float:
    """The ``probability`` quantile of ``chi^2(dof)`` (e.g. 10.83 for 0.999 and one degree of freedom)."""
    return chi2_ppf(probability, dof)


@dataclass(frozen=True)
class ChiSquareGate:
    """Reject a correction whose NIS exceeds the ``probability`` quantile of ``chi^2(k)``.

    Parameters
    ----------
    probability : float
        In ``(0, 1)``: the probability that a measurement that follows the model passes.
    """

    probability: float = 0.999

    def __post_init__(self) -> None:
        if not (0.0 < self.probability < 1.0):
            raise QuadobsError(
                f"noise.gate: expected the gate's probability in (0, 1) (e.g. 0.999; the threshold "
                f"is the chi-square quantile with one degree of freedom per output), got {self.probability}"
            )

    def threshold(self, dof: int) -> float:
        """The NIS threshold for a correction of ``dof`` outputs."""
        return chi2_threshold(self.probability, int(dof))

    def describe(self) -> str:
        """One line for summaries: the rule, its degrees of freedom and threshold."""
        return (
            f"chi-square gate, P = {self.probability}, k = outputs per correction "
            f"(threshold {self.threshold(1):.2f} for k = 1)"
        )


@dataclass(frozen=True)
class Huber:
    """Huber's M-estimator as a re-weighted Kalman update (see the module docstring).

    Parameters
    ----------
    c : float
        The residual, in standard deviations, beyond which the loss is linear.
    """

    c: float = 1.345

    def __post_init__(self) -> None:
        if not (math.isfinite(self.c) and self.c > 0.0):
            raise QuadobsError(f"noise.huber: expected a positive number, got {self.c}")

    def weights(self, nu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """``w_h = min(1, c / |r_h|)`` with ``r_h = nu_h / sqrt(S_hh)``."""
        r = np.abs(nu) / np.sqrt(np.diag(S))
        return np.minimum(1.0, self.c / np.maximum(r, 1e-300))

    def describe(self) -> str:
        return f"Huber M-estimator, c = {self.c} standard deviations"


@dataclass(frozen=True)
class SkewedGate:
    """A chi-square gate that also rejects a range too *long* for line of sight.

    Non-line-of-sight excess only lengthens a range (the signal takes a longer path), so
    its standardised innovation ``r = nu / sqrt(S)`` is positive; Gaussian noise gives
    either sign. The rule rejects a scalar correction when ``nis = r^2`` exceeds the
    ``probability`` quantile of ``chi^2(1)`` (as :class:`ChiSquareGate`) or when ``r``
    exceeds ``z_+ = Phi^{-1}(line_of_sight)``, the one-sided quantile of the standard
    normal: a line-of-sight range is then rejected with probability
    ``1 - line_of_sight``, and the accepted ones have the mean
    ``-sqrt(S) phi(z_+) / Phi(z_+)`` (``-0.11 sqrt(S)`` for ``line_of_sight = 0.95``), the
    same for every anchor. A correction of ``k > 1`` outputs is judged by the chi-square
    gate alone.

    Parameters
    ----------
    probability : float
        The two-sided gate's probability (as :class:`ChiSquareGate`).
    line_of_sight : float
        In ``(0.5, 1)``: the probability that a line-of-sight range passes the one-sided test.
    """

    probability: float = 0.999
    line_of_sight: float = 0.95

    def __post_init__(self) -> None:
        ChiSquareGate(self.probability)
        if not (0.5 < self.line_of_sight < 1.0):
            raise QuadobsError(
                f"line_of_sight: expected a probability in (0.5, 1) (e.g. 0.95), got {self.line_of_sight}"
            )

    @property
    def upper(self) -> float:
        """``z_+``: the largest standardised innovation accepted (1.645 for 0.95)."""
        return norm_ppf(self.line_of_sight)

    def rejects(self, nu: np.ndarray, S: np.ndarray) -> bool:
        """Whether the correction ``nu`` with covariance ``S`` is rejected; a scalar whose
        ``S`` is not positive (a covariance that has lost its definiteness) is, and the
        filter's lock-out watch re-initialises it as for any run of rejections."""
        if nu.shape[0] == 1 and not S[0, 0] > 0.0:
            return True
        nis = float(nu @ np.linalg.solve(S, nu))
        if nis > chi2_threshold(self.probability, nu.shape[0]):
            return True
        return nu.shape[0] == 1 and nu[0] > self.upper * math.sqrt(S[0, 0])

    def describe(self) -> str:
        return (
            f"chi-square gate, P = {self.probability}, k = outputs per correction, and a "
            f"one-sided gate on ranges longer than line of sight (r > {self.upper:.3f}, "
            f"P = {self.line_of_sight})"
        )


@dataclass(frozen=True)
class ExcessMixture:
    """A range likelihood with the radio's non-line-of-sight excess as a latent variable.

    A range is ``rho~ = rho + e + sigma n`` with the excess ``e = 0`` in line of sight
    (prior probability ``1 - nlos``) and ``e = e_50 exp(s n_e)``, ``n_e ~ N(0, 1)``, behind an
    obstacle (probability ``nlos``): the log-normal of the radio's stated median ``e_50`` and
    shape ``s``. The log-normal is discretised on ``z_j = -4, -3.8, ..., 4`` standard
    deviations (weights ``phi(z_j)``, normalised), so that ``e`` takes the values ``e_j``
    (``e_0 = 0``) with prior weights ``pi_j``. Given the innovation ``nu`` of a range with
    covariance ``S = H P H^T + R``, every value has the same Gaussian likelihood shape,
    ``N(nu - e_j; 0, S)``, so the posterior weights are
    ``gamma_j = pi_j exp(-(nu - e_j)^2 / 2S) / sum_i pi_i exp(-(nu - e_i)^2 / 2S)``,
    and the Gaussian-sum update collapses exactly to one Kalman update: with the gain
    ``K = P H^T S^{-1}``, ``x += K (nu - E[e | nu])`` and
    ``P = (I - K H) P + K Var[e | nu] K^T``, i.e. a range corrected by its expected excess,
    its variance grown by the excess's posterior variance (:meth:`posterior`). A
    line-of-sight range (``nu`` within the noise of 0) is taken at full weight; one well
    beyond it moves the estimate only by what its excess is uncertain by, so that a bias
    state takes in neither the excess nor, on average, less than it.

    Whether an anchor's path is blocked depends on where the vehicle is, so it persists
    from one of its ranges to the next: each anchor's probability of non-line-of-sight is a
    two-state Markov chain (a per-anchor NLOS state). Its prior for a range is the
    posterior ``P(NLOS | nu) = 1 - gamma_0`` of the anchor's previous range relaxed towards
    the stationary ``nlos`` over :attr:`memory` (:meth:`prior`). The bias-state filters keep
    each anchor's chain jointly with its bias (:class:`BiasSightGrid`): a chain conditioned on
    the filter's own bias estimate reads a clear anchor whose bias is estimated low as
    blocked. A fixed prior instead (every range with probability ``nlos``) takes a
    fraction of every line-of-sight range's positive noise for excess.

    A range is rejected (an outlier) when it is shorter than line of sight by more than
    the chi-square gate of ``probability`` allows (``nu < -z sqrt(S)``, ``z^2`` the
    ``chi^2(1)`` quantile) or longer than the excess's ``probability`` quantile by as much
    (``nu > e_50 exp(s Phi^{-1}(probability)) + z sqrt(S)``). A correction of ``k > 1``
    outputs is judged by the chi-square gate alone.

    Parameters
    ----------
    median, shape : float
        The radio's stated log-normal excess: its median ``e_50`` (m) and shape ``s``.
    nlos : float
        In ``(0, 1)``: the stationary probability that a range is non-line-of-sight. The
        radio states none (the room decides it), so the default is the uninformed ``0.5``.
    probability : float
        The gate's probability (as :class:`ChiSquareGate`).
    memory : float
        The time (s) over which an anchor's state of sight is remembered (:meth:`prior`):
        whether a path is blocked is decided by where the vehicle is in the room, which
        changes over seconds, not between two ranges 0.08 s apart. Not derived from the room:
        neither a radio nor a log states the obstacles' shadows or the vehicle's speed
        through them, and every range refreshes the chain, so ``memory`` only sets how fast
        an anchor's evidence fades between its ranges. So it is a stated figure, checked by
        measurement (``docs/error-sources.md``, "Defaults and why"): below a second the chain
        forgets between two rounds of the anchors and the figure worsens; from 3 to 30 s it
        moves by a few millimetres on the replayed flights and by up to 0.026 m (3 s best) on
        four live seeds.
    """

    median: float
    shape: float
    nlos: float = 0.5
    probability: float = 0.999
    memory: float = 10.0
    excess: np.ndarray = field(init=False, repr=False, compare=False)
    log_prior: np.ndarray = field(init=False, repr=False, compare=False)
    _work: np.ndarray = field(init=False, repr=False, compare=False)
    _upper: float = field(init=False, repr=False, compare=False)
    _z: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        ChiSquareGate(self.probability)
        for name, v in (("nlos_median", self.median), ("nlos_shape", self.shape)):
            if not (math.isfinite(v) and v > 0.0):
                raise QuadobsError(f"radio.{name}: expected a positive number, got {v}")
        if not (0.0 < self.nlos < 1.0):
            raise QuadobsError(f"nlos: expected a probability in (0, 1), got {self.nlos}")
        if not (math.isfinite(self.memory) and self.memory > 0.0):
            raise QuadobsError(f"memory: expected a positive number of seconds, got {self.memory}")
        z = np.linspace(-4.0, 4.0, 41)
        w = np.exp(-0.5 * z * z)
        excess = np.concatenate([[0.0], self.median * np.exp(self.shape * z)])
        object.__setattr__(self, "excess", excess)
        object.__setattr__(self, "log_prior", np.log(np.concatenate([[1.0], w / w.sum()])))
        # work space of :meth:`posterior` (the hot path allocates nothing per range)
        object.__setattr__(self, "_work", np.empty((2, excess.shape[0])))
        # the gate's bounds, computed once: :meth:`posterior` runs for every range
        quantile = norm_ppf(self.probability)
        object.__setattr__(self, "_upper", self.median * math.exp(self.shape * quantile))
        object.__setattr__(self, "_z", math.sqrt(chi2_threshold(self.probability, 1)))

    @property
    def upper(self) -> float:
        """The excess's ``probability`` quantile (m): longer ranges beyond the noise are outliers."""
        return self._upper

    def prior(self, last: float, dt: float) -> float:
        """The prior probability that an anchor's range is non-line-of-sight, given the
        posterior ``last`` of its previous range ``dt`` seconds before: the two-state Markov
        chain ``pi = nlos + (last - nlos) exp(-dt / memory)`` (``last`` itself where ``dt`` is not positive)."""
        if not dt > 0.0:
            return last
        return self.nlos + (last - self.nlos) * math.exp(-dt / self.memory)

    def posterior(
        self, nu: float, S: float, nlos: float | None = None
    ) -> tuple[float, float, float] | None:
        """``(E[e | nu], Var[e | nu], P(NLOS | nu))`` of a range's excess given its innovation
        ``nu``, the innovation's variance ``S`` under line of sight and the prior probability
        ``nlos`` (default :attr:`nlos`) that it is non-line-of-sight; ``None`` when it is
        rejected, and where ``S`` is not positive (a covariance that has lost its
        definiteness: the range is refused and the filter's lock-out watch counts it, as
        :class:`SkewedGate` does)."""
        if not S > 0.0:
            return None
        sd, z = math.sqrt(S), self._z
        if nu < -z * sd or nu > self._upper + z * sd:
            return None
        pi = self.nlos if nlos is None else min(max(nlos, 1e-6), 1.0 - 1e-6)
        g, e2 = self._work
        np.subtract(nu, self.excess, out=g)
        g /= sd
        g *= g
        g *= -0.5
        g += self.log_prior
        g[0] += math.log1p(-pi)
        g[1:] += math.log(pi)
        g -= g.max()
        np.exp(g, out=g)
        g /= g.sum()
        mean = float(g @ self.excess)
        np.multiply(self.excess, self.excess, out=e2)
        var = max(float(g @ e2) - mean * mean, 0.0)
        return mean, var, 1.0 - float(g[0])

    def describe(self) -> str:
        return (
            f"non-line-of-sight mixture likelihood (excess log-normal, median {self.median} m, "
            f"shape {self.shape}; prior probability {self.nlos}), outliers beyond the "
            f"P = {self.probability} gate on either side rejected"
        )


@dataclass(frozen=True)
class ExcessHuber:
    """Huber's M-estimator on a range's innovation less its expected non-line-of-sight excess.

    A range is ``rho~ = rho + e + n``, ``n ~ N(0, S)`` in the innovation, with ``e = 0`` in line
    of sight (prior probability ``1 - pi``) and ``e`` exponential of mean ``mu`` (rate
    ``lambda = 1 / mu``: the largest-entropy law of a positive excess of a given mean) behind
    an obstacle (probability ``pi``). The innovation's two likelihoods are the Gaussian and
    the exponentially modified Gaussian,

    .. math::

        \\ell_0(\\nu) = \\frac{\\phi(\\nu / \\sqrt S)}{\\sqrt S}, \\qquad
        \\ell_1(\\nu) = \\lambda\\, e^{\\lambda^2 S / 2 - \\lambda \\nu}\\,
        \\Phi\\Big(\\frac{\\nu - \\lambda S}{\\sqrt S}\\Big),

    the responsibility of the excess ``gamma = pi l_1 / ((1 - pi) l_0 + pi l_1)``, and behind
    an obstacle ``e | nu`` is ``N(m, S)`` truncated to ``e >= 0``, ``m = nu - lambda S``: with
    ``z = m / sqrt S`` and the inverse Mills ratio ``h = phi(z) / Phi(z)``,

    .. math::

        \\mathrm E[e \\mid \\nu, \\text{blocked}] = m + \\sqrt S\\, h, \\qquad
        \\operatorname{Var}[e \\mid \\nu, \\text{blocked}] = S\\,(1 - z h - h^2).

    :meth:`posterior` gives ``E[e | nu] = gamma E_1`` and ``Var[e | nu] = gamma (V_1 + E_1^2) -
    E[e | nu]^2``; the filter corrects with the innovation ``nu' = nu - E[e | nu]`` and adds
    ``K Var[e | nu] K^T`` to its covariance (the exact collapse of the two-component posterior,
    as :class:`ExcessMixture`). Huber's weight ``w = min(1, c / |nu'| sqrt(S))`` then bounds what
    is left (:meth:`weights`): an outlier shorter than line of sight moves the estimate as one
    ``c`` standard deviations off would, as :class:`Huber`. Nothing is rejected, so the rule
    cannot lock a filter out.

    Its influence is bounded on both sides: ``nu'`` is largest where ``gamma`` turns from 0 to
    1 (for :meth:`at_bound`'s prior 0.0151, 2.29 standard deviations at ``nu = 2.71 sqrt(S)``,
    against Huber's ``c = 3.29``; 0.69 at a prior of 1/2), and as ``nu -> +inf``, ``gamma ->
    1`` and ``nu' -> lambda S``, so a range far beyond the noise moves the estimate by
    ``lambda S`` in the innovation and leaves the covariance as it was (``Var[e | nu] ->
    S``). An excess a little beyond the noise is taken in part. With ``pi = 0`` (no excess) ``E[e | nu] = Var[e | nu] = 0`` and the rule is
    :class:`Huber`'s.

    Parameters
    ----------
    mean : float
        ``mu``, the excess's prior mean (m).
    nlos : float
        ``pi`` in ``[0, 1)``: the prior probability that a range is blocked.
    c : float
        Huber's bound (standard deviations) on what the excess does not explain.
    memory : float
        The time (s) over which an anchor's evidence of a blocked path carries to its next
        range (:meth:`prior`; the filter keeps each anchor's last ``gamma``): an obstacle
        beside the path blocks every range to an anchor behind it while the vehicle passes,
        a burst. 0: every range has the prior ``nlos``.
    """

    mean: float
    nlos: float = 0.05
    c: float = 3.29
    memory: float = 0.0
    _huber: Huber = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_huber", Huber(self.c))  # checks c; the weights' rule
        if not (math.isfinite(self.mean) and self.mean > 0.0):
            raise QuadobsError(f"excess mean: expected a positive number (m), got {self.mean}")
        if not (0.0 <= self.nlos < 1.0):
            raise QuadobsError(f"nlos: expected a probability in [0, 1), got {self.nlos}")

    @classmethod
    def at_bound(cls, c: float, sigma: float, memory: float = 0.0) -> ExcessHuber:
        """The rule whose excess is stated by the range noise ``sigma`` and Huber's bound ``c``
        alone: an excess worth telling from the noise is one beyond the bound, so its mean is
        ``mu = c sigma``, and its prior probability ``pi`` is the one at which a range ``c sigma``
        long (``S = sigma^2``) is as likely blocked as clear (``gamma = 1/2``):

        .. math::

            \\frac{\\pi}{1 - \\pi} = \\frac{\\ell_0(c \\sigma)}{\\ell_1(c \\sigma)}
            = \\frac{c\\, \\phi(c)}{e^{1 / 2c^2 - 1}\\, \\Phi(c - 1/c)}

        (``lambda sigma = 1 / c``): 0.0151 for ``c = 3.29``, whatever ``sigma``. A range
        within the noise is then taken as clear (a shift of millimetres, :meth:`posterior`),
        one beyond the bound as blocked."""
        log_odds = (
            math.log(c) - 0.5 * c * c - _HALF_LOG_2PI
            - (0.5 / (c * c) - 1.0) - float(special.log_ndtr(c - 1.0 / c))
        )  # fmt: skip
        return cls(c * sigma, 1.0 / (1.0 + math.exp(-log_odds)), c, memory)

    def prior(self, last: float, dt: float) -> float:
        """The prior probability that an anchor's range is blocked, its previous range's
        ``gamma`` being ``last`` ``dt`` seconds before: the two-state Markov chain ``nlos +
        (last - nlos) exp(-dt / memory)`` (as :meth:`ExcessMixture.prior`); ``nlos`` itself
        without a memory."""
        if not self.memory > 0.0 or not dt < math.inf:
            return self.nlos
        return self.nlos + (last - self.nlos) * math.exp(-max(dt, 0.0) / self.memory)

    def posterior(
        self, nu: float, S: float, nlos: float | None = None
    ) -> tuple[float, float, float]:
        """``(E[e | nu], Var[e | nu], gamma)`` of a range's excess given its innovation ``nu``
        of variance ``S`` in line of sight and the prior probability ``nlos`` (default
        :attr:`nlos`) that it is blocked (class docstring)."""
        if not S > 0.0:
            raise QuadobsError(f"innovation variance: expected a positive number, got {S}")
        pi = self.nlos if nlos is None else min(max(nlos, 0.0), 1.0 - 1e-9)
        if pi == 0.0:
            return 0.0, 0.0, 0.0
        sd, lam = math.sqrt(S), 1.0 / self.mean
        z = (nu - lam * S) / sd
        log_cdf = float(special.log_ndtr(z))
        log_l0 = -0.5 * (nu / sd) ** 2 - math.log(sd) - _HALF_LOG_2PI
        log_l1 = math.log(lam) + 0.5 * lam * lam * S - lam * nu + log_cdf
        a = math.log(pi) + log_l1
        b = math.log1p(-pi) + log_l0
        gamma = 1.0 / (1.0 + math.exp(min(b - a, 700.0)))
        h = math.exp(-0.5 * z * z - _HALF_LOG_2PI - log_cdf)  # phi(z) / Phi(z)
        mean1 = sd * (z + h)
        var1 = max(S * (1.0 - z * h - h * h), 0.0)
        mean = gamma * mean1
        return mean, max(gamma * (var1 + mean1 * mean1) - mean * mean, 0.0), gamma

    def weights(self, nu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Huber's weights ``min(1, c / |r|)`` of the innovation ``nu`` (less its expected
        excess, :meth:`posterior`), ``r = nu / sqrt(S_hh)``."""
        return self._huber.weights(nu, S)

    def describe(self) -> str:
        return (
            f"Huber M-estimator, c = {self.c} standard deviations, on the innovation less its "
            f"expected non-line-of-sight excess (exponential, mean {self.mean:.3g} m, prior "
            f"probability {self.nlos})"
        )


_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


class BiasSightGrid:
    """Each anchor's joint posterior of its range bias and its state of sight, on a bias grid.

    Under an :class:`ExcessMixture` a bias estimated low by ``c`` makes the anchor's
    line-of-sight ranges long by ``c``, which an excess explains as well: one Gaussian bias
    and one probability of sight, updated range by range, cannot tell the two apart, and a
    clear anchor read as blocked keeps its bias low. What separates them is the shape of the
    residuals over many ranges: in line of sight they are spread by the noise alone around
    the bias, behind an obstacle they only add the excess's spread above it. The joint
    posterior of ``(b_h, s)``, ``s`` in {line of sight, blocked}, keeps both explanations.

    The bias of anchor ``h`` takes the values ``b_hj = m_h + sd_h z_j``, ``z_j`` on
    ``[-4, 4]`` (``points`` values; ``m_h``, ``sd_h`` the filter's bias estimate and standard
    deviation when the grid is built), with prior weights ``phi(z_j)`` and the probability
    ``start`` of a blocked path. Between two ranges of the anchor ``dt`` apart the state of sight follows
    the mixture's two-state chain (:meth:`ExcessMixture.prior`, at every bias value: the
    bias is constant); a range with the residual ``r = rho - |p^ - a_h|`` (the range less
    the filter's predicted distance) of variance ``S_p = H_p P_pp H_p^T + R`` (the position's
    uncertainty and the noise, without the bias's) multiplies the weights by

    .. math::

        \\ell(r \\mid b_j, \\text{sight}) = \\mathcal N(r - b_j; 0, S_p), \\qquad
        \\ell(r \\mid b_j, \\text{blocked}) = \\sum_i \\pi_i\\, \\mathcal N(r - b_j - e_i; 0, S_p)

    (the mixture's discretised log-normal ``e_i``, ``pi_i``). The residual's error is the
    position's along the anchor, ``H_p (p - p^)``, as well as the noise, and the position's
    error persists from one range to the next: taken as independent, a few hundred ranges
    would narrow the bias to millimetres around wherever the position sat. So before each
    range the bias values take a random walk of variance ``2 (S_p - R)^2 / S_p``: twice the
    variance at which a walk observed through ranges of noise ``R`` settles to the position's
    own variance ``P = S_p - R`` (a scalar Kalman filter's steady state, ``Q = P^2 / (P + R)``),
    so that the grid resolves the bias no finer than the filter knows the position (the
    factor 2 is the walk measured in ``docs/error-sources.md``; the steady state's own
    variance was not measured).

    The filter takes the prior
    probability that a range is blocked from :meth:`predict` (the weight of ``blocked``
    summed over the bias values) instead of a chain conditioned on its own bias estimate;
    its bias state and its update are unchanged.

    Parameters
    ----------
    rule : ExcessMixture
    mean, std : ndarray (q,)
        The biases' estimate and standard deviation (m) the grid spans.
    points : int
        Bias values per anchor.
    start : float or ndarray (q,)
        Each anchor's probability of a blocked path when the grid is built.
    """

    def __init__(
        self,
        rule: ExcessMixture,
        mean: np.ndarray,
        std: np.ndarray,
        points: int = 81,
        start: float | np.ndarray = 0.0,
    ) -> None:
        self.rule = rule
        z = np.linspace(-4.0, 4.0, int(points))
        self.bias = (
            np.asarray(mean, dtype=float)[:, None] + np.asarray(std, dtype=float)[:, None] * z
        )
        q = self.bias.shape[0]
        self._prior = np.exp(-0.5 * z * z)
        self._prior /= self._prior.sum()
        self.weights = np.zeros((q, 2, z.shape[0]))
        start = np.broadcast_to(np.asarray(start, dtype=float), (q,))[:, None]
        self.weights[:, 0] = (1.0 - start) * self._prior
        self.weights[:, 1] = start * self._prior
        self.time = np.full(q, np.nan)
        self._excess = rule.excess[1:]
        self._excess_prior = np.exp(rule.log_prior[1:])
        self._work = np.empty((z.shape[0], self._excess.shape[0]))
        self._lik = np.empty((2, z.shape[0]))
        self._lap = np.empty((2, z.shape[0]))

    def predict(self, h: int, t: float) -> float:
        """Move anchor ``h``'s state of sight to the time ``t`` of its next range (the chain at
        every bias value); returns the prior probability that this range is blocked."""
        w, last = self.weights[h], self.time[h]
        dt = t - last if math.isfinite(last) else 0.0
        if dt > 0.0:
            p = self.rule.nlos * (1.0 - math.exp(-dt / self.rule.memory))
            q = p / self.rule.nlos * (1.0 - self.rule.nlos)  # blocked -> clear
            moved = w[0] * p - w[1] * q
            w[0] -= moved
            w[1] += moved
        self.time[h] = t
        return float(w[1].sum())

    def _diffuse(self, w: np.ndarray, var: float, step: float) -> None:
        """The bias values' random walk of variance ``var``: ``n`` explicit steps of the heat
        equation on the grid (reflecting ends), each adding ``2 a step^2`` with ``a <= 1/2``.
        A walk of more than the grid's prior variance (its span is +-4 prior standard
        deviations) forgets where the bias was: each state's weight is spread as the grid's
        prior (at most 100 steps otherwise)."""
        if not step > 0.0:
            return
        prior_sd = 0.125 * step * (w.shape[1] - 1)  # the grid spans +-4 prior sd
        if var > prior_sd * prior_sd:
            w[:] = w.sum(axis=1, keepdims=True) * self._prior
            return
        n = max(1, math.ceil(var / (step * step)))
        a, lap = var / (2 * n * step * step), self._lap
        for _ in range(n):
            lap[:, 1:-1] = w[:, :-2] + w[:, 2:]
            lap[:, 1:-1] -= 2.0 * w[:, 1:-1]
            lap[:, 0] = w[:, 1] - w[:, 0]
            lap[:, -1] = w[:, -2] - w[:, -1]
            lap *= a
            w += lap

    def update(self, h: int, r: float, S: float, R: float) -> None:
        """Weigh anchor ``h``'s grid by a range's residual ``r`` of variance ``S`` (``R`` of it
        the range's noise), after the walk of its bias values by ``2 (S - R)^2 / S``."""
        D, lik, w = self._work, self._lik, self.weights[h]
        if S > R:
            self._diffuse(w, 2.0 * (S - R) ** 2 / S, self.bias[h, 1] - self.bias[h, 0])
        np.subtract(r, self.bias[h], out=lik[0])
        np.subtract(lik[0][:, None], self._excess, out=D)
        D *= D
        D *= -0.5 / S
        np.exp(D, out=D)
        np.dot(D, self._excess_prior, out=lik[1])
        lik[0] *= lik[0]
        lik[0] *= -0.5 / S
        np.exp(lik[0], out=lik[0])
        w *= lik
        total = w.sum()
        if total > 1e-300 and math.isfinite(total):
            w /= total
        else:  # no bias value explains the range: the anchor's prior, its sight unknown
            np.multiply(self._prior, 1.0 - self.rule.nlos, out=w[0])
            np.multiply(self._prior, self.rule.nlos, out=w[1])

    def blocked(self) -> np.ndarray:
        """Each anchor's probability of being blocked at its last range ``(q,)``."""
        return self.weights[:, 1].sum(axis=1)

    def bias_mean(self) -> np.ndarray:
        """Each anchor's posterior mean bias ``(q,)`` (m)."""
        return np.einsum("hsj,hj->h", self.weights, self.bias)


def reweight(rule, nu: np.ndarray, S: np.ndarray, R: np.ndarray) -> np.ndarray | None:
    """The measurement covariance to update with: ``R``, ``R`` re-weighted, or ``None`` (rejected).

    Parameters
    ----------
    rule : ChiSquareGate, Huber or None
    nu : ndarray (k,)
        The innovation.
    S : ndarray (k, k)
        Its covariance ``H P H^T + R``.
    R : ndarray (k, k)
        The measurement covariance.
    """
    if rule is None:
        return R
    if isinstance(rule, SkewedGate):
        return None if rule.rejects(nu, S) else R
    if isinstance(rule, (ChiSquareGate, ExcessMixture)):
        # an ExcessMixture's scalar update (its shift of the innovation) is the filter's own
        nis = float(nu @ np.linalg.solve(S, nu))
        return None if nis > chi2_threshold(rule.probability, nu.shape[0]) else R
    w = rule.weights(nu, S)
    if np.all(w == 1.0):
        return R
    s = 1.0 / np.sqrt(w)
    return R * np.outer(s, s)


def reinitialised_covariance(
    P: np.ndarray, P0: np.ndarray, innovation: float, dim: int, span: float
):
    """The covariance a locked-out filter restarts from.

    A range innovation ``nu`` bounds the position error along the line of sight from
    below, so the position block becomes at least ``nu^2 I`` (``nu``: the largest
    innovation seen while locked out), the velocity block at least ``(nu / span)^2 I``
    (that error grown over the lock-out's ``span`` seconds), and never less than the prior
    ``P0``; the correlations are dropped.
    """
    n = P.shape[0]
    diag = np.maximum(np.diag(P), np.diag(P0))
    diag[:dim] = np.maximum(diag[:dim], innovation**2)
    diag[dim : 2 * dim] = np.maximum(diag[dim : 2 * dim], (innovation / max(span, 1e-9)) ** 2)
    return np.diag(diag[:n])


def multilateration(
    C: np.ndarray,
    d: np.ndarray,
    y: np.ndarray,
    centred: bool = False,
    variances: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The state entries fixed by one snapshot of outputs that share one quadratic form.

    For ranges, ``y_h = 1/2 x^T C x + d_h^T x`` with the same ``C`` for every anchor
    (``d_h = -a_h`` on the position), so differences are linear,
    ``y_h - y_0 = (d_h - d_0)^T x``: the position is the least-squares solution, exact
    for noise-free ranges to at least ``dim + 1`` anchors in general position.

    Parameters
    ----------
    C : ndarray (q, n, n)
    d : ndarray (q, n)
    y : ndarray (q,)
        The latest value of each output (NaN: none).
    centred : bool
        Differences from the outputs' mean, ``y_h - ybar = (d_h - dbar)^T x``, instead of from
        the first output. For outputs with independent errors of one variance this is the
        generalised least squares of the differences (whose errors share the first one's), and
        the fix does not depend on the outputs' order; from the first output it does.
    variances : ndarray (q,), optional
        Each output's error variance ``v_h``: the weighted least squares of ``y_h = c + d_h^T x``
        with the common term ``c`` (``1/2 x^T C x``) as an unknown, weights ``w_h = 1 / v_h``,
        i.e. differences from the weighted means ``dbar_w``, ``ybar_w`` solved with the weights
        (:func:`multilateration_covariance`): the best linear unbiased fix of independent
        outputs, whatever their order (``centred`` is its case of equal variances).

    Returns
    -------
    (columns, values) or None
        The indices of the state entries determined and their values; ``None`` when the
        outputs differ in their quadratic form or do not determine those entries.
    """
    rows = np.flatnonzero(~np.isnan(y))
    if rows.shape[0] < 2 or not np.allclose(C[rows], C[rows[0]]):
        return None
    if variances is not None:
        w = 1.0 / np.asarray(variances, dtype=float)[rows]
        sw = np.sqrt(w / w.sum())[:, None]
        D = sw * (d[rows] - w @ d[rows] / w.sum())
        r = sw[:, 0] * (y[rows] - w @ y[rows] / w.sum())
    elif centred:
        D, r = d[rows] - d[rows].mean(axis=0), y[rows] - y[rows].mean()
    else:
        D, r = d[rows[1:]] - d[rows[0]], y[rows[1:]] - y[rows[0]]
    cols = np.flatnonzero(np.any(D != 0.0, axis=0))
    if cols.shape[0] == 0 or np.linalg.matrix_rank(D[:, cols]) < cols.shape[0]:
        return None
    sol = np.linalg.lstsq(D[:, cols], r, rcond=None)[0]
    return cols, sol


def multilateration_covariance(D: np.ndarray, variances: np.ndarray) -> np.ndarray:
    """The covariance of :func:`multilateration`'s weighted fix: ``(D_w^T W D_w)^-1`` with
    ``D_w`` the rows ``d_h - dbar_w`` (``dbar_w`` the mean weighted by ``w_h = 1 / v_h``) and
    ``W = diag(w)``, the outputs' errors independent of variances ``v_h``.

    Parameters
    ----------
    D : ndarray (k, m)
        The rows ``d_h`` of the outputs used, on the columns the fix determines.
    variances : ndarray (k,)
    """
    w = 1.0 / np.asarray(variances, dtype=float)
    Dw = D - w @ D / w.sum()
    return np.linalg.inv((Dw * w[:, None]).T @ Dw)


#: Fewest corrections in the lock-out's window at the run's end for :meth:`LockOut.locked_at_end`.
LOCKOUT_END_MIN = 10

#: Fewest corrections the lock-out's window holds (:meth:`LockOut.observe`): it reaches back
#: past ``timeout`` seconds to hold at least this many, and no lock-out is declared on fewer.
#: A window of one to four holds too few for the rule's premise: after a pause of every
#: output longer than the window, one range rejected would be "all of them" (probability
#: 0.05 under the one-sided gate's 5 %), where three of five or more has probability at most
#: 1.2e-3, and 5 of 5 3e-7. On a log whose outputs come slower than five a window, the
#: window holds the last five.
LOCKOUT_MIN_TRIED = 5


@dataclass
class LockOut:
    """Watches a filter's corrections in time (see the module docstring).

    The filter counts as locked out when, over the last ``timeout`` seconds or its last
    :data:`LOCKOUT_MIN_TRIED` corrections, whichever reach further back (and at least
    :attr:`grace` after its start or last re-initialisation), more than half of the
    corrections it tried (at least :data:`LOCKOUT_MIN_TRIED` tried) were rejected: under the
    model, with a gate of probability ``P``, the expected fraction is ``1 - P``. This catches
    a filter that rejects everything and one that keeps a few outputs consistent with a wrong
    position (a mirror image of the anchors' geometry) while it rejects the others.

    Parameters
    ----------
    timeout : float
        The window (s).
    max_resets : int
        Re-initialisations before the filter is reported as diverged.
    """

    timeout: float = 2.0
    max_resets: int = 3
    since: float = 0.0
    largest: float = 0.0
    resets: list = field(default_factory=list)
    diverged: dict | None = None
    _window: deque = field(default_factory=deque, repr=False)
    _rejected: int = field(default=0, repr=False)
    _before: float | None = field(default=None, repr=False)

    def observe(self, t: float, accepted: bool, innovation: float) -> bool:
        """Record a correction tried at ``t``; returns whether the filter is now locked out."""
        w = self._window
        w.append((t, accepted, abs(innovation)))
        self._rejected += not accepted
        while len(w) > LOCKOUT_MIN_TRIED and w[0][0] < t - self.timeout:
            dropped = w.popleft()
            self._rejected -= not dropped[1]
            self._before = dropped[0]
        if accepted or self.diverged is not None:
            return False
        self.largest = max(e[2] for e in w if not e[1])
        enough = len(w) >= LOCKOUT_MIN_TRIED
        return t - self.since >= self.grace and enough and 2 * self._rejected > len(w)

    @property
    def grace(self) -> float:
        """Time after the start or the last re-initialisation before a lock-out can be declared:
        the window, doubled at each re-initialisation (a filter re-initialised far off gets
        longer to converge each time, as the refined observer's hand-over waits twice as long)."""
        return self.timeout * 2.0 ** len(self.resets)

    def begin(self, t: float) -> None:
        """The watch starts at ``t`` (s), where it has watched nothing yet: the filter's
        start, from which :attr:`grace` counts, on a clock that does not start at zero (a log
        stamped in seconds since 1970). A watch already under way is left as it is."""
        if not self._window and not self.resets and self.diverged is None:
            self.since = self._before = float(t)

    @property
    def last_accepted(self) -> float:
        """Start of the current window (s): the span the lock-out is judged over ends at the last correction."""
        return self._window[0][0] if self._window else self.since

    def reason(self, t: float) -> str:
        """The re-initialisation's reason at ``t``: the window's seconds, or how far it reached
        back where it holds corrections older than ``timeout`` (:data:`LOCKOUT_MIN_TRIED`)."""
        reach = t - self.last_accepted
        window = self.timeout if reach <= self.timeout else round(reach, 2)
        return f"more than half of the corrections of the last {window} s rejected"

    def span(self, t: float) -> float:
        """Seconds over which a filter locked out at ``t`` has gone wrong: from the window's
        start, or, where the window follows a silence longer than itself (no correction tried:
        every output lost), from the last correction tried before the silence (the watch's
        start or its last re-initialisation where there was none). From the window's start
        alone, a lock-out declared on the first output after such a silence would span no time."""
        start, before = self.last_accepted, self._before
        if before is not None and start - before > self.timeout:
            return t - before
        return t - start

    def reset(self, t: float, step: int, reason: str) -> bool:
        """Count a re-initialisation at ``t``; returns ``False`` (and sets :attr:`diverged`)
        when the filter has used up its re-initialisations."""
        if len(self.resets) >= self.max_resets:
            self.diverged = {"time": t, "step": step, "reason": reason}
            return False
        self.resets.append({"time": t, "step": step, "reason": reason})
        self.since, self.largest = t, 0.0
        self._before = t
        self._window.clear()
        self._rejected = 0
        return True

    def locked_at_end(self) -> dict | None:
        """``None``, or the record of a filter whose window still holds more rejected
        corrections than accepted ones (at least :data:`LOCKOUT_END_MIN`) when the run ends:
        the lock-out's own test without the grace after a re-initialisation (the grace lets a
        re-initialised filter converge; a run that ends inside it has not)."""
        w = self._window
        if self.diverged is not None or len(w) < LOCKOUT_END_MIN or 2 * self._rejected <= len(w):
            return None
        reason = (
            f"locked out at the end of the run: {self._rejected} of the last {len(w)} "
            f"corrections rejected (within {self.timeout:g} s)"
        )
        return {"time": float(w[-1][0]), "step": -1, "reason": reason}

    def summary(self) -> dict:
        """Re-initialisations and divergence as plain data."""
        return {"resets": list(self.resets), "diverged": self.diverged}
