"""The ``torchdeform`` command.

    torchdeform run SCENE.toml --out DIR     run a scene file
    torchdeform demo --out DIR               run the built-in demo scene
    torchdeform bench speed [--quick] [--json]
    torchdeform fuzzy show FILE.fis                      variables, terms, rules
    torchdeform fuzzy eval FILE.fis NAME=VALUE ... [--json] | --inputs FILE.csv
    torchdeform fuzzy plot FILE.fis --out DIR
    torchdeform data cube --out FILE.npz [--springs 70 | --n 4 --load sine] [--noise 0.01]
    torchdeform data balloon --out FILE.npz              synthetic series for torchdeform.learn
    torchdeform warp VOLUME.npy OFFSETS.npy --out OUT.npy [--mode deform|carve|knoche] [--inverse-iters N]
    torchdeform render VOLUME --out IMAGE.png [--offsets FILE] [--mode mip|dvr|average] [--tf PRESET]

Errors that a user can cause print one line (``torchdeform: <file>: <key>: expected ...``) and
exit with status 2, without a traceback.
"""
from __future__ import annotations

import argparse
import sys

from .errors import TorchdeformError


def _run(args) -> int:
    from .scene import load_scene, one_line_warnings, report, run_scene
    with one_line_warnings():
        scene = load_scene(args.scene)
        summary = run_scene(scene, args.out, progress=not args.quiet, device=args.device)
    print(report(summary, args.out))
    return 0


def _demo(args) -> int:
    from .scene import demo_scene, one_line_warnings, report, run_scene
    with one_line_warnings():
        summary = run_scene(demo_scene(), args.out, progress=not args.quiet, device=args.device)
    print(report(summary, args.out))
    return 0


def _bench(args) -> int:
    from . import bench
    return bench.main(args)


def _fuzzy(args) -> int:
    from .fuzzy import commands
    return commands.main(args)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchdeform", description="Soft-tissue simulation on PyTorch.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a scene file (TOML)")
    r.add_argument("scene", help="scene file (.toml)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--device", default=None, help="cpu or cuda (default: the scene's, else cpu)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_run)

    d = sub.add_parser("demo", help="run the built-in demo: a soft cube, fixed base, top centre dragged")
    d.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    d.add_argument("--device", default=None, help="cpu or cuda")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=_demo)

    b = sub.add_parser("bench", help="benchmarks")
    from . import bench                     # light: imports nothing heavy until a bench runs
    bench.add_arguments(b)
    b.set_defaults(func=_bench)

    f = sub.add_parser("fuzzy", help="Mamdani rule files: show, evaluate, plot")
    from .fuzzy import commands                 # light: torch and the engine only
    commands.add_arguments(f)
    f.set_defaults(func=_fuzzy)

    from . import data as _data                 # synthetic series for learning (torchdeform.data)
    s = sub.add_parser("data", help="generate synthetic time series (.npz): data cube|balloon --out FILE")
    _data.add_arguments(s)
    s.set_defaults(func=_data.command)

    from . import volume_io                     # light: numpy only until a command runs
    w = sub.add_parser("warp", help="warp a volume by node offsets (3, n_d, n_h, n_w) in voxels")
    volume_io.add_warp_arguments(w)
    w.set_defaults(func=volume_io.warp_command)
    v = sub.add_parser("render", help="render a volume (MIP, DVR, average), optionally deformed by node offsets")
    volume_io.add_render_arguments(v)
    v.set_defaults(func=volume_io.render_command)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except TorchdeformError as e:
        print(f"torchdeform: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("torchdeform: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
