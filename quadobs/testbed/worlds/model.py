"""Loading the MJCF vehicle and checking that it is the model the estimators assume.

The built-in model is ``models/vehicle.xml`` (shipped inside the wheel as
``quadobs/_models/vehicle.xml``). Every element is looked up by name; a missing one is
reported by name. Beacons missing from the model are added with MuJoCo's model editing
API (``mujoco.MjSpec``) at the scenario's positions.
"""

from __future__ import annotations

import contextlib
import os
import stat
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from quadobs.errors import QuadobsError, RunFault, abbreviated, as_array, as_finite_scalar

__all__ = [
    "REQUIRED_ELEMENTS",
    "PhysicsFault",
    "VehicleModel",
    "builtin_model_path",
    "default_model_path",
    "load_vehicle_model",
    "physics_check",
]

#: (kind, name) of the elements a vehicle model must define.
REQUIRED_ELEMENTS = (
    ("body", "vehicle"),
    ("joint", "vehicle_joint"),
    ("site", "imu"),
    ("actuator", "force_x"),
    ("actuator", "force_y"),
    ("actuator", "force_z"),
    ("sensor", "accelerometer"),
    ("sensor", "velocimeter"),
)


def builtin_model_path(name: str) -> Path:
    """The built-in MJCF file ``name``: inside the installed package, or ``models/`` of a source checkout."""
    here = Path(__file__).resolve().parents[2]
    for candidate in (here / "_models" / name, here.parent / "models" / name):
        if candidate.is_file():
            return candidate
    raise QuadobsError(
        f"model: the built-in {name} was not found beside the package (broken installation)"
    )


def default_model_path() -> Path:
    """The built-in vehicle MJCF (:func:`builtin_model_path`)."""
    return builtin_model_path("vehicle.xml")


@dataclass(frozen=True, eq=False)
class VehicleModel:
    """A compiled vehicle model with the indices the testbed needs.

    Attributes
    ----------
    model : mujoco.MjModel
    path : str
        Where the MJCF came from.
    beacons : ndarray (q_b, 3)
        Beacon positions as compiled (world frame).
    mass : float
        Mass of the vehicle subtree (kg): the force for an acceleration ``a`` is ``mass * a``.
    """

    model: mujoco.MjModel
    path: str
    beacons: np.ndarray
    mass: float
    qpos_adr: int
    qvel_adr: int
    site_id: int
    accel_adr: int
    velocimeter_adr: int
    offset_adr: np.ndarray  # (q_b,) sensordata addresses of the beacon-relative positions
    actuator_ids: np.ndarray  # (3,)
    gravity: np.ndarray  # (3,)


def _model_file(path) -> Path:
    """``path`` if it names a readable regular file, else a :class:`QuadobsError` saying what it is."""
    text = str(path)
    shown = abbreviated(text)
    if not text.strip() or "\0" in text or len(text) > 4096:
        raise QuadobsError(
            f"model: {shown!r} is not a file name (empty, holding NUL or longer than 4096 characters)"
        )
    try:
        st = os.stat(text)
    except FileNotFoundError:
        raise QuadobsError(f"model: MJCF file {shown!r} does not exist") from None
    except OSError as exc:  # a symbolic-link loop, a name too long, a component that is a file
        raise QuadobsError(
            f"model: MJCF file {shown!r} cannot be opened ({exc.strerror})"
        ) from None
    if stat.S_ISDIR(st.st_mode):
        raise QuadobsError(f"model: {shown!r} is a directory, expected an MJCF file")
    if not stat.S_ISREG(st.st_mode):
        raise QuadobsError(
            f"model: {shown!r} is not a regular file (a device or a FIFO), expected an MJCF file"
        )
    _check_model_size(Path(text), st.st_size, shown)
    return Path(text)


#: Largest MJCF file read (bytes), and most ``<body>`` elements in it: a vehicle is a few bodies;
#: MuJoCo's parse, which cannot be interrupted, takes minutes for 100 000 of them.
MAX_MODEL_BYTES, MAX_BODIES = 4 << 20, 1000


def _check_model_size(path: Path, size: int, shown: str) -> None:
    """Refuse, before MuJoCo parses it, an MJCF file over :data:`MAX_MODEL_BYTES` or :data:`MAX_BODIES` bodies."""
    if size > MAX_MODEL_BYTES:
        raise QuadobsError(
            f"model: {shown!r} has {size:,} bytes; an MJCF vehicle of at most {MAX_MODEL_BYTES:,} is read"
        )
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise QuadobsError(f"model: MJCF file {shown!r} cannot be read ({exc.strerror})") from None
    bodies = text.count(b"<body")
    if bodies > MAX_BODIES:
        raise QuadobsError(
            f"model: {shown!r} has {bodies:,} bodies; a vehicle model of at most {MAX_BODIES:,} is read"
        )


