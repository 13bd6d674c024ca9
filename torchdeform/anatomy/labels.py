r"""Label volumes to bodies: a lattice in the image's patient frame, a tissue per label.

A segmentation (an integer label per voxel, with its affine) becomes a lattice body:

1. **The lattice.** Its axes (D, H, W) are LPS (x, y, z), its nodes ``spacing`` metres apart, and it
   covers the voxels of every label that is a tissue or fixed (cropped to the nodes in use).
2. **Node labels** (nearest voxel): node ``n`` takes the label of the voxel that holds its rest
   position, ``round(A^-1 p_n)`` for the image affine ``A`` (background outside the image).
3. **Cells and their fill.** Each cell (the box between 8 nodes) is sampled at ``s^3`` points
   (``s`` even, about one per voxel, :func:`samples_per_cell`); its *fill* ``f_c`` is the fraction of
   samples that fall in a tissue or fixed label. A cell is part of the body when ``f_c > 0``, when it
   holds the centre of a tissue voxel, or when it holds a point the caller needs covered (the
   vertices of an embedded surface); the body's nodes are the corners of those cells, so every such
   point has all 8 corners of its cell in the body.
4. **Material per cell.** From the samples in tissue: Young's modulus the *harmonic* mean (springs in
   series: a cell half liver, half tumour is the two halves in series), Poisson ratio and density
   the mean. A cell's modulus and mass are scaled by ``max(f_c, min_fraction)``, so a cell half full
   of tissue carries half a cell's stiffness and mass (both by the same factor: the explicit time
   step of the full tissue still holds). Cells of the body without a tissue sample take the
   material of the nearest cell that has one.
5. **Node fraction** (the partial-volume fraction): the share of the node's own box (side
   ``spacing``, centred on the node) in tissue, from the same samples (each cell's octant nearest the
   node).
6. **Fixed labels** (bone): the nodes whose label is fixed do not move. Their cells have a material
   too (the springs to the tissue around them): the given one, else the stiffest tissue's.

The result is a :class:`LabelBody`; :meth:`LabelBody.model` makes the
:class:`~torchdeform.sim.model.Model` (an :class:`~torchdeform.sim.material.Elastic` material per
cell, a lumped mass per node, the fixed nodes).

Example:
    >>> import numpy as np
    >>> from torchdeform.anatomy import Image, body_from_labels
    >>> lab = np.zeros((20, 20, 20), np.uint8); lab[4:16, 4:16, 4:16] = 1; lab[8:12, 8:12, 8:12] = 2
    >>> img = Image(lab, np.diag([0.001, 0.001, 0.001, 1.0]), "cube")      # 1 mm voxels
    >>> body = body_from_labels(img, 0.002, tissues={1: "liver", 2: {"youngs_modulus": 2e4, "poisson_ratio": 0.45}})
    >>> body.grid.shape, sorted(np.unique(body.labels[body.grid.nodes()].numpy()).tolist())
    ((7, 7, 7), [0, 1, 2])
    >>> round(float(body.fraction.sum()) * 0.002**3 * 1e9)          # mm^3 of tissue: 12^3
    1728
    >>> model = body.model()

(Label 0 on body nodes: corners of the outer cells, which lie just outside the labelled voxels.)
"""

from __future__ import annotations

import math
from dataclasses import KW_ONLY, dataclass

import numpy as np
import torch

from ..checks import check_grid
from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.material import Elastic
from .frame import image_box, sample_nearest

__all__ = ["LabelBody", "Tissue", "body_from_labels", "samples_per_cell", "MIN_FRACTION"]

#: The least fill a cell's stiffness and mass are scaled by (a cell with one sample of tissue is not
#: left nearly massless beside full cells).
MIN_FRACTION = 0.2

_MATERIAL_KEYS = ("tissue", "youngs_modulus", "poisson_ratio", "density")


