"""The ``torchdeform`` command.

    torchdeform --version
    torchdeform run SCENE.toml --out DIR [--set KEY=VALUE ...]   run a scene file (torchrun ... -m torchdeform run: split over ranks)
    torchdeform demo --out DIR               run the built-in demo scene
    torchdeform bench speed [--quick] [--json]
    torchdeform fuzzy show FILE.fis                      variables, terms, rules
    torchdeform fuzzy eval FILE.fis NAME=VALUE ... [--json] | --inputs FILE.csv
    torchdeform fuzzy plot FILE.fis --out DIR
    torchdeform fuzzy vocabulary [--out DIR]             membership kinds, hedges, norms against MATLAB, Octave, ...
    torchdeform data cube --out FILE.npz [--springs 70 | --n 4 --load sine] [--noise 0.01]
    torchdeform data balloon --out FILE.npz              synthetic series for torchdeform.learn
    torchdeform data phantom --labels DIR [--voxel 0.001] [--seed 0] [--no-dicom]   abdominal phantom: labels, CT
    torchdeform warp VOLUME.npy OFFSETS.npy --out OUT.npy [--mode deform|carve|knoche] [--inverse-iters N]
    torchdeform render VOLUME --out IMAGE.png [--offsets FILE] [--mode mip|dvr|average] [--tf PRESET]
    torchdeform view SCENE.toml [--host 127.0.0.1] [--port 0] [--token T] [--open]
    torchdeform sweep SCENE.toml --set KEY=V1,V2 [--set ...] --out DIR   (torchrun ... -m torchdeform sweep ...)

Errors that a user can cause print one line (``torchdeform: <file>: <key>: expected ...``) and
exit with status 2, without a traceback; the whole contract is in :mod:`torchdeform.options`.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import os
import sys
from typing import NoReturn

from .options import Parser, guarded

__all__ = ["build_parser", "main", "entry", "EXAMPLES"]

_SCENES = "scene files: docs/scenes.md (every section and key), examples in scenes/"

#: the example at the end of a command's ``--help``
EXAMPLES = {
    "run": "example:\n  torchdeform run scenes/cube.toml --out out/cube --set integrator.steps=200\n\n" + _SCENES,
    "demo": "example:\n  torchdeform demo --out demo-out\n\nthe demo is a scene too; " + _SCENES,
    "view": "example:\n  torchdeform view scenes/cube.toml --open\n\n" + _SCENES,
    "sweep": "example:\n  torchdeform sweep scenes/cube.toml --set material.stiffness=10,20,40 --out out/sweep\n\n"
    + _SCENES,
}


def build_parser() -> argparse.ArgumentParser:
    """The ``torchdeform`` parser: each capability's ``commands`` module adds its sub-commands.

    Every ``commands`` module is light (torch and the engine only): heavy dependencies are
    imported when a command runs.
    """
    from .anatomy import commands as anatomy
    from .bench import commands as bench
    from .distributed import commands as distributed
    from .fuzzy import commands as fuzzy
    from .learn import commands as learn
    from .scene import commands as scene
    from .texture import commands as texture
    from .view import commands as view
    from .volume import commands as volume

    def data_arguments(parser) -> None:  # data cube|balloon (learn), data phantom (anatomy)
        anatomy.add_phantom_arguments(learn.add_arguments(parser))

    def data_command(args) -> int:
        return anatomy.phantom_command(args) if args.data_command == "phantom" else learn.command(args)

    from . import __version__

    p = Parser(prog="torchdeform", description="Soft-tissue simulation on PyTorch.")
    p.add_argument("--version", action="version", version=f"torchdeform {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    # name, help line, adds the arguments, runs the command
    commands = [
        (
            "run",
            "run a scene file (TOML); under torchrun, its body split over the ranks",
            scene.add_run_arguments,
            distributed.run_command,
        ),
        (
            "demo",
            "run the built-in demo: the phantom's liver pressed by a probe over its tumour",
            scene.add_demo_arguments,
            scene.demo_command,
        ),
        ("bench", "benchmarks", bench.add_arguments, bench.main),
        ("fuzzy", "Mamdani rule files: show, evaluate, plot", fuzzy.add_arguments, fuzzy.main),
        (
            "data",
            "synthetic data: data cube|balloon|phantom --out ...",
            data_arguments,
            data_command,
        ),
        (
            "warp",
            "warp a volume by node offsets (3, n_d, n_h, n_w) in voxels",
            volume.add_warp_arguments,
            volume.warp_command,
        ),
        (
            "render",
            "render a volume (MIP, DVR, average), optionally deformed by node offsets",
            volume.add_render_arguments,
            volume.render_command,
        ),
        (
            "texture",
            "colour a closed mesh with a solid texture (.ply, .glb, .obj)",
            texture.add_arguments,
            texture.command,
        ),
        (
            "view",
            "watch and touch a scene in the browser (local server, token in the URL)",
            view.add_arguments,
            view.command,
        ),
        (
            "sweep",
            "sweep scene keys over values (--set KEY=V1,V2): one row per point; spread over ranks under torchrun",
            distributed.add_arguments,
            distributed.command,
        ),
    ]
    for name, help_, add_arguments, func in commands:
        c = sub.add_parser(
            name,
            help=help_,
            description=help_[:1].upper() + help_[1:] + ".",
            epilog=EXAMPLES.get(name),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        add_arguments(c)
        c.set_defaults(func=func)
    return p


def main(*, argv=None) -> int:
    """Run the ``torchdeform`` command; returns the exit status (:func:`torchdeform.options.guarded`).

    ``0`` done, ``2`` a user's mistake or an environment that cannot do it (one line on stderr),
    ``130`` interrupted, ``1`` a bug (a traceback and a line asking for a report).
    """
    args = build_parser().parse_args(argv)
    return guarded("torchdeform", args.func, args)


def entry() -> NoReturn:
    """The installed ``torchdeform`` script and ``python -m torchdeform``: :func:`main`, then exit.

    Every output is written and closed when :func:`main` returns, and the exit functions
    (logging, worker pools) run as usual; what is left out is the interpreter's teardown of
    torch's modules, which took 0.3-0.5 s of every command on a 2-core machine (``--version``,
    ``--help`` and a usage error included).
    """
    try:
        status = main()
    except SystemExit as e:  # argparse's --help, --version and usage errors: the same quick exit
        if isinstance(e.code, int | None):
            status = e.code or 0
        else:  # a message, as sys.exit("...") gives
            print(e.code, file=sys.stderr)
            status = 1
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe (``| head``) or stream
            stream.flush()
    atexit._run_exitfuncs()
    os._exit(status)


if __name__ == "__main__":
    entry()
