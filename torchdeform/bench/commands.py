"""``torchdeform bench <name>``: one sub-command per entry of :data:`~.registry.BENCHES`."""

from __future__ import annotations

from .registry import BENCHES, module

__all__ = ["add_arguments", "main"]


def add_arguments(parser) -> None:
    """Add one sub-command per benchmark to the ``bench`` parser."""
    sub = parser.add_subparsers(dest="bench", required=True, metavar="BENCH")
    for name, (help_, _) in BENCHES.items():
        p = sub.add_parser(name, help=help_, description=help_)
        bench = module(name)
        bench.add_arguments(p)
        p.set_defaults(bench_main=bench.run)


def main(args) -> int:
    """Run the benchmark chosen on the command line; returns the exit status."""
    return args.bench_main(args)
