"""How an episode cuts its steps into blocks (shared by the episode loop and the worlds)."""

from __future__ import annotations

__all__ = ["LEAD", "TAIL", "block_count"]

#: Steps of an episode's first block (see :func:`block_count`).
LEAD = 1024

#: The fewest steps of a block after the first, but the last (see :func:`block_count`).
TAIL = 512


def block_count(k0: int, steps: int, capacity: int, lead: int = LEAD, tail: int = TAIL) -> int:
    """Steps of the block that starts at step ``k0`` of an episode of ``steps`` steps.

    The first block has at most ``lead`` steps; after it, each block takes a quarter of
    what is left, at least ``tail`` and at most ``capacity`` steps, so that blocks shrink
    by a quarter towards the end. A world that computes the physics of the blocks ahead
    while the current one is read (:class:`~quadobs.testbed.worlds.PointMassWorld`) reads a
    block only once its physics is done: the reader, faster than the physics by more than
    a quarter, then keeps up as the blocks shrink and is one short block behind when the
    physics ends. Results do not depend on where blocks begin (the sensor layer draws its
    noise in its own batches).

    Examples
    --------
    >>> k, blocks = 0, []
    >>> while k < 20000:
    ...     blocks.append(block_count(k, 20000, 8192))
    ...     k += blocks[-1]
    >>> blocks
    [1024, 4744, 3558, 2668, 2001, 1501, 1126, 844, 633, 512, 512, 512, 365]
    """
    left = steps - k0
    lead = max(min(lead, capacity), 1)
    if k0 == 0:
        return min(left, lead)
    return min(capacity, max(min(tail, capacity), left // 4), left)
