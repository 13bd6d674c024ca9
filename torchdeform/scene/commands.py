"""Command-line code of scenes: ``torchdeform run SCENE.toml --out DIR`` and ``torchdeform demo``."""
from __future__ import annotations

from .mass_spring import demo_scene
from .run import load_scene, one_line_warnings, report, run_scene

__all__ = ["add_run_arguments", "add_demo_arguments", "run_command", "demo_command"]


def add_run_arguments(p) -> None:
    """Options of ``torchdeform run``."""
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the scene's, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_demo_arguments(p) -> None:
    """Options of ``torchdeform demo``."""
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    p.add_argument("--device", default=None, help="cpu or cuda")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run_command(args) -> int:
    """Run a scene file; prints one line (what ran, how fast, where the outputs are)."""
    with one_line_warnings():
        scene = load_scene(args.scene)
        summary = run_scene(scene, args.out, progress=not args.quiet, device=args.device)
    print(report(summary, args.out))
    return 0


def demo_command(args) -> int:
    """Run the built-in demo scene."""
    with one_line_warnings():
        summary = run_scene(demo_scene(), args.out, progress=not args.quiet, device=args.device)
    print(report(summary, args.out))
    return 0
