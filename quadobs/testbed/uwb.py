"""A simulated UWB radio: ranges and TDOAs as a tag takes them, with the errors real ones carry.

A UWB tag does not measure every anchor at once. In two-way ranging (``"twr"``) it polls
one anchor at a time in turn (round-robin), each exchange at its own time; in the
TDoA3 scheme (``"tdoa"``) the anchors transmit in a random order and the tag differences
each packet's time of arrival with the previous one's. :class:`UwbRadio` produces those
events as :class:`~quadobs.core.measurements.Measurement` objects, from the true position
of the tag at the event's time.

Error model
-----------
For a range to anchor ``i`` at time ``t`` (tag at ``p``):

.. math::

    \\tilde\\rho = |p - a_i| + b_i + u_i^T S_i u_i + k \\log_{10} |p - a_i| + \\sigma n + \\mathbb 1_{\\mathrm{NLOS}}\\, e
                  + \\mathbb 1_{\\mathrm{out}}\\, \\sigma_o n_o ,
    \\qquad u_i = \\frac{p - a_i}{|p - a_i|},
    \\qquad e = e_{50} \\exp(s\\, n_e) > 0,

with ``n, n_o, n_e`` standard normal:

* ``b_i``: a constant per-anchor bias (antenna delay), given or drawn once
  ``N(bias_mean, bias_std^2)`` (an antenna delay lengthens the range: ``bias_mean > 0``);
* ``u_i^T S_i u_i``: a bias that varies with the direction ``u_i`` of the tag seen from the
  anchor (``pattern``; none by default). An antenna's delay depends on the direction of the
  signal through it, so that a real range's bias is no constant but a smooth function of
  the anchor-tag direction, set by the antennas' radiation patterns (Zhao et al.,
  arXiv:2003.09371, for two-way ranging and TDOA on a Crazyflie; Zhao, Panerati and
  Schoellig, RA-L 2021, arXiv:2103.01885). Of its expansion in the direction, the constant
  is the bias ``b_i`` and the first-order term ``g^T u`` is a displaced phase centre, which
  is an anchor surveyed off (``|p - a - c| = |p - a| - c^T u`` to first order); the
  second-order term is taken here, a symmetric traceless ``S_i`` drawn once per anchor (the
  symmetric part of a standard normal matrix less its trace, scaled). Over directions ``u``
  uniform on the sphere its mean is ``tr(S) / 3 = 0`` and its variance ``2 tr(S^2) / 15``,
  scaled to ``pattern^2``, and being even in ``u`` it is apart from a constant and a
  displaced anchor there; over the narrow cone of directions in which one anchor sees a
  vehicle in a room it is mostly a constant and a linear term in ``u`` all the same, i.e. a
  bias and a phase centre off the anchor (docs/error-sources.md). The tag's attitude is not
  taken: the pattern is that of a level tag of constant heading, fixed in the room;
* ``k log10 |p - a_i|``: a bias that changes with the distance (``level_bias``, ``k`` in m
  per decade of distance; none by default). The received signal's level falls by 20 dB per
  decade of distance, and the receiver's leading-edge detection reads the first path
  earlier or later with it: Decawave's application note APS011 ("Sources of error in DW1000
  based two-way ranging schemes") tabulates a correction of the order of 0.1 to 0.2 m
  across its levels. Its value at 1 m is a constant that the bias ``b_i`` holds; below
  :data:`NEAR_FIELD` (0.1 m, the antennas' near field) it is held at its value there;
* ``sigma n``: the line-of-sight noise;
* non-line-of-sight, decided by geometry: the segment from the anchor to the tag is cast
  against the obstacles of an MJCF room with MuJoCo's ray casting (``mj_ray``); when it
  hits a geom before reaching the tag, the range carries a positive, heavy-tailed
  (log-normal, median ``e_50``, shape ``s``) excess delay ``e``, as a signal that goes
  through or around an obstacle;
* outliers: with probability ``outlier_probability``, a Gaussian error of ``outlier_std``;
* dropouts: with probability ``dropout`` an exchange yields nothing.

A TDOA between anchors ``i`` (the packet received now) and ``j`` (the previous one) is the
difference of two such one-way paths:

.. math::

    \\tilde d_{ij} = |p - a_i| - |p - a_j| + (b_i - b_j) + \\sigma n
                     + \\mathbb 1_{\\mathrm{NLOS},i} e_i - \\mathbb 1_{\\mathrm{NLOS},j} e_j
                     + \\mathbb 1_{\\mathrm{out}} \\sigma_o n_o ,

so its bias is per pair, ``b_ij = b_i - b_j`` (:meth:`UwbRadio.pair_bias`); with a
``pattern`` or a ``level_bias`` each path also carries its own terms.

Timing
------
Round-robin at ``rate`` exchanges per second over all anchors: exchange ``k`` at
``t_k = (k + 1) / rate + jitter_k`` with anchor ``k mod m``; with per-anchor ``rates``,
anchor ``i`` on its own schedule ``t_{i,k} = (phi_i + k) / r_i + jitter`` (phase
``phi_i`` uniform in ``[0, 1)``), the events merged in time. ``jitter`` is Gaussian,
clipped to 0.45 of the nominal spacing so that an anchor's events stay in order.
TDOA packets arrive at ``rate`` per second, each from an anchor drawn uniformly among
the others than the previous one.

Every draw comes from its own stream spawned from the seed (schedule, noise,
non-line-of-sight, outliers, dropouts, biases, pattern), one draw per event whether or not it is
used, so the same seed gives the same events and switching one error source on or off
leaves the others' draws unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError

__all__ = ["RadioConfig", "Room", "UwbRadio", "radio_of", "room_model_path"]

_STREAMS = ("schedule", "noise", "nlos", "outlier", "dropout", "bias", "pattern")
#: Distance (m) below which the level's bias is held at its value there: the antennas' near
#: field, where the received level no longer follows the distance.
NEAR_FIELD = 0.1
#: Most of a nominal spacing a jittered event may move, so that one anchor's events keep their order.
_JITTER_CLIP = 0.45


def room_model_path(name: str = "uwb_room.xml") -> Path:
    """A built-in room MJCF: inside the installed package, or ``models/`` of a source checkout."""
    here = Path(__file__).resolve().parents[1]
    for candidate in (here / "_models" / name, here.parent / "models" / name):
        if candidate.is_file():
            return candidate
    raise QuadobsError(f"radio.room: the built-in {name} was not found beside the package")


@dataclass(frozen=True)
class RadioConfig:
    """The radio's protocol, rates and error sources (see the module docstring).

    Attributes
    ----------
    protocol : {"twr", "tdoa"}
        Two-way ranging (ranges, round-robin) or TDoA3-style (differences, random order).
    rate : float
        Exchanges (TWR) or packets (TDOA) per second over all anchors (Hz).
    rates : tuple of float or None
        TWR only: each anchor's own rate (Hz) instead of the round-robin.
    std : float
        Line-of-sight noise of one range or one difference (m).
    biases : tuple of float or None
        Per-anchor biases (m); ``None``: drawn once ``N(bias_mean, bias_std^2)``.
    bias_std : float
        Standard deviation of the drawn biases (m).
    bias_mean : float
        Mean of the drawn biases (m).
    jitter : float
        Standard deviation of each event's timing jitter (s).
    dropout, outlier_probability : float
        Probabilities that an event is lost, or carries an outlier.
    outlier_std : float
        Standard deviation of an outlier's error (m).
    nlos_median, nlos_shape : float
        Median (m) and log-normal shape of the excess of a non-line-of-sight path.
    pattern : float
        Standard deviation over all directions of each anchor's direction-dependent bias
        ``u_i^T S_i u_i`` (m; 0: none).
    level_bias : float
        ``k`` of the bias ``k log10 |p - a_i|`` that changes with the distance, through the
        received signal's level (m per decade of distance; 0: none).
    room : str or None
        MJCF file of the obstacles; ``None``: every path is in line of sight.
    """

    protocol: str = "twr"
    rate: float = 100.0
    rates: tuple[float, ...] | None = None
    std: float = 0.1
    biases: tuple[float, ...] | None = None
    bias_std: float = 0.0
    jitter: float = 0.0
    bias_mean: float = 0.0
    dropout: float = 0.0
    outlier_probability: float = 0.0
    outlier_std: float = 0.0
    nlos_median: float = 0.0
    nlos_shape: float = 0.5
    pattern: float = 0.0
    level_bias: float = 0.0
    room: str | None = None

    def check(self, m: int) -> None:
        """Refuse, naming the field, what cannot describe a radio with ``m`` anchors."""
        if self.protocol not in ("twr", "tdoa"):
            raise QuadobsError(f"radio.protocol: expected 'twr' or 'tdoa', got {self.protocol!r}")
        if self.protocol == "tdoa" and m < 2:
            raise QuadobsError("radio.protocol: 'tdoa' needs at least two anchors")
        positive = {"rate": self.rate, "std": self.std}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0.0):
                raise QuadobsError(f"radio.{name}: expected a positive number, got {value}")
        for name in ("bias_std", "jitter", "outlier_std", "nlos_median", "nlos_shape", "pattern"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise QuadobsError(f"radio.{name}: expected a non-negative number, got {value}")
        for name in ("bias_mean", "level_bias"):
            if not math.isfinite(getattr(self, name)):
                raise QuadobsError(
                    f"radio.{name}: expected a finite number, got {getattr(self, name)}"
                )
        for name in ("dropout", "outlier_probability"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise QuadobsError(f"radio.{name}: expected a probability in [0, 1), got {value}")
        for name in ("rates", "biases"):
            value = getattr(self, name)
            if value is not None and len(value) != m:
                raise QuadobsError(f"radio.{name}: expected {m} numbers (one per anchor)")
        if self.rates is not None:
            if self.protocol != "twr":
                raise QuadobsError("radio.rates: per-anchor rates are for protocol 'twr'")
            if not all(math.isfinite(r) and r > 0.0 for r in self.rates):
                raise QuadobsError("radio.rates: expected positive rates (Hz)")


class Room:
    """The obstacles of an MJCF file, and whether they block the line of sight between two points.

    Parameters
    ----------
    path : str or Path
        An MJCF model whose geoms are the obstacles (static; a floor, if any, counts too).
    """

    def __init__(self, path: str | Path) -> None:
        import mujoco

        try:
            self.model = mujoco.MjModel.from_xml_path(str(path))
        except ValueError as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else "unreadable"
            raise QuadobsError(f"radio.room: cannot load the room MJCF ({first})") from None
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self._ray, self._geom = mujoco.mj_ray, np.zeros(1, dtype=np.int32)
        self._vec = np.zeros(3)

    def blocked(self, a: np.ndarray, p: np.ndarray) -> bool:
        """Whether a geom crosses the segment from ``a (3,)`` to ``p (3,)`` (``mj_ray`` from ``a``)."""
        np.subtract(p, a, out=self._vec)
        length = math.sqrt(self._vec @ self._vec)
        if length == 0.0:
            return False
        self._vec /= length
        hit = self._ray(self.model, self.data, a, self._vec, None, 1, -1, self._geom)
        return 0.0 <= hit < length


class UwbRadio:
    """A tag ranging a set of anchors (see the module docstring).

    Parameters
    ----------
    anchors : ndarray (m, 3)
        Anchor positions (m).
    config : RadioConfig
    seed : int
        Seed of every draw.
    room : Room, optional
        The obstacles (default: ``config.room`` loaded, or none).

    Attributes
    ----------
    biases : ndarray (m,)
        The per-anchor biases in use (the truth a bias estimate is compared with).
    pattern_forms : ndarray (m, 3, 3)
        Each anchor's ``S_i`` of the direction-dependent bias (zeros without ``pattern``).
    counts : dict
        Events so far: ``measurements``, ``dropped``, ``nlos``, ``outliers``.
    """

    def __init__(
        self, anchors: np.ndarray, config: RadioConfig, seed: int, room: Room | None = None
    ) -> None:
        anchors = np.asarray(anchors, dtype=float)
        if anchors.ndim != 2 or anchors.shape[1] != 3:
            raise QuadobsError(f"anchors: the radio needs shape (m, 3), got {anchors.shape}")
        config.check(anchors.shape[0])
        self.anchors, self.config, self.m = anchors, config, int(anchors.shape[0])
        children = np.random.SeedSequence([int(seed), 0x55B]).spawn(len(_STREAMS))
        self._rng = {k: np.random.default_rng(c) for k, c in zip(_STREAMS, children)}
        drawn = config.bias_std * self._rng["bias"].standard_normal(self.m)
        if config.bias_mean:  # added only when set: a zero mean leaves the draws bit-identical
            drawn = config.bias_mean + drawn
        self.biases = drawn if config.biases is None else np.array(config.biases, dtype=float)
        self.biases.setflags(write=False)
        self.pattern_forms = self._pattern_forms(config.pattern)
        self.room = room if room is not None else (Room(config.room) if config.room else None)
        self.counts = {"measurements": 0, "dropped": 0, "nlos": 0, "outliers": 0}
        self._previous: int | None = None
        self._schedule_start()

    def _pattern_forms(self, pattern: float) -> np.ndarray:
        """Each anchor's ``S_i`` (module docstring) from the stream ``pattern``, drawn only where
        ``pattern > 0`` (the other streams' draws are the same either way); zeros without one."""
        forms = np.zeros((self.m, 3, 3))
        if not pattern > 0.0:
            return forms
        g = self._rng["pattern"].standard_normal((self.m, 3, 3))
        forms[:] = 0.5 * (g + g.transpose(0, 2, 1))
        forms -= np.trace(forms, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
        spread = np.sqrt(2.0 / 15.0 * np.einsum("hij,hij->h", forms, forms))
        forms *= (pattern / spread)[:, None, None]
        return forms

    def pattern_bias(self, i: int, p: np.ndarray) -> float:
        """Anchor ``i``'s direction-dependent bias ``u_i^T S_i u_i`` (m) for the tag at ``p (3,)``."""
        d = np.asarray(p, dtype=float) - self.anchors[i]
        return self._pattern_term(i, d, float(d @ d))

    def _pattern_term(self, i: int, d: np.ndarray, length2: float) -> float:
        """``d^T S_i d / |d|^2`` for the tag at ``d = p - a_i`` (``length2 = |d|^2``), 0 at the anchor."""
        return float(d @ self.pattern_forms[i] @ d) / length2 if length2 > 0.0 else 0.0

    # -- schedule ------------------------------------------------------------------------

    def _schedule_start(self) -> None:
        c, m = self.config, self.m
        if c.rates is not None:
            self._period = 1.0 / np.asarray(c.rates, dtype=float)
            self._phase = self._rng["schedule"].random(m)
            self._index = np.zeros(m, dtype=np.int64)
            self._next = np.array([self._nominal(i) for i in range(m)])
        else:
            self._period = np.full(1, 1.0 / c.rate)
            self._index = np.zeros(1, dtype=np.int64)
            self._next = np.array([self._nominal(0)])

    def _nominal(self, lane: int) -> float:
        """The next event time of a lane (one anchor, or the whole round-robin), jittered."""
        c, period = self.config, float(self._period[lane])
        k = int(self._index[lane])
        base = (self._phase[lane] + k) * period if c.rates is not None else (k + 1) * period
        jitter = c.jitter * self._rng["schedule"].standard_normal() if c.jitter else 0.0
        bound = _JITTER_CLIP * period
        return base + min(max(jitter, -bound), bound)

    def _anchor_of(self, lane: int) -> int:
        """The anchor of the lane's current event (round-robin, per-anchor, or TDoA3's random order)."""
        if self.config.rates is not None:
            return lane
        if self.config.protocol == "twr":
            return int(self._index[0] % self.m)
        prev = self._previous
        draw = int(self._rng["schedule"].integers(self.m - (prev is not None)))
        return draw + (prev is not None and draw >= prev)

    @property
    def next_time(self) -> float:
        """The time of the next event (s)."""
        return float(self._next.min())

    # -- events --------------------------------------------------------------------------

    def take(self, t0: float, t1: float, p: np.ndarray, v: np.ndarray) -> list[Measurement]:
        """The measurements of the events in ``[t0, t1)``, in time order.

        The tag is at ``p + v (t - t0)`` at time ``t`` (the state at ``t0`` of a physics
        step of length ``t1 - t0``). Returns an empty list (no allocation beyond it) when
        no event falls in the interval.
        """
        out: list[Measurement] = []
        nxt = self._next
        while True:
            lane = int(np.argmin(nxt))
            t = float(nxt[lane])
            if t >= t1:
                return out
            m = self._event(max(t, t0), lane, p + v * (max(t, t0) - t0))
            if m is not None:
                out.append(m)
            self._index[lane] += 1
            nxt[lane] = self._nominal(lane)

    def _event(self, t: float, lane: int, p: np.ndarray) -> Measurement | None:
        c, rng = self.config, self._rng
        i = self._anchor_of(lane)
        noise = c.std * rng["noise"].standard_normal()
        drop = rng["dropout"].random() < c.dropout
        is_out = rng["outlier"].random() < c.outlier_probability
        outlier = c.outlier_std * rng["outlier"].standard_normal()
        n_e = rng["nlos"].standard_normal(2)
        if drop:
            self.counts["dropped"] += 1
            return None
        value = self._path(i, p, n_e[0]) + noise + (outlier if is_out else 0.0)
        if c.protocol == "tdoa":
            j, self._previous = self._previous, i
            if j is None:  # the first packet has nothing to be differenced with
                return None
            value -= self._path(j, p, n_e[1])
            anchors: tuple[int, ...] = (i, j)
        else:
            value, anchors = max(value, 0.0), (i,)
        self.counts["outliers"] += bool(is_out)
        self.counts["measurements"] += 1
        return Measurement(
            t, c.protocol if c.protocol == "tdoa" else "range", value, anchors, c.std
        )

    def _path(self, i: int, p: np.ndarray, n_e: float) -> float:
        """One anchor's path: distance, bias, the direction's and the level's terms where set,
        and the excess delay when the line of sight is blocked."""
        a = self.anchors[i]
        d = p - a
        length = math.sqrt(d @ d)
        value = length + float(self.biases[i])
        if self.config.pattern > 0.0:
            value += self._pattern_term(i, d, length * length)
        if self.config.level_bias:
            value += self.config.level_bias * math.log10(max(length, NEAR_FIELD))
        if self.room is not None and self.room.blocked(a, p):
            self.counts["nlos"] += 1
            value += self.config.nlos_median * math.exp(self.config.nlos_shape * n_e)
        return value

    def pair_bias(self, i: int, j: int) -> float:
        """The bias of a TDOA between anchors ``i`` and ``j``: ``b_i - b_j`` (m)."""
        return float(self.biases[i] - self.biases[j])

    def line_of_sight(self, p: np.ndarray) -> np.ndarray:
        """``(m,)`` booleans: whether each anchor sees the tag at ``p`` (all true without a room)."""
        if self.room is None:
            return np.ones(self.m, dtype=bool)
        return np.array([not self.room.blocked(a, np.asarray(p, float)) for a in self.anchors])

    def measurements(self, position, duration: float, dt: float = 1e-3) -> list[Measurement]:
        """Every event of ``[0, duration)`` for a tag moving along ``position(t) -> (3,)``.

        Steps of ``dt`` with the velocity by central difference: for tests and studies
        without a world.
        """
        out: list[Measurement] = []
        steps = int(round(duration / dt))
        for k in range(steps):
            t = k * dt
            p = np.asarray(position(t), dtype=float)
            v = (np.asarray(position(t + 0.5 * dt)) - np.asarray(position(t - 0.5 * dt))) / dt
            out.extend(self.take(t, t + dt, p, v))
        return out


def radio_of(scenario) -> UwbRadio | None:
    """The radio of a scenario's ``[radio]`` table (``None`` without one), seeded by its seed.

    A planar scenario's anchors are placed in the plane ``z = 0`` (the tag's position is
    padded likewise by the world, :class:`~quadobs.testbed.worlds.radio_feed.RadioFeed`).

    ``room = "builtin"`` is the package's room (``uwb_room.xml``); another name is read
    relative to the scenario file.
    """
    spec = getattr(scenario, "radio", None)
    if spec is None:
        return None
    room = spec.room
    if room == "builtin":
        room = str(room_model_path())
    elif room is not None and not Path(room).is_absolute():
        source = Path(scenario.source) if scenario.source else None
        if source is not None and source.is_file():
            room = str(source.parent / room)
    config = RadioConfig(
        protocol=spec.protocol,
        rate=spec.rate,
        rates=spec.rates,
        std=spec.std,
        biases=spec.biases,
        bias_std=spec.bias_std,
        bias_mean=spec.bias_mean or 0.0,
        jitter=spec.jitter,
        dropout=spec.dropout,
        outlier_probability=spec.outlier_probability,
        outlier_std=spec.outlier_std,
        nlos_median=spec.nlos_median,
        nlos_shape=spec.nlos_shape,
        pattern=spec.pattern,
        level_bias=spec.level_bias,
        room=room,
    )
    anchors = np.asarray(scenario.beacons, dtype=float)
    if anchors.shape[1] == 2:  # a planar tag: the anchors and the tag in the plane z = 0
        anchors = np.column_stack([anchors, np.zeros(anchors.shape[0])])
    return UwbRadio(anchors, config, scenario.seed)
