"""Command-line code of the viewer: ``torchdeform view SCENE.toml``.

Loads the scene (one body: :class:`~torchdeform.view.session.ViewerSession`; several,
``[[bodies]]``: :class:`~torchdeform.view.bodies.BodiesSession`), serves the viewer on loopback (a random token in the URL) and prints one line:
the page's URL. Ctrl-C stops it (exit status 0). A bad scene file is a
:class:`~torchdeform.errors.ConfigError`: one line on stderr and exit status 2.
"""

from __future__ import annotations

import os

from ..errors import ConfigError
from ..options import integer

__all__ = ["add_arguments", "command", "default_threads"]


def default_threads() -> int:
    """Torch threads for the simulation: all cores but one, which the browser needs to draw (>= 1)."""
    return max(1, (os.cpu_count() or 1) - 1)


def add_arguments(p) -> None:
    """The arguments of ``torchdeform view`` on an :mod:`argparse` parser.

    Args:
        p: the sub-command's parser.
    """
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=integer(lo=0, hi=65535), default=0, help="port (default 0: a free one)")
    p.add_argument("--token", default=None, help="the URL's secret (default: a random one)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the scene's, else cpu)")
    p.add_argument("--open", action="store_true", help="open the page in a browser")
    p.add_argument(
        "--threads",
        type=integer(lo=1),
        default=None,
        help="CPU threads for the simulation (default: all cores but one, left to the browser)",
    )


def command(args) -> int:
    """``torchdeform view``: serve a scene in the browser until Ctrl-C; returns the exit status.

    Args:
        args: the parsed arguments (see :func:`add_arguments`).

    Returns:
        0 once stopped.
    """
    if not 0 <= args.port <= 65535:
        raise ConfigError("--port", "a port in [0, 65535] (0: a free one)", got=args.port)
    if args.token is not None and not (
        8 <= len(args.token) <= 256 and args.token.isprintable() and all(c.isalnum() or c in "-_.~" for c in args.token)
    ):
        raise ConfigError(
            "--token", "8 to 256 URL-safe characters (letters, digits, - _ . ~)", got=args.token, show_got=False
        )
    if args.threads is not None and args.threads < 1:
        raise ConfigError("--threads", "a thread count >= 1", got=args.threads)
    try:
        import websockets  # noqa: F401 - only to say what is missing
    except ImportError:
        raise ConfigError(
            "view", "the websockets library (pip install 'torchdeform[viewer]')", show_got=False
        ) from None
    import torch

    from ..scene.run import load_scene, one_line_warnings
    from .server import serve

    torch.set_num_threads(args.threads or default_threads())
    from ..scene.bodies import BodiesScene
    from .bodies import BodiesSession
    from .session import ViewerSession

    with one_line_warnings():
        scene = load_scene(args.scene, surfaces=True)  # a body of labels: its smooth surfaces
        if isinstance(scene, BodiesScene):  # several bodies: play, pause, reset and the scene's tools
            session = BodiesSession(scene, device=args.device)
        else:
            session = ViewerSession(scene, device=args.device)
    return serve(
        session,
        host=args.host,
        port=args.port,
        token=args.token,
        log=lambda url: print(url, flush=True),
        open_browser=args.open,
    )