def _one_line_text(text: object) -> str:
    """MuJoCo's multi-line messages on one line: the lines stripped, joined with "; "."""
    return "; ".join(line.strip() for line in str(text).splitlines() if line.strip())


def _find(spec: mujoco.MjSpec, kind: str, name: str):
    finder = getattr(spec, kind)
    try:
        return finder(name)
    except Exception:
        return None


def _add_beacons(spec, beacons: np.ndarray) -> np.ndarray:
    """Add (or move) a world site and a ``framepos`` sensor of ``imu`` relative to it per beacon; returns ``(q_b, 3)``."""
    b3 = np.zeros((beacons.shape[0], 3))
    b3[:, : beacons.shape[1]] = beacons
    for h, pos in enumerate(b3):
        site_name, sensor_name = f"beacon{h}", f"beacon{h}_offset"
        site = _find(spec, "site", site_name)
        if site is None:
            site = spec.worldbody.add_site(
                name=site_name, pos=pos, size=[0.4, 0, 0], rgba=[1.0, 0.5, 0.0, 1.0]
            )
        else:
            site.pos = pos
        if _find(spec, "sensor", sensor_name) is None:
            spec.add_sensor(
                name=sensor_name,
                type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
                objtype=mujoco.mjtObj.mjOBJ_SITE,
                objname="imu",
                reftype=mujoco.mjtObj.mjOBJ_SITE,
                refname=site_name,
            )
    return b3


@contextlib.contextmanager
def _warnings_refused(name: str):
    """MuJoCo's warnings while a model is parsed and compiled (a NaN in the XML, for one) become an error.

    Without this MuJoCo prints the warning, appends it to ``MUJOCO_LOG.TXT`` in the working
    directory and goes on: a vehicle of mass NaN was accepted.
    """
    said: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda text: said.append(str(text).strip()))
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)
    if said:
        raise QuadobsError(f"model {name}: MuJoCo warns: {_one_line_text(said[0])}")


def _check_dynamics(model, name: str):
    """The compiled model realises the double integrator: RK4, no fluid, no contact, damping or friction."""
    if model.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4:
        raise QuadobsError(
            f"model {name}: option integrator must be RK4 (exact for the double integrator under a held input)"
        )
    if model.opt.density != 0 or model.opt.viscosity != 0:
        raise QuadobsError(
            f"model {name}: fluid density and viscosity must be 0 (the wind must exert no force)"
        )
    body = model.body("vehicle")
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == body.id and (model.geom_contype[g] or model.geom_conaffinity[g]):
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
            raise QuadobsError(
                f"model {name}: geom {name!r} of the vehicle must have contype=0 and conaffinity=0"
            )
    joint = model.joint("vehicle_joint")
    if np.any(model.dof_damping[joint.dofadr[0] : joint.dofadr[0] + 6]) or np.any(
        model.dof_frictionloss[joint.dofadr[0] : joint.dofadr[0] + 6]
    ):
        raise QuadobsError(
            f"model {name}: joint 'vehicle_joint' must have no damping or friction loss"
        )
    return body, joint


def _check_beacons(model, b3: np.ndarray, name: str) -> tuple[list[int], np.ndarray]:
    """Each beacon sensor measures ``imu`` relative to its world site; returns their addresses and positions."""
    offset_adr = []
    for h in range(b3.shape[0]):
        sensor = model.sensor(f"beacon{h}_offset")
        site = model.site(f"beacon{h}")
        if (
            sensor.type[0] != mujoco.mjtSensor.mjSENS_FRAMEPOS
            or sensor.objid[0] != model.site("imu").id
            or sensor.refid[0] != site.id
            or sensor.reftype[0] != mujoco.mjtObj.mjOBJ_SITE
        ):
            raise QuadobsError(
                f"model {name}: sensor 'beacon{h}_offset' must be a framepos of site 'imu' relative to site 'beacon{h}'"
            )
        if site.bodyid[0] != 0:
            raise QuadobsError(f"model {name}: site 'beacon{h}' must belong to the world body")
        offset_adr.append(int(sensor.adr[0]))
    compiled_beacons = np.array([model.site(f"beacon{h}").pos for h in range(b3.shape[0])])
    if not np.allclose(compiled_beacons, b3):
        raise QuadobsError(
            f"model {name}: beacon sites must sit directly in the world body, without a frame offset"
        )
    return offset_adr, compiled_beacons


