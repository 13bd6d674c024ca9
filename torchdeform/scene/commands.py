"""Command-line code of scenes: ``torchdeform run SCENE.toml --out DIR`` and ``torchdeform demo``."""

from __future__ import annotations

import re

from ..checks import usable_device
from ..errors import ConfigError
from ..sim.engine import ENGINES
from ..sim.threads import omp_threads, setup_threads
from .bodies import BodiesScene
from .demo import demo_scene
from .mass_spring import Scene
from .run import load_scene, report, run_scene

__all__ = [
    "add_run_arguments",
    "add_demo_arguments",
    "add_force_argument",
    "run_command",
    "demo_command",
    "scene_with_values",
]


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
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="set a scene key for this run (repeatable; a TOML value): --set integrator.steps=200 "
        "--set integrator.dt=1e-4 --set output.name=x",
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
    with omp_threads(setup_threads()):  # one thread beside a busy process (a label body's build: seconds)
        scene = scene_with_values(args.scene, getattr(args, "set", None) or [])
    if getattr(args, "animation", False):
        if not isinstance(scene, Scene):
            several = isinstance(scene, BodiesScene)
            raise ConfigError(
                "--animation",
                "a mass-spring scene of one body (several bodies are not animated yet)"
                if several
                else "a mass-spring scene (ChainMail scenes write no animation)",
                got="[[bodies]]" if several else "chainmail",
            )
        scene.animation = scene.animation or "animation.gif"
    if getattr(args, "engine", None):
        if not isinstance(scene, Scene):
            several = isinstance(scene, BodiesScene)
            raise ConfigError(
                "--engine",
                "a mass-spring scene of one body (several bodies step eagerly)"
                if several
                else "a mass-spring scene (ChainMail scenes have no engine)",
                got="[[bodies]]" if several else "chainmail",
            )
        scene.engine = args.engine
    summary = run_scene(scene, args.out, progress=not args.quiet, device=args.device, force=args.force)
    print(report(summary, args.out))
    return 0


def check_key(key: str) -> None:
    """Raise a :class:`ConfigError` unless ``key`` is ``section.key`` of a scene file (no array tables).

    ``torchdeform run --set`` and ``torchdeform sweep --set`` take these keys; a scene of several
    bodies also ``contact.friction`` and ``bodies.NAME.SECTION.KEY`` (the body of that name).

    Examples:
        >>> check_key("integrator.steps")
        >>> check_key("integrator.stepz")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: --set: expected SECTION.KEY of a scene file (...), got 'integrator.stepz'
    """
    from .bodies import GLOBAL, PER_BODY
    from .mass_spring import INTEGRATOR_OPTIONS
    from .reader import LISTS, SECTIONS

    if key.startswith("bodies."):  # a scene of several bodies: bodies.NAME.SECTION.KEY
        parts = key.split(".")
        sub = [s for s in PER_BODY if s not in LISTS]
        if len(parts) != 4 or parts[2] not in sub or parts[3] not in SECTIONS[parts[2]]:
            raise ConfigError("--set", f"bodies.NAME.SECTION.KEY (sections {', '.join(sub)})", got=key)
        return
    if key == "contact.friction" or (key.partition(".")[0] == "output" and key.partition(".")[2] in GLOBAL["output"]):
        return
    section, _, name = key.partition(".")
    known = SECTIONS.get(section, ())
    if section == "integrator":
        known = tuple(dict.fromkeys(known + tuple(k for opts in INTEGRATOR_OPTIONS.values() for k in opts)))
    if section in LISTS or name not in known or "." in name:
        sections = ", ".join(s for s in SECTIONS if s not in LISTS)
        raise ConfigError(
            "--set",
            f"SECTION.KEY of a scene file (sections {sections}; {section}: {', '.join(known) or 'no such section'})",
            got=key,
        )


def scene_with_values(path, sets: list):
    """The scene of file ``path`` with the ``--set KEY=VALUE`` texts of ``sets`` applied (built, so checked).

    A key that is not ``section.key`` of a scene file, or a value the key does not take, raises a
    :class:`ConfigError` naming ``--set KEY``; other problems name the file and line as usual.
    """
    if not sets:
        return load_scene(path)
    from pathlib import Path

    from .bodies import bodies_scene, check_bodies_sections, read_scene
    from .chainmail import chainmail_scene
    from .mass_spring import mass_spring_scene
    from .reader import check_sections, parse_set, with_values

    values = {}
    for text in sets:
        key, value = parse_set(text, several=False)
        check_key(key)
        if key in values:
            raise ConfigError("--set", "each key once", got=key)
        values[key] = value
    src, data = read_scene(path)
    data = with_values(data, values)
    several = "bodies" in data
    (check_bodies_sections if several else check_sections)(src, data)  # a set key may make a section required
    base, name = Path(path).parent, Path(path).stem
    build = bodies_scene if several else chainmail_scene if data.get("model") == "chainmail" else mass_spring_scene
    scene = build_with_values(src, data, base, name, values, build=build)
    scene.source = src  # later errors (a run's) name the file
    return scene


def build_with_values(src, data: dict, base, name: str, values: dict, *, build):
    """``build(Source(), data, base, name=name)`` of a file's ``data`` with ``values`` set in it.

    An error of a set key names ``--set KEY`` and its value; any other names the file ``src`` and
    the key's line there (the data no longer has the file's own lines).
    """
    from .reader import Source

    try:
        return build(Source(), data, base, name=name)
    except ConfigError as e:
        key = e.key
        entry = re.fullmatch(r"bodies\[(\d+)\]\.(.+)", key or "")
        if entry and isinstance(data.get("bodies"), list) and int(entry.group(1)) < len(data["bodies"]):
            key = f"bodies.{data['bodies'][int(entry.group(1))].get('name')}.{entry.group(2)}"  # as --set names it
        if key in values:
            raise ConfigError(f"--set {key}", e.expected, got=values[key]) from None
        raise ConfigError(
            e.key,
            e.expected,
            got=e.got if e.show_got else None,
            file=src.path,
            line=src.line_of(e.key),
            show_got=e.show_got,
        ) from None


def demo_command(args) -> int:
    """Run the built-in demo scene."""
    if args.device is not None:
        usable_device(args.device, key="--device")
    with omp_threads(setup_threads()):  # one thread beside a busy process (the phantom's liver: seconds)
        scene = demo_scene()
    summary = run_scene(scene, args.out, progress=not args.quiet, device=args.device, force=args.force)
    print(report(summary, args.out))
    return 0
