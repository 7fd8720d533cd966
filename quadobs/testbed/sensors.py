"""The sensor layer: exact readings in, what the estimators receive out.

Turns ranges, airspeed and accelerometer readings into the outputs of the
quadratic-output system and the measured input, applying the scenario's noise, sample
rates, dropouts and outliers:

* range ``h``: ``rho~ = rho + n``, ``y_h = rho~^2 / 2 - |a_h|^2 / 2`` (see
  :func:`quadobs.core.system.vehicle_system`);
* airspeed: ``s~ = s + n``, ``y = s~^2 / 2``;
* accelerometer: ``u~ = u + n``.

``n`` is Gaussian with the scenario's standard deviation, or uniform in ``[-bound, bound]``
for a sensor with a bound (``noise.range_bound``, ``accel_bound``, ``airspeed_bound``).

A sample that is not taken (rate below the physics rate) or dropped is NaN, which the
estimators read as "predict only". Random draws come from independent streams spawned
from the scenario seed, drawn in fixed-size blocks, so a seed gives the same
measurements whatever else the run does.
"""

from __future__ import annotations

import numpy as np

from quadobs.testbed.scenario import Scenario

__all__ = ["SensorModel", "initial_guess", "spawn_streams"]

_BLOCK = 4096
_STREAMS = ("initial", "range", "accel", "airspeed", "dropout", "outlier", "outlier_size", "spare")


def spawn_streams(seed: int) -> dict[str, np.random.Generator]:
    """Named, independent random generators derived from ``seed`` (fixed order)."""
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS))
    return {name: np.random.default_rng(child) for name, child in zip(_STREAMS, children)}


class _Draws:
    """Rows drawn in blocks of a fixed size: standard normal, uniform on ``[0, 1)``
    (``"uniform"``), or uniform on ``[-1, 1)`` (``"symmetric"``, as ``2 U - 1``)."""

    def __init__(self, rng: np.random.Generator, width: int, kind: str = "normal") -> None:
        self.rng, self.width, self.kind = rng, width, kind
        self.i = _BLOCK

    def _refill(self) -> None:
        if self.kind == "normal":
            self.block = self.rng.standard_normal((_BLOCK, self.width))
        elif self.kind == "symmetric":
            self.block = 2.0 * self.rng.random((_BLOCK, self.width)) - 1.0
        else:
            self.block = self.rng.random((_BLOCK, self.width))
        self.i = 0

    def next(self) -> np.ndarray:
        if self.i == _BLOCK:
            self._refill()
        row = self.block[self.i]
        self.i += 1
        return row

    def take(self, count: int) -> np.ndarray:
        """The next ``count`` rows, ``(count, width)``: exactly what ``count`` calls of :meth:`next` return."""
        out = np.empty((count, self.width))
        done = 0
        while done < count:
            if self.i == _BLOCK:
                self._refill()
            c = min(count - done, _BLOCK - self.i)
            out[done : done + c] = self.block[self.i : self.i + c]
            self.i += c
            done += c
        return out