def _check_actuators(model, joint, name: str) -> np.ndarray:
    """The three force actuators act on the free joint along x, y, z, unlimited; returns their ids."""
    actuators = np.array([model.actuator(f"force_{a}").id for a in "xyz"])
    for a, act in zip("xyz", actuators):
        expected = np.zeros(6)
        expected["xyz".index(a)] = 1.0
        if model.actuator_trnid[act, 0] != joint.id or not np.allclose(
            model.actuator_gear[act], expected
        ):
            raise QuadobsError(
                f"model {name}: actuator 'force_{a}' must act on 'vehicle_joint' with gear {expected.astype(int).tolist()}"
            )
        if model.actuator_ctrllimited[act] or model.actuator_forcelimited[act]:
            raise QuadobsError(
                f"model {name}: actuator 'force_{a}' must not be control- or force-limited"
            )
    return actuators


def load_vehicle_model(
    beacons: np.ndarray,
    *,
    path: str | Path | None = None,
    timestep: float = 1e-3,
    wind: np.ndarray | None = None,
) -> VehicleModel:
    """Load and check the vehicle MJCF, add beacons, set the time step and the wind.

    Parameters
    ----------
    beacons : array_like (q_b, 2 or 3)
        Beacon positions; 2-D positions lie in the plane ``z = 0``.
    path : str or Path, optional
        MJCF file; the built-in vehicle when omitted.
    timestep : float
        Physics step (s).
    wind : array_like (2 or 3,), optional
        Constant wind, stored in ``opt.wind`` (MuJoCo's own wind, read back by the
        airspeed sensor). The model must have no fluid density or viscosity, so the wind
        exerts no force.

    Raises
    ------
    QuadobsError
        Missing file or element (named), a free joint missing, a contact-enabled geom,
        a non-RK4 integrator, fluid forces, or a beacon sensor that does not measure
        ``imu`` relative to its beacon site.
    """
    beacons = as_array("beacons", beacons, ndim=2)
    if beacons.shape[1] not in (2, 3) or beacons.shape[0] == 0:
        raise QuadobsError(f"beacons: expected shape (q, 2 or 3) with q >= 1, got {beacons.shape}")
    timestep = as_finite_scalar("timestep", timestep, positive=True)
    if wind is not None:
        wind = as_array("wind", wind, (beacons.shape[1],))
    mjcf = _model_file(path) if path is not None else default_model_path()
    with _warnings_refused(mjcf.name):
        try:
            spec = mujoco.MjSpec.from_file(str(mjcf))
        except Exception as exc:
            raise QuadobsError(f"model: cannot parse {mjcf.name}: {_one_line_text(exc)}") from None

    for kind, name in REQUIRED_ELEMENTS:
        if _find(spec, kind, name) is None:
            raise QuadobsError(f"model {mjcf.name}: missing {kind} named {name!r}")
    if spec.joint("vehicle_joint").type != mujoco.mjtJoint.mjJNT_FREE:
        raise QuadobsError(f"model {mjcf.name}: joint 'vehicle_joint' must be a free joint")

    b3 = _add_beacons(spec, beacons)
    spec.option.timestep = float(timestep)
    if wind is not None:
        w3 = np.zeros(3)
        w3[: len(wind)] = wind
        spec.option.wind = w3
    with _warnings_refused(mjcf.name):
        try:
            model = spec.compile()
        except Exception as exc:
            raise QuadobsError(
                f"model {mjcf.name}: does not compile: {_one_line_text(exc)}"
            ) from None

    body, joint = _check_dynamics(model, mjcf.name)
    offset_adr, compiled_beacons = _check_beacons(model, b3, mjcf.name)
    actuators = _check_actuators(model, joint, mjcf.name)

    return VehicleModel(
        model=model,
        path=str(mjcf),
        beacons=compiled_beacons,
        mass=float(model.body_subtreemass[body.id]),
        qpos_adr=int(joint.qposadr[0]),
        qvel_adr=int(joint.dofadr[0]),
        site_id=int(model.site("imu").id),
        accel_adr=int(model.sensor("accelerometer").adr[0]),
        velocimeter_adr=int(model.sensor("velocimeter").adr[0]),
        offset_adr=np.array(offset_adr, dtype=int),
        actuator_ids=actuators,
        gravity=np.array(model.opt.gravity, dtype=float),
    )


