"""The ``w2e`` command line: one command, one verb per step of the workflow.

Each verb parses its flags here and calls one function of the core (or of the ROS layer for
``bringup`` and ``demo``); heavy modules are imported only when their verb runs, so
``w2e --help`` is instant.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

Handler = Callable[[argparse.Namespace], int | None]


def _add_collect(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "collect", help="run random interactions in the simulator and write training shards",
        description="Collect interactions grouped by observation into resumable shards.")
    p.add_argument("--out", required=True, help="output directory (shards are appended)")
    p.add_argument("--categories", nargs="+", default=None,
                   help="categories (default: all 14)")
    p.add_argument("--split", default="train", choices=["train", "explore", "test"],
                   help="instance split to draw objects from")
    p.add_argument("--observations", type=int, default=20,
                   help="observations (instance, start state, camera) per category")
    p.add_argument("--interactions", type=int, default=24,
                   help="interactions per observation and primitive")
    p.add_argument("--primitives", nargs="+", default=["push", "pull"])
    p.add_argument("--num-points", type=int, default=2048, help="points per stored cloud")
    p.add_argument("--movable-fraction", type=float, default=0.8,
                   help="share of contact points drawn on movable parts (ground-truth mask)")
    p.add_argument("--workers", type=int, default=2, help="parallel worker processes")
    p.add_argument("--obs-per-shard", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_run_collect)


def _run_collect(a: argparse.Namespace) -> int:
    from w2e_ros.core.collect import CollectConfig, collect

    cfg = CollectConfig(
        out=a.out, categories=a.categories, split=a.split, observations=a.observations,
        interactions=a.interactions, primitives=tuple(a.primitives), num_points=a.num_points,
        movable_fraction=a.movable_fraction, workers=a.workers, obs_per_shard=a.obs_per_shard,
        seed=a.seed)
    summary = collect(cfg)
    print(summary.table())
    return 0


VERBS: list[Callable[[argparse._SubParsersAction], None]] = [_add_collect]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="w2e", description="Where2Explore: few-shot affordance learning (w2e_ros).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for add in VERBS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError) as exc:  # bad input: a clear message, no trace
        logging.getLogger("w2e").debug("details", exc_info=True)
        print(f"w2e {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
