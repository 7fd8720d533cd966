"""Model averaging: filters of rival measurement models run on the same data, their estimates averaged.

Where two filters differ only in a model that the data do not choose between, Bayesian model
averaging estimates the state by the average of their estimates weighted by the models'
posterior probabilities, the mean of the mixture of their posteriors ([HOETING1999, eq. 1]).
This class holds the weights equal, the uniform prior over the models, and never updates them:

.. math::

    \\hat x = \\frac1M \\sum_{i=1}^M \\hat x_i, \\qquad
    P = \\frac1M \\sum_{i=1}^M \\left[P_i + (\\hat x_i - \\hat x)(\\hat x_i - \\hat x)^\\top\\right],

the mean and covariance of the equal mixture of the members' Gaussian posteriors (the
combination of the static multiple-model estimator, [BARSHALOM2001, ch. 11], whose weights
that estimator updates by each model's likelihood). The average's position RMSE is never
above the mean of its members' (Minkowski's inequality).

Why the weights are not updated: the members here differ in how they read a range longer
than line of sight (one leaves it out, one weighs it by an excess model). The models'
likelihood is that of the ranges, the score the held-out check of the excess computes, and
that score was measured not to tell which filter places the vehicle better
(docs/error-sources.md). The equal weights are a choice, not a posterior: they hedge where
nothing measured chooses.

Every member takes every input and measurement; the average has the members' interface in
time. A member that has given up (its lock-out's ``diverged``) makes the average diverged:
an average holding a filter that gave up is not summarised as if it ran.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.base import Estimator, Gated

__all__ = ["MembersLockOut", "MembersRule", "ModelAverage"]


class MembersLockOut:
    """The lock-out record of a :class:`ModelAverage`: its members' re-initialisations, each
    marked with the member, and the earliest divergence among them as its own (the reason
    names the member). The members' lock-outs are read when asked, never copied."""

    def __init__(self, members) -> None:
        self._members = members

    def _locks(self):
        for m in self._members:
            lock = getattr(m, "lockout", None)
            if lock is not None:
                yield m.name, lock

    @property
    def resets(self) -> list:
        return [
            {**r, "member": name} if isinstance(r, dict) else r
            for name, lock in self._locks()
            for r in lock.resets
        ]

    @staticmethod
    def _earliest(records) -> dict | None:
        named = [{**r, "reason": f"member {name}: {r['reason']}"} for name, r in records if r]
        return min(named, key=lambda r: r["time"], default=None)

    @property
    def diverged(self) -> dict | None:
        return self._earliest((name, lock.diverged) for name, lock in self._locks())

    def locked_at_end(self) -> dict | None:
        return self._earliest((name, lock.locked_at_end()) for name, lock in self._locks())

    def summary(self) -> dict:
        return {"resets": self.resets, "diverged": self.diverged}


class MembersRule:
    """The robust rules of a :class:`ModelAverage`'s members, for its summary."""

    def __init__(self, members) -> None:
        self._members = members

    def describe(self) -> str:
        return "; ".join(
            f"{m.name}: {m.robust.describe()}"
            for m in self._members
            if getattr(m, "robust", None) is not None
        )


class ModelAverage(Estimator, Gated):
    """The equal-weight average of ``members`` (module docstring): filters of one state space,
    each fed every input and measurement.

    Parameters
    ----------
    members : sequence of Estimator
        At least one; their :attr:`~Estimator.x_hat` of one shape, their clocks together.
    name : str

    Notes
    -----
    Its :attr:`corrections` and :attr:`rejected` are the members' sums (a member without the
    :class:`~quadobs.estimators.base.Gated` ability counts none), so a step at which any
    member refuses a range counts as refused, and a member locked out by its gate shows in the
    average's counts; :attr:`gate` is the first member's.
    """

    def __init__(self, members, name: str = "average") -> None:
        members = list(members)
        if not members:
            raise QuadobsError(f"{name}: a model average needs at least one member")
        shapes = {np.shape(m.x_hat) for m in members}
        if len(shapes) != 1:
            raise QuadobsError(f"{name}: the members' states differ in shape ({sorted(shapes)})")
        inputs = {getattr(m, "replay_input", None) for m in members}
        if len(inputs) != 1:
            raise QuadobsError(
                f"{name}: the members read different inputs ({sorted(map(str, inputs))})"
            )
        self.members, self.name = members, name
        self.replay_input = inputs.pop()
        self.lockout = MembersLockOut(members)
        if any(getattr(m, "robust", None) is not None for m in members):
            self.robust = MembersRule(members)
        self.steady_test = any(getattr(m, "steady_test", False) for m in members)

    @property
    def gate(self):  # the first member's
        return getattr(self.members[0], "gate", None)

    @property
    def corrections(self) -> int:  # type: ignore[override]
        return sum(getattr(m, "corrections", 0) for m in self.members)

    @property
    def rejected(self) -> int:  # type: ignore[override]
        return sum(getattr(m, "rejected", 0) for m in self.members)

    @property
    def steady_offsets(self) -> list:
        """The members' steady-offset test firings (times, s), in order."""
        return sorted(t for m in self.members for t in getattr(m, "steady_offsets", ()))

    @property
    def time(self) -> float:
        return self.members[0].time

    @time.setter
    def time(self, value: float) -> None:
        for m in self.members:
            m.time = value

    def prepare(self, path: str) -> None:
        for m in self.members:
            m.prepare(path)

    def hold(self, u) -> None:
        for m in self.members:
            m.hold(u)

    def held_input(self) -> np.ndarray:
        return self.members[0].held_input()

    def predict(self, t) -> None:
        for m in self.members:
            m.predict(t)

    def correct(self, m) -> None:
        for member in self.members:
            member.correct(m)
        self._nis()

    def correct_many(self, measurements) -> None:
        for member in self.members:
            member.correct_many(measurements)
        self._nis()

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        for m in self.members:
            m.step(u, y)
        self._nis()

    def _nis(self) -> None:
        """The members' mean NIS of their last corrections (NaN where none corrected)."""
        values = [m.nis for m in self.members if np.isfinite(m.nis)]
        self.nis = float(np.mean(values)) if values else float("nan")

    @property
    def x_hat(self) -> np.ndarray:
        return sum(m.x_hat for m in self.members) / len(self.members)

    @property
    def x_covariance(self) -> np.ndarray | None:
        covs = [m.x_covariance for m in self.members]
        if any(P is None for P in covs):
            return None
        mean = self.x_hat
        total = np.zeros((mean.size, mean.size))
        for m, P in zip(self.members, covs, strict=True):
            d = m.x_hat - mean
            total += P + np.outer(d, d)
        return total / len(self.members)

    @property
    def covariance_trace(self) -> float:
        """``tr P`` of the mixture: the members' mean trace and their mean squared spread."""
        mean = self.x_hat
        spread = sum(float(np.sum((m.x_hat - mean) ** 2)) for m in self.members)
        return (sum(m.covariance_trace for m in self.members) + spread) / len(self.members)
