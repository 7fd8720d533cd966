"""Another sims script (or the command line) run with the bias-state filters' state of sight changed.

The replay builds its filters with their defaults; a study of an option the replay does not
expose runs a sims script in this process with the option set on every bias-state filter the
script builds:

* ``--sight-model grid``: each anchor's bias and state of sight kept jointly
  (:class:`~quadobs.estimators.robust.BiasSightGrid`) instead of the default chain (the
  filters' ``sight_model``, :mod:`quadobs.estimators.bias_states`);
* ``--onset-test``: the Markov onset test of the excess chains on (the filters'
  ``onset_test``: several clear chains turned blocked within one round of the anchors taken as
  a position error);
* ``--steady-test on|off``: the steady-offset test of the excess chains (the filters'
  ``steady_test``: a block of an anchor's ranges read blocked as steady as the noise taken as
  its bias's error) on or off in every bias filter under the mixture, the replay's
  ``ekf-bias-imu-nlos`` included (whose default is on; the replay's summary keeps
  ``noise.steady_test`` at the setup's value, and ``steady_offsets`` follows the filter);
* ``--line-of-sight P``: the one-sided gate's line-of-sight probability (its threshold
  ``z_+ = Phi^{-1}(P)``, :class:`~quadobs.estimators.robust.SkewedGate`; default 0.95) in
  every gate built without one of its own (:func:`line_of_sight`): the replay's
  ``ekf-bias``, ``ukf-bias``, ``ekf-bias-imu``, the robot's height filters, ``ekf-bias-imu-nlos``
  where no excess is identified, and the live bias filters of a radio that states no excess.

The script is a file of ``sims/``, or ``quadobs`` for the command line itself (its
arguments after it).

::

    python sims/bias_filter_options.py --sight-model grid stress_hidden_logs.py flight --seeds 0,1 --variants gap,moving
    python sims/bias_filter_options.py --onset-test stress_hidden_logs.py flight --seeds 0,1 --variants none,gap,moving
    python sims/bias_filter_options.py --sight-model grid replay_flight_variants.py --seeds 0,1 --duration 40 --variants real,bias
    python sims/bias_filter_options.py --steady-test off stress_hidden_logs.py flight --seeds 0,1 --variants gap,moving
    python sims/bias_filter_options.py --line-of-sight 0.99 quadobs replay DIR --burn-in 5
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import runpy
import sys
from pathlib import Path

from quadobs.errors import run_script
from quadobs.estimators import bias_states

SIMS = Path(__file__).resolve().parent


def _set_steady_test(on: bool) -> None:
    """The steady-offset test on or off in every bias filter built from here on: the class's
    default, and the replay's ``ekf-bias-imu-nlos``, which sets its own."""
    from quadobs.estimators.robust import ExcessMixture
    from quadobs.testbed.logs import imu_bias

    bias_states._VehicleBlock.steady_test = on
    build = imu_bias.build_ekf_bias_imu

    def built(*args, **kwargs):
        est = build(*args, **kwargs)
        est.steady_test = on and isinstance(est.robust, ExcessMixture)
        return est

    imu_bias.build_ekf_bias_imu = built


@contextlib.contextmanager
def line_of_sight(probability: float):
    """Inside, every one-sided gate built without a line-of-sight probability of its own
    (:class:`~quadobs.estimators.robust.SkewedGate`) takes ``probability``; restored after.

    The dataclass's generated ``__init__`` reads its defaults when called, so setting the one
    of ``line_of_sight`` reaches every builder, wherever it imported the class from."""
    from quadobs.estimators.robust import SkewedGate

    SkewedGate(line_of_sight=probability)  # refused in one line outside (0.5, 1)
    init = SkewedGate.__init__
    saved = init.__defaults__
    named = [f.name for f in dataclasses.fields(SkewedGate) if f.default is not dataclasses.MISSING]
    init.__defaults__ = tuple(
        probability if name == "line_of_sight" else value for name, value in zip(named, saved)
    )
    try:
        yield
    finally:
        init.__defaults__ = saved


def _run(name: str, rest: list[str], ap: argparse.ArgumentParser) -> None:
    """The sims script ``name`` with ``rest`` as its arguments, or the command line."""
    if name == "quadobs":
        from quadobs import cli

        sys.exit(cli.main(rest))
    script = SIMS / name
    if not script.is_file():
        ap.error(f"no script {name!r} in sims/")
    sys.argv = [str(script), *rest]
    runpy.run_path(str(script), run_name="__main__")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sight-model", choices=("chain", "grid"), default="chain")
    ap.add_argument("--onset-test", action="store_true", help="the Markov onset test on")
    ap.add_argument("--steady-test", choices=("on", "off"), help="default: as each filter is built")
    ap.add_argument(
        "--line-of-sight",
        type=float,
        help="the one-sided gate's line-of-sight probability (default 0.95)",
    )
    ap.add_argument("script", help="a script of sims/, or quadobs (the command line)")
    ap.add_argument("rest", nargs=argparse.REMAINDER, help="the script's own arguments")
    args = ap.parse_args()
    model = bias_states._sight_model(args.sight_model)
    bias_states._sight_model = lambda name: model  # every filter built from here on
    bias_states._VehicleBlock.onset_test = args.onset_test
    if args.steady_test is not None:
        _set_steady_test(args.steady_test == "on")
    gate = (
        contextlib.nullcontext()
        if args.line_of_sight is None
        else line_of_sight(args.line_of_sight)
    )
    with gate:
        _run(args.script, args.rest, ap)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
