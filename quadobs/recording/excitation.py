"""The live excitation monitor in an episode's recording.

Entities (timelines ``step`` and ``sim_time``; values appear once the first window is
full, at the monitor's update times):

=========================================  =====================================================
``excitation/measure``                     ``mu = lambda_min W(t - delta, t)`` of the applied input
``excitation/threshold``                   the monitor's threshold
``excitation/log10``                       ``log10 max(mu, 1e-16 lambda_max)`` (the rounding floor)
                                           and ``log10 threshold`` (the default view)
``excitation/unexcited_directions``        how many eigenvalues of ``W`` are below the threshold
``excitation/unexcited_variance/<est>``    the estimator's largest variance along those
                                           directions, ``lambda_max(V^T P V)`` with ``V`` their
                                           eigenvectors (absent while every direction is
                                           excited), for estimators whose augmented state is
                                           the monitor's
``events``                                 one warning, the first time ``mu`` falls below the threshold
=========================================  =====================================================
"""

from __future__ import annotations

import numpy as np

from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.base import Immersed
from quadobs.observability.excitation import ExcitationMonitor
from quadobs.recording.recorder import Recorder

__all__ = ["ExcitationLog"]

_COLOR = (200, 60, 60)
_THRESHOLD = (120, 120, 120)


def _augmented(est) -> AugmentedObserver | None:
    """The augmented observer that ``est`` is, or that it drives as its ``inner`` (a wrapper that
    feeds it in time, such as the live scenario's ranges one at a time); else ``None``."""
    for candidate in (est, getattr(est, "inner", None)):
        if isinstance(candidate, AugmentedObserver) and isinstance(candidate, Immersed):
            return candidate
    return None


def _same_coordinates(obs: AugmentedObserver, monitor: ExcitationMonitor) -> bool:
    """Whether the augmented observer ``obs`` (whose ``P`` is the covariance of the augmented
    state) is on the monitor's immersion."""
    im, P, mine = obs.immersion, obs.P, monitor.immersion
    if im is None or np.shape(P) != (mine.dim, mine.dim) or im.n_aux != mine.n_aux:
        return False
    if im.system.q != mine.system.q:
        return False
    return bool(
        np.allclose(im.aux_forms, mine.aux_forms)
        and np.allclose(im.output_matrix, mine.output_matrix)
    )


class ExcitationLog:
    """Declares the monitor's series on a :class:`Recorder` and fills them at each recorded row.

    Parameters
    ----------
    recorder : Recorder
    monitor : ExcitationMonitor
    estimators : list of Estimator
        Those sharing the monitor's augmented coordinates get a ``weakest_variance`` series.
    """

    def __init__(self, recorder: Recorder, monitor: ExcitationMonitor, estimators) -> None:
        self.rec = recorder
        self.monitor = monitor
        self.every = every = monitor.update_blocks * monitor.block
        r = recorder
        self.measure = r.series(
            "excitation/measure", 1, every=every, skip_nan=True, names=["mu"], color=_COLOR
        )
        self.threshold = r.series(
            "excitation/threshold",
            1,
            every=every,
            skip_nan=True,
            names=["threshold"],
            color=_THRESHOLD,
        )
        self.log10 = r.series(
            "excitation/log10", 2, every=every, skip_nan=True, names=["log10 mu", "log10 threshold"]
        )
        self.count = r.series(
            "excitation/unexcited_directions",
            1,
            every=every,
            skip_nan=True,
            names=["unexcited directions"],
        )
        observers = [(est.name, _augmented(est)) for est in estimators]
        self.weak = {
            name: (
                obs,
                r.series(
                    f"excitation/unexcited_variance/{name}",
                    1,
                    every=every,
                    skip_nan=True,
                    names=[f"{name} max var"],
                ),
            )
            for name, obs in observers
            if obs is not None and _same_coordinates(obs, monitor)
        }
        self._pending: dict[int, tuple[list[float], list[float]]] = {}

    def capture(self, step: int) -> None:
        """Keep the monitor's values just recomputed, for the recorded row of physics step ``step``.

        Called when the monitor updates (after the input of step ``step - 1``), with the
        estimators' covariances of that moment; :meth:`fill` writes them when the row is
        recorded. Only rows at multiples of the update period are sent (the series' ``every``).
        """
        if step % self.every:
            return
        m = self.monitor
        mu = m.measure
        V = m.unexcited
        finite = np.isfinite(mu)
        values = [
            mu,
            m.threshold if finite else np.nan,
            # Below rounding (1e-16 lambda_max) mu is indistinguishable from 0: show the floor.
            np.log10(max(mu, 1e-16 * m.lambda_max, np.finfo(float).tiny)) if finite else np.nan,
            np.log10(m.threshold) if (finite and m.threshold > 0) else np.nan,
            V.shape[1] if finite else np.nan,
        ]
        weak = [
            float(np.linalg.eigvalsh(V.T @ est.P @ V)[-1]) if V.shape[1] else np.nan
            for est, _ in self.weak.values()
        ]
        self._pending[int(step)] = (values, weak)

    def fill(self, rows: slice, steps: np.ndarray) -> None:
        """Write the captured values into the recorder ``rows`` of the physics ``steps`` (NaN where none)."""
        for i, step in zip(range(rows.start, rows.stop), steps):
            if step % self.every:
                continue
            values, weak = self._pending.pop(int(step), ([np.nan] * 5, [np.nan] * len(self.weak)))
            self.measure.buf[i, 0] = values[0]
            self.threshold.buf[i, 0] = values[1]
            self.log10.buf[i, 0] = values[2]
            self.log10.buf[i, 1] = values[3]
            self.count.buf[i, 0] = values[4]
            for (_, series), w in zip(self.weak.values(), weak):
                series.buf[i, 0] = w

    def warn(self, message: str, step: int, time: float) -> None:
        """Log the monitor's warning at ``events``."""
        self.rec.text("events", message, level="WARN", step=step, time=time)