@dataclass(frozen=True)
class Tissue:
    """The material of one label: Young's modulus E (Pa), Poisson ratio nu, density rho (kg/m^3).

    :meth:`of` reads a tissue of the library (``"liver"``), a consistency word or number, or a dict
    with ``tissue`` and/or ``youngs_modulus``, ``poisson_ratio``, ``density`` (the explicit values win).
    """

    youngs_modulus: float
    poisson_ratio: float
    density: float
    _: KW_ONLY
    name: str = ""
    #: Kelvin-Voigt retardation time eta / E (s) of a library tissue, None for a given material
    retardation: float | None = None

    @classmethod
    def of(cls, value, *, key: str, default_density: float = 1000.0) -> Tissue:
        """The tissue of a scene or API value; ``key`` is named in errors, ``default_density`` (kg/m^3) fills a gap."""
        from ..fuzzy.presets import tissue_properties

        if isinstance(value, Tissue):
            return value
        spec = value if isinstance(value, dict) else {"tissue": value}
        unknown = sorted(set(spec) - set(_MATERIAL_KEYS))
        if unknown:
            raise ConfigError(key, "a tissue or the keys " + ", ".join(_MATERIAL_KEYS), got=unknown[0])
        props = {}
        if "tissue" in spec:
            props = tissue_properties([spec["tissue"]], key=f"{key}.tissue")[0]
        elif "youngs_modulus" not in spec:
            raise ConfigError(key, "a tissue (tissue = ...) or a material (youngs_modulus = ...)", got=value)
        E = float(spec.get("youngs_modulus", props.get("youngs_modulus", 0.0)))
        nu = float(spec.get("poisson_ratio", props.get("poisson_ratio", 0.45)))
        rho = spec.get("density", props.get("density"))
        rho = float(default_density if rho is None else rho)
        if not (math.isfinite(E) and E > 0):
            raise ConfigError(f"{key}.youngs_modulus", "a Young's modulus > 0 (Pa)", got=E)
        if not 1 / 6 <= nu < 0.5:
            raise ConfigError(f"{key}.poisson_ratio", "a Poisson ratio in [1/6, 1/2)", got=nu)
        if not (math.isfinite(rho) and rho > 0):
            raise ConfigError(f"{key}.density", "a density > 0 (kg/m^3)", got=rho)
        name = str(spec.get("tissue", "")) if "tissue" in spec else f"E={E:g} Pa"
        tau = props["viscosity"] / E if props and "youngs_modulus" not in spec else None
        return cls(E, nu, rho, name=name, retardation=tau)


@dataclass
class LabelBody:
    """A body made from a label volume (:func:`body_from_labels`).

    Attributes:
        grid: the lattice (LPS metres, ``node_mask`` = the body's nodes).
        labels: ``(D, H, W)`` int64, each node's label (the voxel holding its rest position; the
            background value outside the image).
        fraction: ``(D, H, W)`` float64, the share of each node's box in tissue (0..1).
        cell_fill: ``(D-1, H-1, W-1)`` float64, the share of each cell in tissue.
        youngs_modulus, poisson_ratio: ``(D-1, H-1, W-1)`` float64 per cell (E already scaled by the fill).
        retardation: ``(D-1, H-1, W-1)`` float64, the cells' Kelvin-Voigt time eta / E (s; 0 where
            no library tissue gives one).
        mass: ``(D, H, W)`` float64, kg per node.
        fixed: ``(D, H, W)`` bool, the nodes of fixed labels.
        tissues: ``{label: Tissue}`` of the labels in the body (fixed ones included).
        source: the image's file name.
    """

    grid: Grid
    labels: torch.Tensor
    fraction: torch.Tensor
    cell_fill: torch.Tensor
    youngs_modulus: torch.Tensor
    poisson_ratio: torch.Tensor
    retardation: torch.Tensor
    mass: torch.Tensor
    fixed: torch.Tensor
    tissues: dict
    source: str

    @property
    def material(self) -> Elastic:
        """The :class:`~torchdeform.sim.material.Elastic` material, per cell."""
        return Elastic(self.youngs_modulus, self.poisson_ratio)

    def model(self, *, dtype=torch.float32, device=None, **kw):
        """The :class:`~torchdeform.sim.model.Model` of the body; ``kw`` go to the model (damping, gravity, ...)."""
        from ..sim.model import Model

        fixed = kw.pop("fixed", None)
        fixed = self.fixed if fixed is None else (self.fixed | fixed)
        return Model(
            self.grid,
            self.material,
            mass=self.mass,
            fixed=fixed if bool(fixed.any()) else None,
            normalize=False,
            dtype=dtype,
            device=device,
            **kw,
        )

    def node_mask_of(self, label: int) -> torch.Tensor:
        """Bool ``(D, H, W)``: the body's nodes whose label is ``label``."""
        return (self.labels == int(label)) & self.grid.nodes()


def samples_per_cell(spacing: float, voxel: float) -> int:
    """``s`` (even, 2..8): about one sample per voxel along a cell edge of ``spacing`` metres."""
    return int(min(8, max(2, 2 * math.ceil(spacing / voxel / 2))))


