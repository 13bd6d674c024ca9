"""Exemplars: the 3-D RGB volumes solid textures are cut from.

An exemplar is a float tensor ``(3, E_d, E_h, E_w)`` with colours in ``[0, 1]`` (channel first,
like every node field of torchdeform). Chen & He used 128 Visible Human liver slices of
128 x 128 pixels (REFERENCE §7.1); :func:`load_exemplar` reads such a folder of PNG slices, or an
``.npy`` / ``.npz`` array, and :func:`liver_exemplar` generates a liver-like one on demand.

**The procedural liver** (seeded; no data files needed):

* lobules: a 3-D Voronoi diagram of jittered seeds about ``lobule`` voxels apart; each lobule
  is lighter at its central vein and darker towards its border (the portal tracts);
* vessels: a few tubes (random smooth paths) with a pale wall and a dark lumen;
* colour: a reddish-brown base modulated by low-frequency noise (the variation across a liver).

Examples:
    >>> ex = liver_exemplar(size=32, seed=1)
    >>> tuple(ex.shape), bool(ex.min() >= 0) and bool(ex.max() <= 1)
    ((3, 32, 32, 32), True)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import ConfigError

__all__ = ["load_exemplar", "liver_exemplar", "as_exemplar", "exemplar_from"]


def as_exemplar(array, *, key: str = "exemplar") -> torch.Tensor:
    """An RGB volume ``(D, H, W, 3)`` or ``(3, D, H, W)`` (uint8 0..255 or floats 0..1) as float32 ``(3, D, H, W)``.

    Examples:
        >>> as_exemplar(np.zeros((4, 5, 6, 3), dtype=np.uint8)).shape
        torch.Size([3, 4, 5, 6])
    """
    t = torch.as_tensor(np.asarray(array))
    if t.dim() != 4 or 3 not in (t.shape[0], t.shape[-1]):
        raise ConfigError(key, "an RGB volume: (D, H, W, 3) or (3, D, H, W)", got=tuple(t.shape))
    if t.shape[0] != 3 or (t.shape[-1] == 3 and t.shape[0] != 3):
        t = t.permute(3, 0, 1, 2)
    if t.dtype == torch.uint8:
        t = t.float() / 255.0
    elif t.is_floating_point():
        t = t.float()
        if not bool(torch.isfinite(t).all()) or float(t.min()) < 0 or float(t.max()) > 1:
            raise ConfigError(
                key,
                "colours in [0, 1] (floats) or 0..255 (uint8)",
                got=f"values in [{float(t.min()):g}, {float(t.max()):g}]",
                show_got=True,
            )
    else:
        raise ConfigError(key, "uint8 or floating-point colours", got=str(t.dtype))
    if min(t.shape[1:]) < 2:
        raise ConfigError(key, "at least 2 voxels along every axis", got=tuple(t.shape[1:]))
    return t.contiguous()


def load_exemplar(path) -> torch.Tensor:
    """Read an exemplar: ``.npy``, ``.npz`` (its first array, or ``exemplar``) or a folder of 2-D slice images.

    Slices are read in file-name order (PNG/JPEG via matplotlib's image reader) and stacked
    along D; all must have the same size and be RGB (an alpha channel is dropped).

    Args:
        path: the file or folder.

    Returns:
        ``(3, D, H, W)`` float32 in ``[0, 1]``.
    """
    p = Path(path)
    if not p.exists():
        raise ConfigError("exemplar", "an existing .npy, .npz or folder of slice images", got=str(p))
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in (".png", ".jpg", ".jpeg"))
        if not files:
            raise ConfigError("exemplar", "a folder holding slice images (.png, .jpg)", got=str(p))
        import matplotlib.image as mpimg

        slices, size = [], None
        for f in files:
            img = np.asarray(mpimg.imread(f))
            if img.ndim != 3 or img.shape[2] not in (3, 4):
                raise ConfigError(f"exemplar: {f.name}", "an RGB slice image", got=f"shape {img.shape}", show_got=True)
            if size is not None and img.shape[:2] != size:
                raise ConfigError(
                    f"exemplar: {f.name}",
                    f"a slice of {size[0]} x {size[1]} pixels like the first",
                    got=f"{img.shape[0]} x {img.shape[1]}",
                    show_got=True,
                )
            size = img.shape[:2]
            img = img[..., :3]
            slices.append(img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32))
        return as_exemplar(np.stack(slices), key=f"exemplar: {p}")
    if p.suffix == ".npy":
        return as_exemplar(np.load(p), key=f"exemplar: {p}")
    if p.suffix == ".npz":
        with np.load(p) as data:
            name = "exemplar" if "exemplar" in data.files else data.files[0]
            return as_exemplar(data[name], key=f"exemplar: {p}")
    raise ConfigError("exemplar", "a .npy, .npz or folder of slice images", got=str(p))


def _smooth_noise(shape, scale: float, gen: torch.Generator) -> torch.Tensor:
    """Noise ``(D, H, W)`` with features about ``scale`` voxels wide, values about in [-1, 1]."""
    coarse = [max(2, math.ceil(n / scale) + 1) for n in shape]
    c = torch.randn(1, 1, *coarse, generator=gen)
    return F.interpolate(c, size=tuple(shape), mode="trilinear", align_corners=True)[0, 0]


def liver_exemplar(*, size: int = 128, seed: int = 0, lobule: float = 12.0, vessels: int = 4) -> torch.Tensor:
    """A liver-like RGB exemplar ``(3, size, size, size)`` in ``[0, 1]`` (see the module docstring).

    Args:
        size: voxels per axis (>= 8).
        seed: random seed (same seed, same exemplar).
        lobule: lobule diameter (voxels).
        vessels: number of vessels.
    """
    if int(size) < 8:
        raise ConfigError("exemplar.size", "at least 8 voxels", got=size)
    n = int(size)
    gen = torch.Generator().manual_seed(int(seed))
    axes = torch.arange(n, dtype=torch.float32)
    P = torch.stack(torch.meshgrid(axes, axes, axes, indexing="ij"))  # (3, n, n, n)
    # lobules: distances to the nearest two jittered seeds (Voronoi; one seed per cell of a k^3
    # lattice, so the nearest seeds lie in the 27 cells around a voxel's own); border where they tie
    k = max(2, round(n / lobule))
    size_c = n / k
    jitter = 0.35 * (torch.rand(3, k, k, k, generator=gen) * 2 - 1)
    seeds = (
        torch.stack(torch.meshgrid(*[torch.arange(k, dtype=torch.float32)] * 3, indexing="ij")) + 0.5 + jitter
    ) * size_c  # (3, k, k, k)
    cell = (P / size_c).floor().long().clamp_(0, k - 1)  # (3, n, n, n)
    dists = []
    for off in [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]:
        idx = [(cell[i] + off[i]).clamp(0, k - 1) for i in range(3)]
        q = seeds[:, idx[0], idx[1], idx[2]]  # (3, n, n, n)
        dists.append(((P - q) ** 2).sum(0))
    two = torch.stack(dists).topk(2, dim=0, largest=False).values.sqrt()  # (2, n, n, n)
    border = two[1] - two[0]  # 0 on lobule borders
    centre = two[0]
    lob = torch.clamp(border / (0.5 * lobule), 0, 1)  # 0 border .. 1 inside
    vein = torch.exp(-((centre / (0.12 * lobule)) ** 2))  # central vein
    # vessels: tubes along smooth random paths
    tube = torch.zeros(n, n, n)
    lumen = torch.zeros(n, n, n)
    for _ in range(int(vessels)):
        a, b = torch.rand(3, generator=gen) * n, torch.rand(3, generator=gen) * n
        bend = (torch.rand(3, generator=gen) - 0.5) * n * 0.5
        r = n * (0.03 + 0.04 * float(torch.rand(1, generator=gen)))
        ts = torch.linspace(0, 1, 24)
        path = a[:, None] * (1 - ts) + b[:, None] * ts + bend[:, None] * torch.sin(math.pi * ts)  # (3, 24)
        dist = torch.cdist(P.reshape(3, -1).T, path.T).min(1).values.view(n, n, n)
        tube = torch.maximum(tube, torch.clamp(1.2 - dist / r, 0, 1))
        lumen = torch.maximum(lumen, torch.clamp(1 - dist / (0.6 * r), 0, 1))
    var = _smooth_noise((n, n, n), n / 3, gen)
    fine = _smooth_noise((n, n, n), 2.0, gen)
    base = torch.tensor([0.55, 0.20, 0.15]).view(3, 1, 1, 1)
    colour = (
        base * (0.75 + 0.25 * lob + 0.08 * var + 0.05 * fine) + torch.tensor([0.12, 0.05, 0.04]).view(3, 1, 1, 1) * vein
    )
    wall = torch.tensor([0.85, 0.70, 0.65]).view(3, 1, 1, 1)
    blood = torch.tensor([0.30, 0.03, 0.05]).view(3, 1, 1, 1)
    colour = colour * (1 - tube) + wall * tube
    colour = colour * (1 - lumen) + blood * lumen
    return colour.clamp(0, 1).contiguous()


def exemplar_from(spec: str, *, seed: int = 0) -> torch.Tensor:
    """``liver`` / ``liver:N`` (procedural) or a file or folder (:func:`~torchdeform.texture.load_exemplar`)."""
    if spec == "liver" or spec.startswith("liver:"):
        size = spec.partition(":")[2] or "128"
        if not size.isdigit():
            raise ConfigError("exemplar", "liver or liver:N with N voxels per side", got=spec)
        return liver_exemplar(size=int(size), seed=seed)
    return load_exemplar(spec)