class SensorModel:
    """Noise, rates, dropouts and outliers of a scenario (see the module docstring).

    Parameters
    ----------
    scenario : Scenario
    streams : dict of Generator, optional
        From :func:`spawn_streams`; derived from ``scenario.seed`` when omitted.
    """

    def __init__(
        self, scenario: Scenario, streams: dict[str, np.random.Generator] | None = None
    ) -> None:
        s = streams or spawn_streams(scenario.seed)
        noise = scenario.noise
        self.q_b = scenario.beacons.shape[0]
        self.has_wind = scenario.has_wind
        self.q = self.q_b + (1 if self.has_wind else 0)
        self.dim = scenario.dimension
        self._beacon_term = 0.5 * np.einsum("hi,hi->h", scenario.beacons, scenario.beacons)
        self.range_every = scenario.sample_interval(noise.range_rate, "range_rate")
        self.airspeed_every = scenario.sample_interval(noise.airspeed_rate, "airspeed_rate")
        self.range_bound, self.accel_bound, self.airspeed_bound = (
            noise.range_bound,
            noise.accel_bound,
            noise.airspeed_bound,
        )
        # A sensor has a standard deviation (Gaussian noise) or a bound (uniform noise), not
        # both: the noise is ``scale * draw`` with a standard normal draw, or ``2 U - 1``.
        self.range_std = noise.range_bound or noise.range_std
        self.accel_std = noise.accel_bound or noise.accel_std
        self.airspeed_std = noise.airspeed_bound or noise.airspeed_std
        self.dropout = noise.dropout
        self.outlier_probability, self.outlier_std = noise.outlier_probability, noise.outlier_std
        self._range = _Draws(s["range"], self.q_b, "symmetric" if self.range_bound else "normal")
        self._accel = _Draws(
            s["accel"], scenario.dimension, "symmetric" if self.accel_bound else "normal"
        )
        self._air = _Draws(s["airspeed"], 1, "symmetric" if self.airspeed_bound else "normal")
        self._drop = _Draws(s["dropout"], self.q, "uniform")
        self._out = _Draws(s["outlier"], self.q_b, "uniform")
        self._out_size = _Draws(s["outlier_size"], self.q_b)
        self.measured_ranges = np.full(self.q_b, np.nan)
        self.outliers_injected = 0
        self.dropped = 0
        self._y = np.full(self.q, np.nan)
        self._y_ranges = self._y[: self.q_b]
        self._no_noise = np.zeros(self.q_b)
        try:  # the compiled range transform (same arithmetic); NumPy when Numba is missing
            from quadobs._kernels.observer import range_outputs as fast
        except ImportError:  # pragma: no cover
            fast = None
        else:  # load (or compile) it now rather than in the first step
            scratch = np.zeros(self.q_b)
            fast(scratch, scratch, 0.0, scratch, scratch.copy(), scratch.copy())
        self._fast = fast

    @property
    def range_period_steps(self) -> int:
        return self.range_every

    def outputs(self, k: int, ranges: np.ndarray, airspeed: float | None = None) -> np.ndarray:
        """The output vector ``y (q,)`` for physics step ``k`` (NaN where no sample).

        Also leaves the noisy ranges in :attr:`measured_ranges` (NaN where no sample). The
        returned array is reused (overwritten) by the next call.
        """
        y = self._y
        measured = self.measured_ranges
        outliers = None
        if k % self.range_every == 0:
            noise = self._range.next() if self.range_std else self._no_noise
            if self._fast is not None and not self.outlier_probability:
                self._fast(
                    ranges, noise, self.range_std, self._beacon_term, measured, self._y_ranges
                )
            else:
                rho = ranges + self.range_std * noise if self.range_std else ranges.copy()
                if self.outlier_probability:
                    hit = self._out.next() < self.outlier_probability
                    size = self._out_size.next()
                    if hit.any():
                        rho = rho + np.where(hit, self.outlier_std * size, 0.0)
                        outliers = hit
                measured[:] = rho
                y[: self.q_b] = 0.5 * rho * rho - self._beacon_term
        else:
            y[: self.q_b] = np.nan
            measured[:] = np.nan
        if self.has_wind:
            if airspeed is not None and k % self.airspeed_every == 0:
                s = airspeed + (
                    self.airspeed_std * self._air.next()[0] if self.airspeed_std else 0.0
                )
                y[self.q_b] = 0.5 * s * s
            else:
                y[self.q_b] = np.nan
        if self.dropout:
            lost = (self._drop.next() < self.dropout) & ~np.isnan(y)
            if lost.any():
                y[lost] = np.nan
                measured[lost[: self.q_b]] = np.nan
                self.dropped += int(lost.sum())
                if outliers is not None:
                    outliers = outliers & ~lost[: self.q_b]
        if outliers is not None:
            self.outliers_injected += int(outliers.sum())
        return y

    # -- a block of steps at once (the compiled per-step path of the episode loop) ---------

    @property
    def draw_width(self) -> int:
        """Columns of :meth:`draws`: range noise, outlier uniforms, outlier sizes (``q_b`` each),
        airspeed noise (1), dropout uniforms (``q``), accelerometer noise (``dim``), flags (1)."""
        return 3 * self.q_b + 1 + self.q + self.dim + 1

    def draws(self, k0: int, count: int) -> np.ndarray:
        """The random draws of steps ``k0 .. k0 + count - 1``, one row per step.

        Each stream gives the rows that :meth:`outputs` and :meth:`input` called for those
        steps would take, in the same order, so the measurements are the same; the last
        column flags the samples (1: ranges, 2: airspeed). :func:`quadobs._kernels.observer.sensor_step`
        turns a row and the exact readings into ``y``, ``u`` and the measured ranges;
        :meth:`commit` then counts the dropouts and outliers of the rows used.
        """
        qb, q, dim = self.q_b, self.q, self.dim
        k = k0 + np.arange(count)
        rng_on = k % self.range_every == 0
        air_on = (k % self.airspeed_every == 0) if self.has_wind else np.zeros(count, dtype=bool)
        out = np.zeros((count, self.draw_width))
        o = 0
        if self.range_std:
            out[rng_on, o : o + qb] = self._range.take(int(rng_on.sum()))
        o += qb
        if self.outlier_probability:
            out[rng_on, o : o + qb] = self._out.take(int(rng_on.sum()))
            out[rng_on, o + qb : o + 2 * qb] = self._out_size.take(int(rng_on.sum()))
        o += 2 * qb
        if self.airspeed_std and self.has_wind:
            out[air_on, o] = self._air.take(int(air_on.sum()))[:, 0]
        o += 1
        if self.dropout:
            out[:, o : o + q] = self._drop.take(count)
        o += q
        if self.accel_std:
            out[:, o : o + dim] = self._accel.take(count)
        out[:, -1] = rng_on + 2 * air_on
        return out

    def events(self, draws: np.ndarray) -> np.ndarray:
        """Per step of these rows of :meth:`draws`: ``[outliers, dropped]``, ``(rows, 2)`` counts.

        ``outliers`` counts the range samples that reach the estimators with an outlier
        added (an outlier whose sample is then dropped is not counted), ``dropped`` the
        samples lost to dropouts.
        """
        qb, q = self.q_b, self.q
        flags = draws[:, -1].astype(int)
        sampled = np.zeros((len(draws), q), dtype=bool)
        sampled[:, :qb] = (flags & 1)[:, None] > 0
        if self.has_wind:
            sampled[:, qb] = (flags & 2) > 0
        lost = np.zeros_like(sampled)
        if self.dropout:
            o = 3 * qb + 1
            lost = sampled & (draws[:, o : o + q] < self.dropout)
        out = np.zeros((len(draws), 2), dtype=np.int64)
        if self.outlier_probability:
            hit = (
                sampled[:, :qb] & (draws[:, qb : 2 * qb] < self.outlier_probability) & ~lost[:, :qb]
            )
            out[:, 0] = hit.sum(axis=1)
        out[:, 1] = lost.sum(axis=1)
        return out

    def commit(self, draws: np.ndarray) -> np.ndarray:
        """Count the dropouts and outliers of steps processed from these rows of :meth:`draws`;
        returns their per-step :meth:`events`."""
        return self.count(self.events(draws))

    def count(self, events: np.ndarray) -> np.ndarray:
        """Add per-step ``[outliers, dropped]`` counts ``(rows, 2)`` to the totals; returns them."""
        self.outliers_injected += int(events[:, 0].sum())
        self.dropped += int(events[:, 1].sum())
        return events

    @property
    def adds_nothing(self) -> bool:
        """Whether the layer hands the ranges and the input on unchanged: no noise, dropout or outlier, every step sampled."""
        return (
            not (self.range_std or self.accel_std or self.dropout or self.outlier_probability)
            and self.range_every == 1
        )

    def input_noise(self, draws: np.ndarray) -> np.ndarray:
        """The accelerometer noise of these rows of :meth:`draws`, ``(rows, dim)`` (as :meth:`input` adds it)."""
        o = 3 * self.q_b + 1 + self.q
        return self.accel_std * draws[:, o : o + self.dim]

    def logged_ranges(self, rho: np.ndarray, draws: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The sensor layer on logged ranges ``rho (rows, q_b)`` (NaN: none logged), with these rows of :meth:`draws`.

        A logged range is read at the layer's sample steps only (``noise.range_rate``);
        there it gets the noise and the outlier of :meth:`outputs`, in the same order, and
        may be dropped. Returns the measured ranges (NaN: none) and the per-step
        ``[outliers, dropped]`` counts of the ranges read, ``(rows, 2)``, to be
        :meth:`count`-ed for the steps kept.
        """
        qb = self.q_b
        read = ~np.isnan(rho) & ((draws[:, -1].astype(int) & 1) > 0)[:, None]
        out = np.where(read, rho, np.nan)
        if self.range_std:
            out = out + self.range_std * draws[:, :qb]
        hit = (
            read & (draws[:, qb : 2 * qb] < self.outlier_probability)
            if self.outlier_probability
            else np.zeros_like(read)
        )
        out = np.where(hit, out + self.outlier_std * draws[:, 2 * qb : 3 * qb], out)
        o = 3 * qb + 1
        lost = read & (draws[:, o : o + qb] < self.dropout) if self.dropout else np.zeros_like(read)
        out[lost] = np.nan
        return out, np.column_stack([(hit & ~lost).sum(axis=1), lost.sum(axis=1)]).astype(np.int64)

    def step_params(self) -> np.ndarray:
        """Constants of :func:`quadobs._kernels.observer.sensor_step`: ``[q_b, q, dim, range_std, outlier_probability,
        outlier_std, airspeed_std, dropout, accel_std, beacon_term (q_b)]``."""
        return np.concatenate(
            [
                [
                    self.q_b,
                    self.q,
                    self.dim,
                    self.range_std,
                    self.outlier_probability,
                    self.outlier_std,
                ],
                [self.airspeed_std, self.dropout, self.accel_std],
                self._beacon_term,
            ]
        ).astype(float)

    def input(self, accel: np.ndarray) -> np.ndarray:
        """The measured input: the accelerometer reading plus its noise."""
        if self.accel_std:
            return accel + self.accel_std * self._accel.next()
        return accel


def initial_guess(scenario: Scenario, truth0: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The initial estimate of the scenario's state (:class:`~quadobs.testbed.scenario.InitialGuess`)."""
    init = scenario.initial
    n = truth0.shape[0]
    if init.kind == "zero":
        return np.zeros(n)
    if init.kind == "point":
        return np.array(init.point, dtype=float)
    dim = scenario.dimension
    spread = np.full(n, init.velocity_spread)
    spread[:dim] = init.position_spread
    return truth0 + spread * rng.standard_normal(n)