def _integer_labels(arr: np.ndarray, key: str, source: str) -> np.ndarray:
    if arr.dtype.kind in "iub":
        return arr
    if arr.dtype.kind == "f" and np.array_equal(arr, np.round(arr)):
        return arr.astype(np.int64)
    raise ConfigError(key, "a label volume of integers", got=f"{source}: dtype {arr.dtype}")


def _tissue_table(present, tissues, fixed, background, key, source) -> tuple[dict, list]:
    """``{label: Tissue}`` of the labels in the body, checked against the labels present."""
    if not isinstance(tissues, dict):
        raise ConfigError(f"{key}.tissues", "a mapping label -> tissue or material", got=type(tissues).__name__)
    table = {}
    for label, value in tissues.items():
        table[int(label)] = Tissue.of(value, key=f"tissues[label={label}]")
    fixed = [int(f) for f in fixed]
    background = [int(b) for b in background]
    both = sorted(set(table) & set(background)) or sorted(set(fixed) & set(background))
    if both:
        raise ConfigError(f"tissues[label={both[0]}]", "a label that is a tissue or background, not both", got=both[0])
    missing = [int(v) for v in present if int(v) not in table and int(v) not in fixed and int(v) not in background]
    if missing:
        raise ConfigError(
            key,
            "a tissue, fixed or background entry for every label of the image",
            got=f"{source}: label {missing[0]} has none" + (f" (nor {missing[1:6]})" if len(missing) > 1 else ""),
        )
    if not table and not fixed:
        raise ConfigError(f"{key}.tissues", "at least one tissue label", got="none")
    stiffest = max(table.values(), key=lambda t: t.youngs_modulus) if table else None
    for f in fixed:
        if f not in table:
            if stiffest is None:
                raise ConfigError(f"{key}.tissues", "a tissue beside the fixed labels", got="fixed labels only")
            table[f] = stiffest
    return table, fixed


