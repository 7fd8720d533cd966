"""What a world gives an episode: the truth and the sensor readings of a block of steps.

A world owns the block's rows, ``out (capacity + 1, width)``; row ``j`` of a block that
starts at physics step ``k0`` describes step ``k = k0 + j`` (time ``t_k = k dt``):

==================  ===============================================================
columns             row ``j``
==================  ===============================================================
``truth (n)``       the true estimator state ``x_k`` (row ``count``: ``x_(k0 + count)``)
``y (q)``           the outputs sampled at ``t_k`` (NaN: missing), after the sensor layer
``u (p)``           the measured input held over ``[t_k, t_(k+1))``
``measured (q_b)``  the measured ranges (NaN where not sampled), for the recording
``extra``           any raw readings of the world's own (named slices)
==================  ===============================================================

Two ways to fill a block (:attr:`World.closed_loop`):

* open loop (``False``): the controls of the block are known before it starts, so
  :meth:`World.fill` may produce every row in one call (``mujoco.rollout`` for instance);
  Such a world may also compute the physics of the blocks ahead in a background thread
  while the episode reads the current one (the point mass does,
  :attr:`World.computes_ahead`); :meth:`World.close` drops them;
* closed loop (``True``): the episode calls :meth:`World.step` once per step with the
  estimate ``x_hat_k`` of the estimator named :attr:`World.controller` (``None``: the
  episode's primary estimator), read before the estimators consume row ``k``; the world
  chooses its control from it.

Either way a world may apply the sensor layer itself (the point mass does it in the same
compiled call as its read-out); :meth:`World.commit` then counts the sensor events of the
rows the episode kept.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["Columns", "World"]


@dataclass(frozen=True)
class Columns:
    """Where each quantity lies in a world's rows (slices of ``out``'s columns).

    Parameters
    ----------
    truth, y, u, measured : slice
        The true state ``(n)``, outputs ``(q)``, input ``(p)`` and measured ranges ``(q_b)``.
    width : int
        Columns of a row.
    extra : dict of str to slice
        Further readings of the world (e.g. ``airspeed``), by name.

    Examples
    --------
    >>> c = Columns(truth=slice(0, 4), y=slice(4, 7), u=slice(7, 9), measured=slice(9, 12), width=12)
    >>> c.n, c.q
    (4, 3)
    """

    truth: slice
    y: slice
    u: slice
    measured: slice
    width: int
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        named = {
            "truth": self.truth,
            "y": self.y,
            "u": self.u,
            "measured": self.measured,
            **self.extra,
        }
        for name, s in named.items():
            if not (0 <= s.start <= s.stop <= self.width):
                raise QuadobsError(
                    f"columns.{name}: {s} does not fit in a row of width {self.width}"
                )

    @property
    def n(self) -> int:
        """State dimension."""
        return self.truth.stop - self.truth.start

    @property
    def q(self) -> int:
        """Number of outputs."""
        return self.y.stop - self.y.start


class World(abc.ABC):
    """The truth and raw sensor readings of an episode, a block of steps at a time.

    Subclasses set :attr:`columns`, :attr:`dt` and :attr:`out` and implement
    :meth:`state`, :meth:`begin_block` and :meth:`step`; an open-loop world that can fill a
    whole block at once overrides :meth:`fill`.

    Attributes
    ----------
    closed_loop : bool
        ``True``: the control of each step depends on an estimate (see the module docstring).
    controller : str or None
        Closed loop: the name of the estimator whose estimate drives the controls
        (``None``: the primary estimator).
    columns : Columns
    dt : float
        Physics step (s).
    out : ndarray (capacity + 1, columns.width)
        The rows of the current block.
    events : ndarray (capacity + 1, 2)
        Per step of the block after :meth:`commit`: outliers delivered and samples dropped.
    """

    closed_loop: bool = False
    controller: str | None = None
    columns: Columns
    dt: float
    out: np.ndarray
    events: np.ndarray

    @abc.abstractmethod
    def state(self) -> np.ndarray:
        """The true state now ``(n,)`` (before the first block: the initial state ``x_0``)."""

    @abc.abstractmethod
    def begin_block(self, k0: int, count: int) -> int:
        """Start the block of steps ``k0 .. k0 + count - 1``: row 0 gets the truth ``x_k0``.

        Returns the number of steps of the block (at most the capacity).
        """

    @abc.abstractmethod
    def step(self, j: int, estimate: np.ndarray | None = None) -> None:
        """Step ``j`` of the block: readings of step ``k0 + j`` into row ``j``, truth after it into row ``j + 1``.

        ``estimate`` is ``x_hat`` at ``t_(k0 + j)`` for a closed-loop world, ``None`` otherwise.
        """

    def fill(self, count: int) -> None:
        """Open loop: every row of the block (``count`` steps). The default steps one at a time."""
        if self.closed_loop:
            raise QuadobsError(
                f"{type(self).__name__}: a closed-loop world is stepped one step at a time"
            )
        step = self.step
        for j in range(count):
            step(j)

    def sinks(self, recording=None) -> list:
        """Sinks of the world's own (e.g. a flight's tracking figures), run beside the episode's.

        ``recording`` is the episode's recording sink (``None`` without a recording). The
        default: none.
        """
        return []

    def prepare(self, path: str) -> None:
        """Load (or compile) what the episode's ``path`` (``"block"`` or ``"step"``) needs, before its loop. The default: nothing."""

    def close(self) -> None:
        """Release what the world holds beyond the episode's loop (a block computing ahead). The default: nothing."""

    @property
    def computes_ahead(self) -> bool:
        """Whether the physics of the blocks ahead is computed in the background while a block is read (after
        :meth:`prepare`): the reader's waits are then free time, which the recording uses. The default: ``False``."""
        return False

    def commit(self, rows: int) -> None:
        """Count the sensor events (outliers, dropouts) of the first ``rows`` steps of the block.

        Called exactly once per block, with the steps the episode keeps; the per-step counts
        are then in :attr:`events` ``[:rows]``. The default: no events.
        """
        self.events[:rows] = 0
