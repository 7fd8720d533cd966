"""The GTSAM peer of a replay (:class:`~quadobs.estimators.gtsam_peer.Isam2Peer`), built from a :class:`ReplaySetup`.

The peer reads the log's own inputs, whatever the replay's model: an odometry log gives
the planar odometry graph (also under ``--model cv``, whose state size then sets the
estimate's: the position and the velocity), an accelerometer log (inputs in the
navigation frame) the double integrator driven by the accelerometer, a log of ranges
alone the constant-velocity prior, a body-frame IMU log gtsam's IMU preintegration. Its
noise is the setup's (the same stated noise as the other estimators): ``range_sigma``,
``q_xy``, ``q_theta``, ``q_acc``, ``q_imu``; its keyframes by the log's kind
(:func:`keyframes`); the rest is :class:`~quadobs.estimators.gtsam_peer.PeerNoise`'s defaults. Where the setup has them, the
attributes ``range_bias`` (1 or ``"state"``: a constant bias per anchor as a state;
:attr:`ReplaySetup.range_bias`, ``quadobs replay --tune range_bias=1``), ``gravity``
and ``frame`` (the log's, for the IMU preintegration) are read too.

:func:`check_peer` refuses a log the peer cannot take, with one line naming what the log
has, before any calibration.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError

__all__ = [
    "KEY_PERIOD",
    "TDOA_KEY_PERIOD",
    "build_peer",
    "check_peer",
    "keyframes",
    "peer_input_kind",
]

#: The log's input kinds (:data:`quadobs.testbed.logs.format.INPUT_KINDS` and those of the
#: measurements' :data:`~quadobs.core.measurements.INPUT_KINDS`) as the peer's.
_KINDS = {"imu": "accel_nav"}


def peer_input_kind(input_kind: str) -> str:
    """The peer's input kind for a log's: an accelerometer log (``imu``) is ``accel_nav``; the rest as they are."""
    return _KINDS.get(input_kind, input_kind)


def check_peer(input_kind: str, dimension: int, name: str = "isam2") -> None:
    """One line naming what the log has that the peer cannot take, or nothing."""
    from quadobs.estimators.gtsam_motion import MOTIONS
    from quadobs.estimators.gtsam_peer import peer_refusal

    kind = peer_input_kind(input_kind)
    reason = (
        peer_refusal(kind, int(dimension)) if kind in MOTIONS else f"inputs of kind {input_kind!r}"
    )
    if reason is not None:
        raise QuadobsError(f"estimators: {name!r} cannot take a log with {reason}")


#: The peer's keyframe period (s) (:class:`~quadobs.estimators.gtsam_peer.PeerNoise`
#: ``key_period``) on a log holding TDOA, or whose nodes have a velocity (ranges alone, an
#: accelerometer, a body IMU: every log but wheel odometry's). A TDoA3 tag hears a packet
#: every few milliseconds (100 Hz in ``quadrotor-tdoa``), a two-way-ranging tag ranges at 50
#: to 400 Hz over its anchors, and a node per measurement made iSAM2's updates the peer's
#: whole cost, each growing with the nodes so far (a 20 s flight of ranges at 100 Hz: 25 ms
#: a range; its first 10 s, 11 ms). A node about every 0.1 s (opened by the first
#: measurement more than 0.1 s after the last), each measurement on its node's
#: position and velocity at its own time (``p + v tau``, whose error ``a tau^2 / 2`` is 5 mm
#: at 1 m/s^2, a twentieth of the radio's 0.1 m): a tenth of the nodes. Wheel odometry's
#: ``Pose2`` nodes have no velocity, so there a range would be moved in time: a node per
#: measurement time. Ranges update iSAM2 with each (``updates="measurement"``: none waits
#: for its node to close); TDOA once a node (docs/tdoa.md, section 5). Timings: docs/peer.md.
KEY_PERIOD = 0.1
#: The name under which :data:`KEY_PERIOD` was first given, for TDOA alone.
TDOA_KEY_PERIOD = KEY_PERIOD


def keyframes(input_kind: str, kinds) -> dict:
    """The peer's ``key_period`` and ``updates`` (:class:`~quadobs.estimators.gtsam_peer.PeerNoise`)
    for a log of ``input_kind`` holding the measurement ``kinds`` (:data:`KEY_PERIOD`)."""
    if "tdoa" in tuple(kinds):
        return {"key_period": KEY_PERIOD, "updates": "node"}
    if peer_input_kind(input_kind) == "odometry":
        return {"key_period": 0.0, "updates": "node"}
    return {"key_period": KEY_PERIOD, "updates": "measurement"}


def build_peer(s, x0: np.ndarray, name: str = "isam2"):
    """The GTSAM peer on the replay's log (module docstring), ``s`` a :class:`~quadobs.testbed.logs.estimators.ReplaySetup`."""
    check_peer(s.input_kind, s.dim, name)
    from quadobs.estimators.gtsam_peer import Isam2Peer, PeerNoise

    noise = PeerNoise(
        range_sigma=s.range_sigma,
        q_xy=s.q_xy,
        q_theta=s.q_theta,
        q_acc=s.q_acc,
        q_imu=s.q_imu,
        bias="state" if getattr(s, "range_bias", 0) in (1, "state") else "none",
        **keyframes(s.input_kind, getattr(s, "kinds", ())),
        **{k: getattr(s, k) for k in ("gravity", "frame") if hasattr(s, k)},
    )
    est = Isam2Peer(
        s.beacons,
        peer_input_kind(s.input_kind),
        x0=np.asarray(x0, dtype=float)[: s.n],
        P0=s.P0,
        noise=noise,
        t0=float(getattr(s, "t0", 0.0)),
        dt=s.dt,
        heading0=s.heading0,
    )
    est.name = name
    if est.input_kind == "imu_body":  # the replay holds the raw body IMU samples for it
        est.replay_input = "imu_body"
    return est