def body_from_labels(
    image,
    spacing: float,
    *,
    tissues: dict,
    fixed=(),
    background=(0,),
    topology: int = 26,
    cover=None,
    samples: int | None = None,
    min_fraction: float = MIN_FRACTION,
    key: str = "grid.labels",
) -> LabelBody:
    """A lattice body from a label volume: the node labels, fill and material per cell, mass and fixed nodes.

    Args:
        image: an :class:`~torchdeform.anatomy.images.Image` of integer labels (or a path,
            read with :func:`~torchdeform.anatomy.images.read_image`).
        spacing: the lattice spacing (metres; cubic cells, which the elastic material needs).
        tissues: ``{label: tissue}``: a tissue of the library (``"liver"``), a consistency, or a dict
            of ``tissue``, ``youngs_modulus`` (Pa), ``poisson_ratio``, ``density`` (kg/m^3).
        fixed: labels whose nodes do not move (bone). A fixed label without a tissue entry takes the
            stiffest tissue's material.
        background: labels left out (air, outside the patient).
        topology: 14, 18 or 26 neighbours.
        cover: optional ``(N, 3)`` LPS points (metres) whose cells the body must contain, e.g. the
            vertices of the surfaces to embed.
        samples: samples per cell edge (even; default :func:`samples_per_cell`).
        min_fraction: the least fill a cell's modulus and mass are scaled by.
        key: the scene key named in errors.

    Returns:
        a :class:`LabelBody`.

    Raises:
        ConfigError: a label with no entry, no tissue voxel, a lattice that would not fit in memory.
    """
    from .images import Image, read_image

    if not isinstance(image, Image):
        image = read_image(image, key=key)
    source = image.source
    h = float(spacing)
    if not (math.isfinite(h) and h > 0):
        raise ConfigError("grid.spacing", "one positive number (metres; cubic cells)", got=spacing)
    arr = _integer_labels(np.asarray(image.array), key, source)
    lo_v, hi_v = int(arr.min()), int(arr.max())
    small = hi_v - lo_v < 1 << 16  # a look-up table instead of sorting
    flat = arr.ravel().astype(np.int64) - lo_v if small else None
    present = np.flatnonzero(np.bincount(flat)) + lo_v if flat is not None else np.unique(arr)
    table, fixed_labels = _tissue_table(present, tissues, fixed, background, key, source)
    body_labels = np.array(sorted(table), dtype=present.dtype if present.dtype.kind != "b" else np.int64)

    # the lattice: the box of the body's voxels, one spare node layer each side, centred
    in_body = np.isin(arr, body_labels)
    if not in_body.any():
        raise ConfigError(key, "voxels of at least one tissue or fixed label", got=f"{source}: none of {list(table)}")
    used = [np.flatnonzero(in_body.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    idx_lo, idx_hi = [int(u.min()) for u in used], [int(u.max()) for u in used]
    lo, hi = image_box(image.affine, idx_lo, idx_hi)
    extent = hi - lo
    n = np.ceil(extent / h).astype(int) + 3
    origin = lo - ((n - 1) * h - extent) / 2
    shape = tuple(int(v) for v in n)
    try:
        check_grid(key, shape, topology=topology, itemsize=8)
    except ConfigError as e:
        size = " x ".join(str(v) for v in shape)
        raise ConfigError(key, e.expected, got=f"{source}: {size} nodes at {h:g} m") from None

    # compact label codes: 0..L-1 for the labels present, and per-code material tables
    if flat is not None:
        lut = np.zeros(hi_v - lo_v + 1, np.int32)
        lut[present - lo_v] = np.arange(len(present), dtype=np.int32)
        codes = torch.from_numpy(lut[flat])
    else:
        codes = torch.from_numpy(np.searchsorted(present, arr).astype(np.int32).reshape(-1))
    L = len(present)
    is_t = torch.zeros(L + 1, dtype=torch.float64)  # code L: outside the image
    inv_E = torch.zeros(L + 1, dtype=torch.float64)
    nu_t = torch.zeros(L + 1, dtype=torch.float64)
    rho_t = torch.zeros(L + 1, dtype=torch.float64)
    tau_t = torch.zeros(L + 1, dtype=torch.float64)
    for c, label in enumerate(present.tolist()):
        if int(label) in table:
            t = table[int(label)]
            is_t[c], inv_E[c], nu_t[c], rho_t[c] = 1.0, 1.0 / t.youngs_modulus, t.poisson_ratio, t.density
            tau_t[c] = t.retardation or 0.0
    voxel = float(np.linalg.norm(np.asarray(image.affine)[:3, :3], axis=0).min())
    s = samples if samples is not None else samples_per_cell(h, voxel)
    if s < 2 or s % 2:
        raise ConfigError("samples", "an even number >= 2 of samples per cell edge", got=s)

    cshape = tuple(v - 1 for v in shape)
    cnt = torch.zeros(cshape, dtype=torch.float64)
    sum_inv_E = torch.zeros(cshape, dtype=torch.float64)
    sum_nu = torch.zeros(cshape, dtype=torch.float64)
    sum_rho = torch.zeros(cshape, dtype=torch.float64)
    sum_tau = torch.zeros(cshape, dtype=torch.float64)
    octant = torch.zeros((2, 2, 2) + cshape, dtype=torch.float64)  # tissue samples per octant of each cell
    for a, b, c in np.ndindex(s, s, s):
        off = ((a + 0.5) / s, (b + 0.5) / s, (c + 0.5) / s)
        code = sample_nearest(
            codes, image.affine, arr.shape, origin=origin, spacing=(h,) * 3, shape=cshape, offset=off, outside=L
        )
        code = code.long()
        tis = is_t[code]
        cnt += tis
        sum_inv_E += inv_E[code]
        sum_nu += nu_t[code]
        sum_rho += rho_t[code]
        sum_tau += tau_t[code]
        octant[int(a >= s // 2), int(b >= s // 2), int(c >= s // 2)] += tis
    fill = cnt / s**3

    # the cells of the body: some tissue sampled, a tissue voxel's centre, or a point to cover
    alive = fill > 0
    A = np.asarray(image.affine, dtype=np.float64)
    from scipy.ndimage import binary_erosion

    centres = np.argwhere(in_body & np.logical_not(binary_erosion(in_body)))  # inner voxels' cells are sampled already
    _mark(alive, (centres @ A[:3, :3].T + A[:3, 3] - origin) / h)
    if cover is not None:
        pts = np.asarray(cover, dtype=np.float64).reshape(-1, 3)
        q = (pts - origin) / h
        outside = ((q < 0) | (q > np.asarray(cshape))).any(1)
        if outside.any():
            raise ConfigError(
                "cover",
                "points inside the labels' box (e.g. a surface of the same labels)",
                got=f"{int(outside.sum())} outside",
            )
        _mark(alive, q)
    nodes = torch.zeros(shape, dtype=torch.bool)
    for a, b, c in np.ndindex(2, 2, 2):
        nodes[a : a + cshape[0], b : b + cshape[1], c : c + cshape[2]] |= alive

    # crop to the nodes in use
    where = [torch.nonzero(nodes.any(dim=tuple(b for b in range(3) if b != a))).flatten() for a in range(3)]
    lo_i = [int(w.min()) for w in where]
    hi_i = [int(w.max()) + 1 for w in where]
    sl = tuple(slice(lo_i[a], hi_i[a]) for a in range(3))
    csl = tuple(slice(lo_i[a], hi_i[a] - 1) for a in range(3))
    nodes = nodes[sl].contiguous()
    origin = origin + np.asarray(lo_i) * h
    shape = tuple(nodes.shape)
    grid = Grid(shape, spacing=(h,) * 3, topology=topology, node_mask=nodes, origin=tuple(float(o) for o in origin))
    fill, cnt = fill[csl].contiguous(), cnt[csl]
    sum_inv_E, sum_nu, sum_rho, sum_tau = sum_inv_E[csl], sum_nu[csl], sum_rho[csl], sum_tau[csl]
    octant = octant[(slice(None),) * 3 + csl]

    # material per cell (cells without a tissue sample: the nearest cell's), scaled by the fill
    from ..sim.material import cell_mask

    cells = cell_mask(grid)
    has = cnt > 0
    E = torch.where(has, cnt / sum_inv_E.clamp_min(1e-300), torch.zeros_like(cnt))
    nu = torch.where(has, sum_nu / cnt.clamp_min(1), torch.zeros_like(cnt))
    rho = torch.where(has, sum_rho / cnt.clamp_min(1), torch.zeros_like(cnt))
    tau = torch.where(has, sum_tau / cnt.clamp_min(1), torch.zeros_like(cnt))
    if bool((cells & ~has).any()):
        if not bool(has.any()):
            raise ConfigError(key, "cells with tissue at this spacing", got=f"{source} at {h:g} m")
        from scipy.ndimage import distance_transform_edt

        near = torch.from_numpy(
            np.asarray(distance_transform_edt(~has.numpy(), return_distances=False, return_indices=True))
        )
        E, nu, rho, tau = (f[near[0], near[1], near[2]] for f in (E, nu, rho, tau))
    scale = fill.clamp_min(float(min_fraction)) * cells
    E = E * scale
    nu = torch.where(cells, nu, torch.full_like(nu, 0.45))
    E = torch.where(cells, E, torch.full_like(E, float(min(t.youngs_modulus for t in table.values()))))
    cell_mass = rho * scale * h**3
    mass = torch.zeros(shape, dtype=torch.float64)
    C = tuple(v - 1 for v in shape)
    for a, b, c in np.ndindex(2, 2, 2):
        mass[a : a + C[0], b : b + C[1], c : c + C[2]] += cell_mass / 8

    # node labels (nearest voxel), node fractions (each cell's octant nearest the node)
    vals = torch.from_numpy(np.asarray(arr).reshape(-1).astype(np.int64))
    bg = int(background[0]) if len(background) else 0
    labels = sample_nearest(vals, image.affine, arr.shape, origin=origin, spacing=(h,) * 3, shape=shape, outside=bg)
    per = (s // 2) ** 3
    frac = torch.zeros(shape, dtype=torch.float64)
    for a, b, c in np.ndindex(2, 2, 2):  # the octant (a, b, c) of a cell touches its corner node (a, b, c)
        frac[a : a + C[0], b : b + C[1], c : c + C[2]] += octant[a, b, c] / per
    frac = frac / 8
    fixed_mask = torch.isin(labels, torch.tensor(fixed_labels, dtype=torch.int64)) & nodes
    if not bool((nodes & ~fixed_mask).any()):
        raise ConfigError(key, "nodes of a tissue that moves (not every node fixed)", got=source)
    return LabelBody(
        grid=grid,
        labels=labels,
        fraction=frac,
        cell_fill=fill,
        youngs_modulus=E,
        poisson_ratio=nu,
        retardation=tau * cells,
        mass=mass,
        fixed=fixed_mask,
        tissues={k: v for k, v in table.items() if int(k) in present.tolist()},
        source=source,
    )


def _mark(alive: torch.Tensor, q: np.ndarray) -> None:
    """Set the cells holding the fractional node indices ``q`` ``(N, 3)`` in ``alive`` (in place)."""
    if not len(q):
        return
    shape = alive.shape
    c = np.floor(q).astype(np.int64)
    for a in range(3):
        c[:, a] = np.clip(c[:, a], 0, shape[a] - 1)
    flat = torch.from_numpy((c[:, 0] * shape[1] + c[:, 1]) * shape[2] + c[:, 2])
    alive.view(-1)[flat] = True
