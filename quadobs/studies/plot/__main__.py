"""``python -m quadobs.studies.plot FOLDER [NAME ...]``: regenerate the documentation's figures (:mod:`.builtins`)."""

import argparse
import sys

from quadobs.errors import QuadobsError
from quadobs.studies.plot.builtins import make_figures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m quadobs.studies.plot", description=__doc__)
    parser.add_argument("folder", help="where the figures go (docs/figures)")
    parser.add_argument(
        "names", nargs="*", help="only these: built-in scenario names, le2013, campaign"
    )
    args = parser.parse_args(argv)
    try:
        for path in make_figures(
            args.folder, only=args.names or None, log=lambda m: print(m, file=sys.stderr)
        ):
            print(f"figure: {path}")
    except QuadobsError as exc:
        print(f"quadobs: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
