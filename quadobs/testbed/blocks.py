"""How an episode cuts its steps into blocks (shared by the episode loop and the worlds)."""

from __future__ import annotations

__all__ = ["LEAD", "block_count"]

#: Steps of an episode's first and last blocks (see :func:`block_count`).
LEAD = 1024


def block_count(k0: int, steps: int, capacity: int, lead: int = LEAD) -> int:
    """Steps of the block that starts at step ``k0`` of an episode of ``steps`` steps.

    The first block and the last one have at most ``lead`` steps, the others ``capacity``
    (the one before the last takes what is left): a world that computes the next block's
    physics while the current one is read (:class:`~quadobs.testbed.worlds.PointMassWorld`)
    then waits alone only over short blocks at the start and the end. Results do not
    depend on where blocks begin (the sensor layer draws its noise in its own batches).

    Examples
    --------
    >>> [block_count(k, 20000, 8192) for k in (0, 1024, 9216, 17408, 18976)]
    [1024, 8192, 8192, 1568, 1024]
    """
    left = steps - k0
    lead = max(min(lead, capacity), 1)
    if k0 == 0 or left <= lead:
        return min(left, lead)
    return capacity if left > capacity + lead else left - lead