#: MuJoCo's warnings that mean the simulated truth is no longer valid: a non-finite or huge
#: position, velocity, acceleration (MuJoCo then resets the state and goes on) or control.
PHYSICS_FAULTS = ("mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC", "mjWARN_BADCTRL")


class PhysicsFault(RunFault):
    """MuJoCo reported an unstable or invalid simulation: the episode's truth is wrong from that step on."""


def _world_data(world):
    """The ``mujoco.MjData`` a world steps (``world.data`` or ``world.sim.data``), else ``None``."""
    data = getattr(world, "data", None)
    if data is None:
        data = getattr(getattr(world, "sim", None), "data", None)
    return data if isinstance(data, mujoco.MjData) else None


def _warning_reader(world):
    """A function giving MuJoCo's warning counts after the world's last block, or ``None``.

    The world's own ``physics_warnings()`` where it has one (a world computing the next
    block in the background keeps the counts of the block just filled); else the counts of
    its ``MjData`` now.
    """
    own = getattr(world, "physics_warnings", None)
    if callable(own):
        return own
    data = _world_data(world)
    if data is None:
        return None
    return lambda: (data.warning.number.copy(), data.warning.lastinfo.copy())


def _first_jump(world, dim: int, dt: float, count: int) -> int | None:
    """The first row ``j`` of the block whose true position does not follow from the velocities
    (``|p_{j+1} - p_j - dt (v_j + v_{j+1}) / 2|`` beyond rounding, or not finite), else ``None``."""
    columns, out = getattr(world, "columns", None), getattr(world, "out", None)
    if columns is None or out is None or count < 2:
        return None
    X = np.asarray(out[:count, columns.truth], dtype=float)
    p, v = X[:, :dim], X[:, dim : 2 * dim]
    with np.errstate(all="ignore"):
        r = np.abs(np.diff(p, axis=0) - 0.5 * dt * (v[1:] + v[:-1])).max(axis=1)
        bad = ~(r <= 1e-6 * (1.0 + np.abs(p[:-1]).max(axis=1)))
    hits = np.flatnonzero(bad)
    return int(hits[0]) if hits.size else None


def _drop_warning(text: str) -> None:
    """MuJoCo's warning handler during episodes: the text is dropped, the warning counted.

    MuJoCo's default handler prints the warning and appends it to ``MUJOCO_LOG.TXT`` in the
    working directory. The counters it also increments (``MjData.warning``) are what
    :func:`physics_check` reads, and the episode reports the fault on one line.
    """


def physics_check(world, scenario):
    """A check of MuJoCo's warning counters, called after every block of steps.

        Returns ``check(k0, count)``, which raises :class:`PhysicsFault` when any counter of
        :data:`PHYSICS_FAULTS` has grown during the block of steps ``[k0, k0 + count)``. MuJoCo
        then resets the state (to ``qpos0``, at rest) and goes on, so the block's truth jumps:
        the message names the warning and the step and time of the first row whose position
        does not follow from the velocities (:func:`_first_jump`), or the block's span when
        there is no such row (a bad control, which MuJoCo zeroes). For a world without a single ``MjData`` the check does nothing.
    A world that computes the next block in the background gives the counts of the block just
    filled (``physics_warnings()``).

        The check costs a few integer reads per block of thousands of steps. MuJoCo's own printing of
        its warnings (and its log file in the working directory) is replaced by
        :func:`_drop_warning`, unless a handler of the user's is installed.
    """
    counts = _warning_reader(world)
    if counts is None:
        return lambda k0, count: None
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_drop_warning)
    dt, dim = float(scenario.dt), int(scenario.dimension)
    slots = [(name, int(getattr(mujoco.mjtWarning, name))) for name in PHYSICS_FAULTS]
    first = counts()
    seen = {i: int(first[0][i]) for _, i in slots}

    def check(k0: int, count: int) -> None:
        now = counts()
        for name, i in slots:
            if int(now[0][i]) > seen[i]:
                j = _first_jump(world, dim, dt, count)
                if j is None:  # e.g. a bad control, which MuJoCo zeroes: no jump in the state
                    where = f"between step {k0} and step {k0 + count} (t = {k0 * dt:.6g} to {(k0 + count) * dt:.6g} s)"
                else:
                    where = f"at step {k0 + j} (t = {(k0 + j) * dt:.6g} s)"
                raise PhysicsFault(
                    f"physics: MuJoCo reported {name[7:].lower()} (index {int(now[1][i])}) {where}; "
                    "the simulation is unstable, the run stopped (see the scenario's trajectory, model and physics_rate)"
                )

    return check
