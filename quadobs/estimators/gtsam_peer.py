"""The peer on logged data: GTSAM's iSAM2 [KAESS2012] on a factor graph of the log's measurements.

The graph has one node per measurement time (measurements at the same time share it; with
``key_period > 0``, every measurement within ``key_period`` seconds after a node shares
that node, on its position and velocity at its own time, ``p + v tau``, where the node has
a velocity, else read as if taken at its time), and the variables of the node depend on the
log's inputs (:data:`MOTIONS`):

===============  ========================  ================================================
input kind       variables of node ``i``   factor between consecutive nodes ``i, j``
===============  ========================  ================================================
``odometry``     ``X_i`` Pose2             ``BetweenFactorPose2``: the odometry composed over
                                           the interval, covariance ``diag(q_xy, q_xy,
                                           q_theta) T``
``none``         ``P_i``, ``V_i`` vectors  the constant-velocity prior: the double
                                           integrator with a white acceleration of
                                           intensity ``q_acc``
``accel_nav``    ``P_i``, ``V_i`` vectors  the double integrator driven by the held
                                           acceleration (``Delta p = int int a``,
                                           ``Delta v = int a``), white noise ``q_imu``
``imu_body``     ``X_i`` Pose3, ``V_i``,   ``CombinedImuFactor``: gtsam's IMU preintegration
                 ``B_i`` IMU bias          [FORSTER2017] of the body-frame specific force and
                                           angular rate, with the biases' random walk
===============  ========================  ================================================

(the double integrator's factor: :func:`~quadobs.estimators.gtsam_factors.double_integrator_factor`).
Each range adds :func:`~quadobs.estimators.gtsam_factors.range_factor` on the node's
position, each TDOA :func:`~quadobs.estimators.gtsam_factors.tdoa_factor`, both under a
robust loss (:class:`PeerNoise`: Huber or Cauchy, its threshold in standard deviations
of the stated noise). With ``bias="state"`` every anchor ``h`` has a constant range bias
``beta_h`` (a 1-vector variable with a zero-mean prior of ``bias_sigma``), and a range
is ``rho = |p - a_h| + beta_h``. The first node has a prior: the initial guess of the
position (``sqrt(P0)`` per axis), of the velocity (``velocity_sigma``), of the heading
(``heading_sigma``, odometry) or attitude and the IMU biases (``imu_body``).

Online: :meth:`Isam2Peer.correct` adds a measurement's factors, and the graph's new part
goes to iSAM2 (one ``update``) before the estimate is read or time moves on (with
``key_period > 0`` and :class:`PeerNoise` ``updates="node"``, once a node, when the next one
opens), so :attr:`Isam2Peer.x_hat` at any time is iSAM2's current estimate of the last node,
propagated with the inputs held since. Offline: :meth:`Isam2Peer.batch_trajectory` solves
the whole graph by Levenberg-Marquardt (started at iSAM2's final estimate);
:meth:`Isam2Peer.online_trajectory` is iSAM2's own final (smoothed) estimate of every node.

``gtsam`` is imported when an estimator is built (the ``data`` extra).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadobs.core.measurements import Measurement, RangeModel, TdoaModel
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.base import Counted, Estimator, check_step
from quadobs.estimators.gtsam_factors import range_factor, tdoa_factor
from quadobs.estimators.gtsam_motion import MOTIONS, make_motion

__all__ = ["Isam2Peer", "Isam2RangeOnly", "PeerNoise", "import_gtsam", "peer_refusal"]

#: The longest interval between two nodes across which their positions are interpolated to
#: the replay's grid for the smoothed and batch figures (s).
INTERPOLATION_GAP = 1.0

#: Robust losses of the measurement factors.
LOSSES = ("huber", "cauchy", "none")


def import_gtsam():
    """The ``gtsam`` module, or a one-line error saying how to install it."""
    try:
        import gtsam
    except ImportError:
        raise QuadobsError(
            "isam2: needs the gtsam package; install the data extra (pip install 'quadobs[data]')"
        ) from None
    return gtsam


@dataclass(frozen=True)
class PeerNoise:
    """The peer's noise settings, each default with its reason.

    Attributes
    ----------
    range_sigma : float
        Stated range standard deviation (m; 1 m, the replay's default).
    tdoa_sigma : float
        Stated TDOA standard deviation (m); NaN: ``range_sigma``.
    loss : {"huber", "cauchy", "none"}
        Robust loss of the range and TDOA factors.
    loss_threshold : float
        Its threshold in standard deviations (3: a Gaussian residual exceeds it with
        probability 0.27 %, so the inliers are weighed as by least squares and only the
        residuals beyond ``3 sigma`` metres are down-weighted).
    bias : {"none", "state"}
        A constant range bias per anchor as a state.
    bias_sigma : float
        Its prior standard deviation (m; the range model's, :meth:`RangeModel.extra_states`).
    q_xy, q_theta : float
        Odometry noise intensities (m^2/s, rad^2/s).
    heading_sigma : float
        Standard deviation of the odometry's heading prior (rad).
    q_acc : float
        White-acceleration intensity of the constant-velocity prior (m^2/s^3).
    q_imu : float
        Accelerometer white-noise intensity (m^2/s^3), for ``accel_nav`` and ``imu_body``.
    q_gyro : float
        Gyro white-noise intensity (rad^2/s); ``1e-6``: 1e-3 rad/s/sqrt(Hz), four times a
        consumer MEMS gyro's datasheet density, for the vibration of a vehicle.
    accel_bias_walk, gyro_bias_walk : float
        Random-walk intensities of the IMU biases (m^2/s^5, rad^2/s^3): ``1e-6`` and
        ``1e-8``, a drift of 1 mm/s^2 and 0.1 mrad/s over a second.
    accel_bias_sigma, gyro_bias_sigma : float
        Prior standard deviations of the IMU biases at the start (0.2 m/s^2, 0.02 rad/s:
        an uncalibrated consumer IMU).
    attitude_sigma : tuple of float
        Prior standard deviations of the initial roll, pitch (from the accelerometer's
        first sample: 0.1 rad) and yaw (unobserved at the start: 1 rad) (rad).
    velocity_sigma : float
        Standard deviation of the initial velocity per axis (m/s; 2, as the replay's filters).
    gravity : float
        Magnitude of gravity (m/s^2; standard gravity, the log format's default).
    frame : {"enu", "ned"}
        The navigation frame's z axis: up (gravity along ``-z``) or down (along ``+z``).
    key_period : float
        Measurements within this many seconds after a node share it (0: a node per time); a
        range or a TDOA then sits on the node's position and velocity at its own time (where
        the node has a velocity; else it is read as if taken at the node's time).
    updates : {"node", "measurement"}
        With ``key_period > 0``: iSAM2 updates once a node, when the next one opens
        (``"node"``; :meth:`Isam2Peer._flush`), or with each measurement (``"measurement"``,
        every measurement in the online estimate as it comes; iSAM2 then relinearises at
        each update, ``relinearizeSkip = 1``, where gtsam's default is every tenth: cheaper
        and quicker from a start far off on the flights measured, docs/peer.md).
    """

    range_sigma: float = 1.0
    tdoa_sigma: float = math.nan
    loss: str = "huber"
    loss_threshold: float = 3.0
    bias: str = "none"
    bias_sigma: float = 0.5
    q_xy: float = 0.1
    q_theta: float = 1e-3
    heading_sigma: float = 0.05
    q_acc: float = 1.0
    q_imu: float = 1e-2
    q_gyro: float = 1e-6
    accel_bias_walk: float = 1e-6
    gyro_bias_walk: float = 1e-8
    accel_bias_sigma: float = 0.2
    gyro_bias_sigma: float = 0.02
    attitude_sigma: tuple = (0.1, 0.1, 1.0)
    velocity_sigma: float = 2.0
    gravity: float = 9.80665
    frame: str = "enu"
    key_period: float = 0.0
    updates: str = "node"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise QuadobsError(f"loss: expected one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.bias not in ("none", "state"):
            raise QuadobsError(f"bias: expected 'none' or 'state', got {self.bias!r}")
        if self.frame not in ("enu", "ned"):
            raise QuadobsError(f"frame: expected 'enu' or 'ned', got {self.frame!r}")
        if self.updates not in ("node", "measurement"):
            raise QuadobsError(f"updates: expected 'node' or 'measurement', got {self.updates!r}")
        words = ("loss", "bias", "frame", "updates")
        numbers = {k: v for k, v in vars(self).items() if k not in words}
        numbers.update(
            {f"attitude_sigma[{i}]": v for i, v in enumerate(numbers.pop("attitude_sigma"))}
        )
        if math.isnan(numbers["tdoa_sigma"]):
            del numbers["tdoa_sigma"]
        for key, value in numbers.items():
            low = 0.0 if key == "key_period" else math.nextafter(0.0, 1.0)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= low):
                what = "non-negative" if key == "key_period" else "positive"
                raise QuadobsError(f"{key}: expected a {what} finite number, got {value!r}")
        if len(self.attitude_sigma) != 3:
            raise QuadobsError("attitude_sigma: expected three numbers (roll, pitch, yaw)")


def peer_refusal(input_kind: str, dimension: int) -> str | None:
    """Why the peer cannot take a log of these inputs and dimension (one line), or ``None``."""
    if input_kind not in MOTIONS:
        return f"inputs of kind {input_kind!r} (it takes {', '.join(MOTIONS)})"
    if input_kind == "odometry" and dimension != 2:
        return "odometry inputs on 3-D anchors (planar odometry needs a 2-D log)"
    if input_kind == "imu_body" and dimension != 3:
        return "a body-frame IMU on 2-D anchors (imu_body needs a 3-D log)"
    return None


class Isam2Peer(Estimator, Counted):
    """iSAM2 on the log's measurements and inputs, online and batch (module docstring).

    Parameters
    ----------
    anchors : array_like (m, d)
        Anchor positions (the indices of :attr:`Measurement.anchors` refer to their rows).
    input_kind : {"odometry", "none", "accel_nav", "imu_body"}
    x0 : array_like (n,)
        Initial guess: the position, then (``n = 2 d``) the velocity.
    P0 : float
        Variance of the initial position guess per axis (m^2).
    noise : PeerNoise, optional
    t0 : float
        Time of the first node (s).
    dt : float, optional
        The fixed grid's step, for :meth:`step` (and the grid steps of the nodes).
    heading0 : float
        Odometry: the heading at ``t0`` (rad). ``imu_body``: the initial yaw guess.
    fixed_bias : array_like (m,), optional
        Known range biases subtracted from every range (the range model's ``bias="fixed"``;
        not with ``bias="state"``).
    online : bool
        ``True`` (default): iSAM2 updates as the measurements arrive. ``False``: the graph is
        only built (:attr:`graph`, :attr:`values`: each new node's initial value propagated
        from the previous one by the held inputs), for a batch solution of the whole log
        (:meth:`batch_trajectory`) at a fraction of the cost; the estimate in between is that
        propagation, not an estimate from the measurements.
    """

    name = "isam2"
    #: The input the replay holds for it: ``"imu_body"`` for the raw body IMU (set for a body-IMU
    #: log), else ``None`` (the replay's own input of the log).
    replay_input: str | None = None

    def __init__(
        self,
        anchors,
        input_kind: str,
        *,
        x0,
        P0: float = 2500.0,
        noise: PeerNoise | None = None,
        t0: float = 0.0,
        dt: float | None = None,
        heading0: float = 0.0,
        fixed_bias=None,
        online: bool = True,
    ) -> None:
        gtsam = self._g = import_gtsam()
        self.online = bool(online)
        self.anchors = np.asarray(anchors, dtype=float)
        d = self.anchors.shape[1] if self.anchors.ndim == 2 else 0
        self.anchors = as_array("anchors", anchors, (None, d if d in (2, 3) else 3))
        reason = peer_refusal(input_kind, d)
        if reason is not None:
            raise QuadobsError(f"isam2: cannot take {reason}")
        self.noise = noise = noise if noise is not None else PeerNoise()
        self.dim, self.input_kind = d, input_kind
        self.x0 = as_array("x0", x0, (None,))
        self.n = self.x0.size
        if self.n not in (d, 2 * d):
            raise QuadobsError(f"x0: expected {d} or {2 * d} entries, got {self.n}")
        self.dt = None if dt is None else as_finite_scalar("dt", dt, positive=True)
        self._time = self._t0 = float(as_finite_scalar("t0", t0))
        if fixed_bias is not None and noise.bias == "state":
            raise QuadobsError("fixed_bias: known biases and biases as states exclude each other")
        self.ranges = RangeModel(
            self.anchors,
            noise.range_sigma,
            bias="fixed" if fixed_bias is not None else noise.bias,
            fixed_bias=None
            if fixed_bias is None
            else as_array("fixed_bias", fixed_bias, (len(self.anchors),)),
        )
        tdoa_sigma = noise.range_sigma if math.isnan(noise.tdoa_sigma) else noise.tdoa_sigma
        self.tdoas = TdoaModel(self.anchors, tdoa_sigma)
        self.measurement_models = {"range": self.ranges, "tdoa": self.tdoas}
        self._a2 = np.einsum("hi,hi->h", self.anchors, self.anchors)
        self._noises: dict = {}
        self.motion = make_motion(gtsam, input_kind, d, noise)
        params = gtsam.ISAM2Params()
        params.setFactorization(self.motion.factorization)
        if noise.key_period > 0.0 and noise.updates == "measurement":
            params.relinearizeSkip = 1  # relinearised at each update (the class docstring)
        self.isam = gtsam.ISAM2(params)
        self.graph, self.values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        self._g_new, self._v_new = gtsam.NonlinearFactorGraph(), gtsam.Values()
        self.motion.start(
            self._g_new,
            self._v_new,
            self.x0,
            float(as_finite_scalar("P0", P0, positive=True)),
            heading0,
        )
        self._bias_priors()
        self.key, self.node_times, self._steps, self.key_steps = 0, [self.time], 0, [0]
        self.corrections = 0
        #: Why iSAM2 stopped (gtsam refused an update), or ``None``: from then on the estimate
        #: is NaN, which the replay reports as a divergence, never summarised as if it ran.
        self.failure: str | None = None
        self._flush()

    # -- the graph ------------------------------------------------------------------------

    def _bias_key(self, h: int) -> int:
        return self._g.symbol("r", h)

    def _bias_priors(self) -> None:
        if self.noise.bias != "state":
            return
        gtsam = self._g
        for h, extra in enumerate(self.ranges.extra_states()):
            sigma = self.noise.bias_sigma if self.noise.bias_sigma > 0 else extra.prior_std
            key = self._bias_key(h)
            self._g_new.add(
                gtsam.PriorFactorVector(
                    key, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, sigma)
                )
            )
            self._v_new.insert(key, np.zeros(1))

    def _noise(self, sigma: float):
        """The robust noise model of one scalar measurement of standard deviation ``sigma`` (cached)."""
        model = self._noises.get(sigma)
        if model is None:
            gtsam, k = self._g, self.noise.loss_threshold
            base = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
            if self.noise.loss == "none":
                model = base
            else:
                est = gtsam.noiseModel.mEstimator
                loss = (est.Huber if self.noise.loss == "huber" else est.Cauchy).Create(k)
                model = gtsam.noiseModel.Robust.Create(loss, base)
            self._noises[sigma] = model
        return model

    def _flush(self, keyframe: bool = False) -> None:
        """The graph's new part to iSAM2 (one update), and the last node's estimate read back.

        ``keyframe`` (time moving on, the estimate read): with ``key_period > 0``, only once a
        node has opened since the last update, so that iSAM2 updates once per keyframe, not
        once per measurement; the estimate between takes the last node's measurements from
        the next node on."""
        if self._g_new.size() == 0 and self._v_new.size() == 0:
            return
        gated = self.noise.key_period > 0.0 and self.noise.updates == "node"
        if keyframe and gated and self._v_new.size() == 0:
            return
        g, v = self._g_new, self._v_new
        self._g_new, self._v_new = self._g.NonlinearFactorGraph(), self._g.Values()
        if self.failure is not None:
            return
        self.graph.push_back(g)
        self.values.insert(v)
        if not self.online:
            return
        try:
            self.isam.update(g, v)
        except RuntimeError as exc:  # gtsam's indeterminate system: the estimate is lost
            first = next((line for line in str(exc).splitlines() if line.strip()), "")
            self.failure = f"iSAM2 update at t = {self.time:.9g} s failed: {first.strip()}"
            return
        self.motion.read(self.isam, self.key)

    def _node_for(self, t: float) -> int:
        """The node a measurement at ``t`` (the current time) attaches to: the last one, or a new one."""
        if t - self.node_times[-1] <= self.noise.key_period + 1e-12:
            return self.key
        self.motion.close(self._g_new, self._v_new, self.key, self.key + 1)
        self.key += 1
        self.node_times.append(t)
        self.key_steps.append(self._steps)
        return self.key

    # -- the estimator interface ----------------------------------------------------------

    @property
    def time(self) -> float:
        """The current time (s). Set before anything happened, it moves the first node there too
        (the start of a log)."""
        return self._time

    @time.setter
    def time(self, value: float) -> None:
        t = as_finite_scalar("time", value)
        fresh = self.key == 0 and self.corrections == 0 and self._time == self.node_times[0]
        if not fresh:
            raise QuadobsError(f"{self.name}: time can be set only before the first correction")
        self._time = self.node_times[0] = float(t)

    def hold(self, u) -> None:
        """Hold the input ``u`` from the current time on (its layout: :mod:`quadobs.estimators.gtsam_motion`)."""
        self.motion.hold(as_array("u", u, (None,)))

    def predict(self, t: float) -> None:
        """Propagate to ``t`` with the held input (the graph's new part goes to iSAM2 first)."""
        dt = self._interval(t)
        self._flush(keyframe=True)
        if dt > 0.0:
            self._propagate(dt, None)
        self._time = float(t)

    def _propagate(self, dt: float, u) -> None:
        """The motion's inputs accumulated over ``dt`` (the input the motion holds; ``u`` unused)."""
        self.motion.advance(dt)

    def correct(self, m: Measurement) -> None:
        """The factor of one range or TDOA ``m`` taken at the current time, on its node.

        The value less its known bias (:meth:`MeasurementModel.unbiased`); its own standard
        deviation, or the model's.
        """
        self._check_measurement(m)
        model = self._model_of(m)
        node = self._node_for(self.time)
        key = self.motion.position_key(node)
        kind, noise = self.motion.position_type, self._noise(model.sigma(m))
        v_key, tau = self._offset(node)
        if m.kind == "range":
            (h,) = m.anchors
            bias_key = self._bias_key(h) if self.noise.bias == "state" else None
            rho = model.unbiased(m)
            factor = range_factor(
                self._g, noise, key, kind, self.anchors[h], rho, bias_key, v_key, tau
            )
        else:
            i, j = m.anchors
            a, d = self.anchors, model.unbiased(m)
            factor = tdoa_factor(self._g, noise, key, kind, a[i], a[j], d, v_key, tau)
        self._g_new.add(factor)
        self.corrections += 1

    def _offset(self, node: int) -> tuple[int | None, float]:
        """The velocity variable of ``node`` and the time since it (s) of a measurement taken now
        (a keyframe's), or ``(None, 0)`` at the node's own time or without a velocity variable."""
        tau = self.time - self.node_times[node]
        velocity_key = getattr(self.motion, "velocity_key", None)
        if tau <= 0.0 or velocity_key is None:
            return None, 0.0
        return velocity_key(node), tau

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """The fixed grid: the ranges ``y_h = rho_h^2 / 2 - |a_h|^2 / 2`` (NaN: none) at the current time, then ``u`` held over ``dt``."""
        if self.dt is None:
            raise QuadobsError("isam2: step() needs the grid's dt")
        u, y = check_step(u, y, self.motion.grid_inputs, len(self.anchors))
        for h in np.flatnonzero(~np.isnan(y)):
            rho = math.sqrt(max(2.0 * y[h] + self._a2[h], 0.0))
            self.correct(Measurement(self.time, "range", rho, (int(h),)))
        self.hold(u)
        self.predict(self.time + self.dt)
        self._steps += 1

    @property
    def x_hat(self) -> np.ndarray:
        """iSAM2's estimate of the last node propagated to the current time: the position (and velocity)."""
        self._flush(keyframe=True)
        if self.failure is not None:
            return np.full(self.n, np.nan)
        return self.motion.current(self.n)

    @property
    def biases(self) -> np.ndarray | None:
        """iSAM2's current estimate of the range bias per anchor (``bias="state"``), else ``None``."""
        if self.noise.bias != "state":
            return None
        self._online_only("biases")
        self._flush()
        est = self._estimate()
        return np.array([est.atVector(self._bias_key(h))[0] for h in range(len(self.anchors))])

    # -- the whole log ----------------------------------------------------------------------

    def online_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """The nodes' times ``(m,)`` and iSAM2's current (smoothed) positions of them ``(m, d)`` (NaN after a :attr:`failure`)."""
        self._online_only("online_trajectory")
        self._flush()
        if self.failure is not None:
            return self._lost()
        return self._positions(self._estimate())

    def batch_trajectory(self, max_iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
        """The nodes' times and positions in the Levenberg-Marquardt optimum of the whole graph,
        started at iSAM2's estimate (``online=False``: at :attr:`values`)."""
        self._flush()
        if self.failure is not None:
            return self._lost()
        gtsam = self._g
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(int(max_iterations))
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph, self._estimate(), params)
        try:
            return self._positions(opt.optimize())
        except RuntimeError:  # an indeterminate system for Levenberg-Marquardt too
            return self._lost()

    def _estimate(self):
        """iSAM2's current estimate of every variable (``online=False``: :attr:`values`)."""
        return self.isam.calculateEstimate() if self.online else self.values

    def _online_only(self, what: str) -> None:
        """Refuse ``what``, an estimate of iSAM2's, from a graph built with ``online=False``."""
        if not self.online:
            raise QuadobsError(
                f"{what}: the peer was built with online=False (no iSAM2 estimate); "
                "solve the graph with batch_trajectory"
            )

    def _lost(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.node_times), np.full((len(self.node_times), self.dim), np.nan)

    def online_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`online_trajectory` on the grid of ``dt`` (:meth:`_on_grid`)."""
        return self._on_grid(*self.online_trajectory())

    def batch_optimum(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`batch_trajectory` on the grid of ``dt`` (:meth:`_on_grid`)."""
        return self._on_grid(*self.batch_trajectory())

    def _on_grid(self, T: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid steps ``k`` (of ``t_k = t_0 + k dt``) and positions there.

        Stepped on the grid (:meth:`step`) with a node per step that has a measurement
        (``key_period`` 0), the nodes are grid steps: their steps and their positions. Run in
        time, or on keyframes, the nodes lie anywhere or some steps apart: the positions
        interpolated linearly between two consecutive nodes to the grid times between them,
        where the nodes are at most :data:`INTERPOLATION_GAP` apart (the chord's error,
        ``v omega T^2 / 8``, is then at most 6 cm at 1 m/s turning at 0.5 rad/s); a longer gap
        has no figure at its times.
        """
        if self.dt is None or (self._steps > 0 and self.noise.key_period == 0.0):
            return np.array(self.key_steps), P
        k = np.arange(int(np.floor((T[-1] - T[0]) / self.dt + 1e-9)) + 1)
        t = T[0] + k * self.dt
        i = np.clip(np.searchsorted(T, t, side="right") - 1, 0, max(T.size - 2, 0))
        near = (T.size == 1) | (T[np.minimum(i + 1, T.size - 1)] - T[i] <= INTERPOLATION_GAP)
        near |= np.isin(t, T)  # a grid time that is a node's own
        k, t = k[near], t[near]
        return k, np.column_stack([np.interp(t, T, P[:, c]) for c in range(P.shape[1])])

    def _positions(self, values) -> tuple[np.ndarray, np.ndarray]:
        from quadobs.estimators.gtsam_factors import position_of

        kind = self.motion.position_type
        P = [position_of(values, self.motion.position_key(i), kind)[0] for i in range(self.key + 1)]
        return np.array(self.node_times), np.array(P)


#: The name of earlier releases (the planar odometry peer), kept for callers that test for it.
Isam2RangeOnly = Isam2Peer
