"""The built-in demo: :func:`demo_scene` reads the scene file shipped with the package (``demo.toml``)."""

from __future__ import annotations

from .mass_spring import Scene
from .run import load_scene

__all__ = ["demo_scene"]


def demo_scene() -> Scene:
    """The built-in demo: the phantom's liver pressed by a probe over its tumour (``scenes/demo.toml``).

    The scene file ships with the package (``torchdeform/scene/demo.toml``, the same text as
    ``scenes/demo.toml``): a body of labels made from the procedural abdominal phantom
    (:func:`~torchdeform.anatomy.abdominal_phantom`) at 6 mm, liver, a tumour about 11 times
    stiffer, a vessel, the bone fixed; a sphere probe of 12 mm radius pressed 12 mm into the
    liver's front over the tumour in 0.25 s, held, released; symplectic Euler at 0.9 of the
    stability bound for 0.55 s. ``run_scene`` writes ``demo.gif``: the liver's smooth, textured
    surface with the probe beside the deformed CT. Its smooth surfaces need scikit-image (the
    ``anatomy`` extra).

    Examples:
        >>> import torchdeform as td
        >>> scene = td.demo_scene()
        >>> scene.integrator.name, scene.steps, scene.tools.names, scene.animation
        ('symplectic', 1400, ['probe'], 'demo.gif')
        >>> sorted(scene.embedded), scene.volume["file"].shape, scene.volume["tf"]  # the CT on the lattice's box
        (['label1'], (157, 133, 157), 'ct-liver')
    """
    from importlib.resources import as_file, files

    with as_file(files("torchdeform.scene") / "demo.toml") as path:
        scene = load_scene(path)
    assert isinstance(scene, Scene)
    scene.animation = "demo.gif"
    return scene
