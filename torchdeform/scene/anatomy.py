"""``[grid] labels`` and ``[[tissues]]`` (a body made from a label volume); ``[[surfaces]]`` (meshes embedded in it).

.. code-block:: text

    [grid]
    labels = "labels.nii.gz"       # NIfTI, NRRD, .npz, .npy (with label_spacing) or a DICOM folder
    spacing = 0.004                # the lattice's spacing (m; cubic cells)

    [[tissues]]
    label = 1
    tissue = "liver"               # or youngs_modulus (Pa), poisson_ratio, density (kg/m^3)

    [[tissues]]
    label = 3
    fixed = true                   # bone: its nodes do not move

Label 0 is background unless a ``[[tissues]]`` entry names it; ``background = true`` leaves out
another label. Every other label of the image needs an entry. ``[material]`` may then hold only
``damping`` (and ``damping_mode``); without it the springs get the Kelvin-Voigt damping of the
library tissues. The mass comes from the tissues' densities (no ``[mass]``), and ``[[regions]]`` do
not apply (the labels are the regions). See :mod:`torchdeform.anatomy.labels`.

``[[surfaces]]`` (any mass-spring body) embeds the user's own closed meshes in the lattice
(:class:`~torchdeform.mesh.embed.EmbeddedSurface`), written and animated like the label surfaces:

.. code-block:: text

    [[surfaces]]
    file = "liver.stl"             # .stl, .obj, .ply, ... (relative to the scene file); x, y, z -> D, H, W
    scale = 0.001                  # metres per mesh unit (1)
    name = "liver"                 # the surface's name in the files (the file's stem)

A body of labels or of a mesh (``[grid] mesh``) grows by the cells the surfaces pass through, so
that it covers them; a box body (``[grid] shape``) covers what lies in its box.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..sim.grid import Grid
from .reader import SECTIONS, Source, Table, is_number

__all__ = ["label_body_section", "lattice_ct", "CT_SIDE", "surfaces_section", "cover_surfaces", "check_surfaces"]

_GRID_ONLY = ("shape", "mesh", "origin", "padding", "scale")


def _tissue_tables(src: Source, items) -> tuple[dict, list, list]:
    """``({label: Tissue}, fixed labels, background labels)`` of the ``[[tissues]]`` tables."""
    from ..anatomy.labels import Tissue

    if not isinstance(items, list) or not items:
        raise src.error("tissues", "[[tissues]] tables (label = .., tissue = ..) for a body of labels")
    tissues, fixed, background, seen = {}, [], [], {}
    for n, item in enumerate(items):
        t = Table(src, f"tissues[{n}]", item, SECTIONS["tissues"])
        label = t.integer("label", "an integer label of the image", lo=-(2**31))
        if label in seen:
            raise t.fail("label", f"a label not given before (tissues[{seen[label]}] has it)", got=label)
        seen[label] = n
        flags = {k: t.flag(k, default=False) for k in ("fixed", "background")}
        material = {k: t.data[k] for k in ("tissue", "youngs_modulus", "poisson_ratio", "density") if t.has(k)}
        if flags["background"]:
            if material or flags["fixed"]:
                raise t.fail("background", "a background label alone (no tissue, material or fixed)", got=True)
            background.append(label)
            continue
        if flags["fixed"]:
            fixed.append(label)
        if not material:
            if flags["fixed"]:
                continue
            raise src.error(t.name, "tissue = .. or youngs_modulus = .. (or fixed = true, or background = true)")
        for k in ("youngs_modulus", "poisson_ratio", "density"):
            if k in material and not is_number(material[k]):
                raise t.fail(k, "a number", got=material[k])
        with src.located(t.key("tissue" if "tissue" in material else "youngs_modulus")):
            tissues[label] = Tissue.of(material, key=t.key("tissue" if "tissue" in material else "youngs_modulus"))
    if 0 not in seen:
        background.append(0)
    return tissues, fixed, background


def label_body_section(
    src: Source, data: dict, section: dict, base: Path, *, user: dict | None = None, surfaces: bool = False
):
    """``(grid, model keywords, embedded surfaces or None)`` of a scene whose ``[grid]`` has ``labels``.

    The surfaces (``{"label<k>": (vertices, faces)}``, :func:`~torchdeform.mesh.embed.label_surfaces`)
    are made only when the run shows or writes them (``[output] surfaces = "embedded"``,
    ``animation = true`` or a ``[camera]``), and the body then covers them; it also covers the ``user`` surfaces
    (:func:`surfaces_section`, ``{name: (vertices, faces, key, file)}``), which it does not return.
    """
    from ..anatomy.images import read_image
    from ..anatomy.labels import body_from_labels

    t = section["grid"]
    for k in _GRID_ONLY:
        t.only_with(k, "labels")
    for name in ("mass", "regions"):
        if name in data:
            raise src.error(
                name,
                f"no [{name}] with [grid] labels (the [[tissues]] give each label its material and density)",
            )
    spacing = t.num("spacing", "one positive number (metres; cubic cells)", lo=0, lo_open=True)
    topology = t.integer("topology", "14, 18 or 26", default=26)
    if topology not in (14, 18, 26):
        raise t.fail("topology", "14, 18 or 26 (an elastic body needs shear springs)", got=topology)
    voxel = None
    if t.has("label_spacing"):
        v = t.data["label_spacing"]
        ok = (is_number(v) and v > 0) or (
            isinstance(v, list) and len(v) == 3 and all(is_number(c) and c > 0 for c in v)
        )
        if not ok:
            raise t.fail("label_spacing", "the voxel size of a .npy label volume (metres: one or three numbers)", got=v)
        voxel = v
    tissues, fixed, background = _tissue_tables(src, data.get("tissues"))
    name = t.text("labels", 'a label volume file, a DICOM folder (relative to the scene file) or "phantom"')
    out = Table(src, "output", data.get("output", {}), SECTIONS["output"])
    wanted = (
        surfaces
        or out.data.get("surfaces") == "embedded"
        or out.data.get("animation") is True
        or isinstance(data.get("camera"), dict)  # the endoscope draws them
    )
    faces = out.integer("surface_faces", "an integer >= 100 (triangles per label surface)", default=10_000, lo=100)
    with src.located(t.key("labels")):
        image = _phantom(t, 0) if name.split(":")[0] == "phantom" else None
        if image is None:
            image = read_image(base / name, key=t.key("labels"), spacing=voxel)
    embedded, cover = None, None
    if wanted:  # smooth surfaces at image resolution; the body then covers them
        from ..mesh.embed import label_surfaces

        which = _surface_labels(t, sorted(tissues) + [f for f in fixed if f not in tissues])
        with src.located(t.key("labels")):
            found = label_surfaces(image.array, image.affine, which=which, smooth=10, faces=faces)
        embedded = {f"label{k}": v for k, v in found.items()}
        cover = np.concatenate([v for v, _ in found.values()]) if found else None
    if user:
        cover = np.concatenate(([] if cover is None else [cover]) + [u[0] for u in user.values()])
    try:
        with src.located(t.key("labels")):
            body = body_from_labels(
                image,
                spacing,
                tissues=tissues,
                fixed=fixed,
                background=background,
                topology=topology,
                cover=cover,
                key=t.key("labels"),
            )
    except ConfigError as e:
        if not user or e.key != t.key("labels") or "points inside the labels' box" not in e.expected:
            raise
        keys = [u[2] for u in user.values()]
        raise src.error(
            keys[0] if len(keys) == 1 else "surfaces",
            "meshes inside the box of the labels' lattice (their tissue voxels, one spacing around; "
            "a mesh in millimetres needs scale = 0.001)",
            got=f"{', '.join(u[3] for u in user.values())}: {e.got}",
        ) from None
    args: dict = {"stiffness": body.material, "normalize": False, "mass": body.mass}
    if bool(body.fixed.any()):
        args["fixed"] = body.fixed
    if "material" in data:
        m = Table(src, "material", data["material"], ("damping", "damping_mode"))
        if m.has("damping"):
            args["damping"] = m.per_class("damping", "N s/m")
        args["damping_mode"] = m.text(
            "damping_mode", '"projected" or "unprojected"', default="projected", choices=("projected", "unprojected")
        )
    if "damping" not in args and bool((body.retardation > 0).any()):
        from ..sim.material import kelvin_voigt_damping

        args["damping"] = kelvin_voigt_damping(body.grid, body.youngs_modulus, body.poisson_ratio, body.retardation)
    grid: Grid = body.grid
    return grid, args, embedded


@functools.lru_cache(maxsize=2)
def _phantom_images(voxel: float) -> tuple:
    """:func:`~torchdeform.anatomy.phantom.abdominal_phantom` at ``voxel``, made once per process.

    A scene of the phantom reads its labels (the body) and its CT (the volume): one phantom, not
    two (0.3 s each at 2 mm). The arrays are read-only, so no reader can change what the next one gets.
    """
    from ..anatomy.phantom import abdominal_phantom

    images = abdominal_phantom(voxel=voxel)
    for image in images:
        image.array.setflags(write=False)
    return images


def _phantom(t: Table, which: int):
    """The abdominal phantom of ``[grid] labels = "phantom[:VOXEL]"``: its labels (``which = 0``) or CT (1).

    :func:`~torchdeform.anatomy.phantom.abdominal_phantom` at that voxel size (m, default 1 mm),
    made once per voxel size (:func:`_phantom_images`).
    """
    name = t.data["labels"]
    voxel = 0.001
    if ":" in name:
        try:
            voxel = float(name.split(":", 1)[1])
        except ValueError:
            raise t.fail("labels", '"phantom" or "phantom:VOXEL" (the voxel size in metres)', got=name) from None
    return _phantom_images(voxel)[which]


def _surface_labels(t: Table, default: list) -> list:
    """``[grid] surface_labels``: the labels whose surfaces are embedded (default: every label of the body)."""
    if not t.has("surface_labels"):
        return default
    v = t.data["surface_labels"]
    if not (isinstance(v, list) and v and all(isinstance(k, int) and k in default for k in v)):
        raise t.fail("surface_labels", f"a list of labels of the body ({default})", got=v)
    return list(v)


#: the most voxels along a side of a CT resampled onto a lattice's box (the volume panel's cost)
CT_SIDE = 160


def lattice_ct(name: str, base: Path, t: Table, grid: Grid) -> np.ndarray:
    """``[volume] file`` of a body of labels: a CT in the labels' frame, resampled onto the lattice's box.

    ``name`` is a CT file or DICOM folder (relative to the scene file) or ``"phantom"`` (the
    abdominal phantom's CT, at the voxel size of ``[grid] labels = "phantom:VOXEL"``). The volume
    has the lattice's axes and fills its rest bounding box (what a scene's volume does), at the CT's
    finest voxel size or coarser, at most :data:`CT_SIDE` voxels a side.

    Returns:
        float32 ``(D', H', W')`` in the CT's units (HU), -1000 outside the image.
    """
    from ..anatomy.frame import resample_image
    from ..anatomy.images import read_image

    if name.split(":")[0] == "phantom":
        if t.data["labels"].split(":")[0] != "phantom":
            raise t.fail("labels", '"phantom" with [volume] file = "phantom" (its CT)', got=t.data["labels"])
        ct = _phantom(t, 1)
    else:
        ct = read_image(base / name, key="volume.file", dtype=np.float32)
    extent = np.asarray([(n - 1) * s for n, s in zip(grid.shape, grid.spacing)])
    step = max(float(ct.spacing.min()), float(extent.max()) / (CT_SIDE - 1))
    shape = tuple(int(v) for v in np.floor(extent / step).astype(int) + 1)
    step3 = tuple(float(e / (n - 1)) if n > 1 else step for e, n in zip(extent, shape))
    return resample_image(ct, origin=grid.origin, spacing=step3, shape=shape).numpy()


# ------------------------------------------------------------------ [[surfaces]]: the user's meshes
def surfaces_section(src: Source, items, base: Path) -> dict:
    """The meshes of the ``[[surfaces]]`` tables: ``{name: (vertices (V, 3) m, faces (F, 3), key, file)}``.

    Each table: ``file`` (a closed mesh trimesh reads, relative to the scene file ``base``; mesh
    x, y, z are D, H, W, as for ``[grid] mesh``), ``scale`` (metres per mesh unit, 1) and ``name``
    (the file's stem). ``key`` is the table's ``file`` key (``surfaces[0].file``) for later errors.

    Raises:
        ConfigError: naming the scene file, the line and the key: a missing, unreadable or open
            mesh (with the mesh file's path), a bad scale, two surfaces of one name.
    """
    from ..mesh.surfaces import load_mesh

    if not isinstance(items, list) or not items:
        raise src.error("surfaces", '[[surfaces]] tables (file = "organ.stl")', got=items)
    out: dict = {}
    for n, item in enumerate(items):
        t = Table(src, f"surfaces[{n}]", item, SECTIONS["surfaces"])
        name = t.text("file", "a closed mesh file (.stl, .obj, .ply, ...; relative to the scene file)")
        scale = t.num("scale", "a positive number (metres per mesh unit)", default=1.0, lo=0, lo_open=True)
        label = t.text("name", "a name for the surface", default=Path(name).stem)
        if label in out or (label.startswith("label") and label[5:].lstrip("-").isdigit()):
            taken = "another [[surfaces]] table's" if label in out else "a label surface's"
            raise t.fail("name", f"a name of its own (this one is {taken}; give name = ..)", got=label)
        with src.located(t.key("file")):
            vertices, faces = load_mesh(base / name, scale=scale, key="surface")
        out[label] = (vertices, faces, t.key("file"), name)
    return out


def cover_surfaces(grid: Grid, user: dict) -> Grid:
    """``grid`` with the corners of the cells that hold the ``user`` surfaces' vertices added to its nodes.

    A body with a node mask (a voxelised mesh) leaves out the cells its own surface passes through;
    an embedded surface needs them. Vertices outside the lattice's box add nothing (the check after
    names them). A grid without a mask is returned as it is.
    """
    if grid.node_mask is None or not user:
        return grid
    import torch

    shape = np.asarray(grid.shape)
    mask = grid.node_mask.cpu().numpy().copy()
    for vertices, *_ in user.values():
        q = (vertices - np.asarray(grid.origin)) / np.asarray(grid.spacing)
        base = np.clip(np.floor(q), 0, np.maximum(shape - 2, 0)).astype(np.int64)
        for a, b, c in np.ndindex(2, 2, 2):
            corner = np.minimum(base + (a, b, c), shape - 1)
            mask[tuple(corner.T)] = True
    if mask.sum() == grid.node_mask.sum():
        return grid
    return Grid(
        grid.shape,
        spacing=grid.spacing,
        origin=grid.origin,
        topology=grid.topology,
        node_mask=torch.from_numpy(mask),
    )


def check_surfaces(src: Source, grid: Grid, user: dict) -> dict:
    """The ``user`` surfaces as the scene keeps them, ``{name: (vertices, faces)}``, once each embeds in ``grid``.

    Raises:
        ConfigError: naming the scene file, the line, the table's ``file`` key and the mesh file: a
            mesh more than one spacing outside the lattice's box, or with vertices in cells the body
            does not fill.
    """
    import torch

    from ..mesh.embed import EmbeddedSurface

    lo = np.asarray(grid.origin)
    hi = lo + (np.asarray(grid.shape) - 1) * np.asarray(grid.spacing)
    box = "[" + ", ".join(f"{a:g}..{b:g}" for a, b in zip(lo, hi)) + "] m"
    out = {}
    for name, (vertices, faces, key, file) in user.items():
        try:
            EmbeddedSurface(vertices, faces, grid, dtype=torch.float64)
        except ConfigError as e:
            if "millimetres" in e.expected:
                expected = (
                    f"a mesh within one spacing of the body's lattice (its box is {box}; a mesh in "
                    "millimetres needs scale = 0.001)"
                )
            else:
                expected = "a mesh inside the body: " + e.expected
            raise src.error(key, expected, got=f"{file}: {e.got}") from None
        out[name] = (vertices, faces)
    return out
