"""Command-line code of scenes: ``torchdeform run SCENE.toml --out DIR`` and ``torchdeform demo``."""
from __future__ import annotations

from ..errors import ConfigError
from ..sim.engine import ENGINES
from .mass_spring import Scene, demo_scene
from .run import load_scene, one_line_warnings, report, run_scene

__all__ = ["add_run_arguments", "add_demo_arguments", "run_command", "demo_command"]


def add_run_arguments(p) -> None:
    """Options of ``torchdeform run``."""
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the scene's, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--animation", action="store_true",
                   help="also write animation.gif: the textured surface beside the deformed volume, time and forces "
                        "(mass-spring scenes; as [output] animation = true)")
    p.add_argument("--engine", choices=ENGINES, default=None,
                   help="auto: compiled steps when the run repays the compile (the default); eager; compiled "
                        "(overrides [integrator] engine; the summary says which ran and why)")


def add_demo_arguments(p) -> None:
    """Options of ``torchdeform demo``."""
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out); besides the run's "
                                                     "outputs it gets demo.gif, the animation of the run")
    p.add_argument("--device", default=None, help="cpu or cuda")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run_command(args) -> int:
    """Run a scene file; prints one line (what ran, how fast, where the outputs are)."""
    with one_line_warnings():
        scene = load_scene(args.scene)
        if getattr(args, "animation", False):
            if not isinstance(scene, Scene):
                raise ConfigError("--animation", "a mass-spring scene (ChainMail scenes write no animation)",
                                  "chainmail")
            scene.animation = scene.animation or "animation.gif"
        if getattr(args, "engine", None):
            if not isinstance(scene, Scene):
                raise ConfigError("--engine", "a mass-spring scene (ChainMail scenes have no engine)", "chainmail")
            scene.engine = args.engine
        summary = run_scene(scene, args.out, progress=not args.quiet, device=args.device)
    print(report(summary, args.out))
    return 0


def demo_command(args) -> int:
    """Run the built-in demo scene."""
    with one_line_warnings():
        summary = run_scene(demo_scene(), args.out, progress=not args.quiet, device=args.device)
    print(report(summary, args.out))
    return 0
