"""Command-line code of scenes: ``torchdeform run SCENE.toml --out DIR`` and ``torchdeform demo``."""

from __future__ import annotations

from ..checks import usable_device
from ..errors import ConfigError
from ..sim.engine import ENGINES
from .demo import demo_scene
from .mass_spring import Scene
from .run import load_scene, report, run_scene

__all__ = ["add_run_arguments", "add_demo_arguments", "add_force_argument", "run_command", "demo_command"]


def add_run_arguments(p) -> None:
    """Options of ``torchdeform run``."""
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the scene's, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--animation",
        action="store_true",
        help="also write animation.gif: the textured surface beside the deformed volume, time and forces "
        "(mass-spring scenes; as [output] animation = true)",
    )
    p.add_argument(
        "--engine",
        choices=ENGINES,
        default=None,
        help="auto: compiled steps when the run repays the compile (the default); eager; compiled "
        "(overrides [integrator] engine; the summary says which ran and why)",
    )
    add_force_argument(p)


def add_force_argument(p) -> None:
    """``--force``: write into an output folder that holds files of no earlier run."""
    p.add_argument(
        "--force",
        action="store_true",
        help="write into an --out folder that holds other files (they are left alone); a folder of an "
        "earlier run needs no --force: its outputs are replaced, and those not written again removed",
    )


def add_demo_arguments(p) -> None:
    """Options of ``torchdeform demo``."""
    p.add_argument(
        "--out",
        default="demo-out",
        help="output folder (default: demo-out); besides the run's outputs it gets demo.gif, the animation of the run",
    )
    p.add_argument("--device", default=None, help="cpu or cuda")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_force_argument(p)


def run_command(args) -> int:
    """Run a scene file; prints one line (what ran, how fast, where the outputs are)."""
    if args.device is not None:
        usable_device(args.device, key="--device")
    scene = load_scene(args.scene)
    if getattr(args, "animation", False):
        if not isinstance(scene, Scene):
            raise ConfigError(
                "--animation", "a mass-spring scene (ChainMail scenes write no animation)", got="chainmail"
            )
        scene.animation = scene.animation or "animation.gif"
    if getattr(args, "engine", None):
        if not isinstance(scene, Scene):
            raise ConfigError("--engine", "a mass-spring scene (ChainMail scenes have no engine)", got="chainmail")
        scene.engine = args.engine
    summary = run_scene(scene, args.out, progress=not args.quiet, device=args.device, force=args.force)
    print(report(summary, args.out))
    return 0


def demo_command(args) -> int:
    """Run the built-in demo scene."""
    if args.device is not None:
        usable_device(args.device, key="--device")
    summary = run_scene(demo_scene(), args.out, progress=not args.quiet, device=args.device, force=args.force)
    print(report(summary, args.out))
    return 0
