"""Solid texture synthesis as an indirection texture (Chen & He's tiling, REFERENCE §7.1 and §7.3).

The texture space is cut into blocks of ``b`` voxels (Chen & He: ``b = 64``); block ``(i, j, k)``
is a copy of the exemplar starting at a random offset ``o_ijk`` (integers, each in
``[0, E - b]``, Chen & He's ``[0, 64]`` for a 128^3 exemplar). The colour at a point ``P``
(voxels of texture space) is

    C(P) = exemplar[o[floor(P / b)] + (P - b floor(P / b))]

looked up with ``grid_sample`` (trilinear, or nearest), so nothing is materialised: the table
``offsets`` ``(n_d, n_h, n_w, 3)`` is the whole texture. ``ceil(extent / b)`` blocks per axis
cover the body's bounding box. Trilinear samples near a block's far face read the exemplar one
voxel past the block (clamped at the exemplar's border): within a block the texture is the
exemplar's own continuous field.

**Seams.** :meth:`SolidTexture.blend` removes the block seams by Poisson blending (3-D, or Chen
& He's per slice; :mod:`torchdeform.texture.seams`): it materialises the texture over its extent
once (``3 D H W`` values: 150 MB in float32 for Chen & He's 256 x 256 x 192 voxels), and lookups
read the blended volume from then on (trilinear, clamped at its border).

Material coordinates (metres) map to texture voxels by ``(X - origin) / voxel``: a point of the
tissue keeps its colour however the body moves or is cut (:meth:`SolidTexture.at_material`).

**Devices.** The texture is built on the CPU; a lookup runs on the device of its points, where
the exemplar (or the blended volume), the block offsets and the origin are copied once and kept.

Examples:
    >>> import torch
    >>> from torchdeform.texture import liver_exemplar
    >>> tex = SolidTexture(liver_exemplar(size=32), block=16, extent=(40, 20, 20), seed=0)
    >>> tex.blocks                                        # ceil(40/16), ceil(20/16), ceil(20/16)
    (3, 2, 2)
    >>> tex.colour(torch.tensor([[1.0, 2.0, 3.0]])).shape
    torch.Size([1, 3])
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..errors import ConfigError
from ..volume.deform import to_grid_sample
from .exemplar import as_exemplar

__all__ = ["SolidTexture", "SEAM_METHODS"]

#: seam methods of :meth:`SolidTexture.blend` (and of a scene's ``[texture] seams``, ``torchdeform texture --seams``)
SEAM_METHODS = ("none", "3d", "slices")


class SolidTexture:
    """An indirection texture over a box of ``extent`` voxels (see the module docstring).

    Args:
        exemplar: ``(3, E_d, E_h, E_w)`` in ``[0, 1]`` (or anything :func:`~torchdeform.texture.as_exemplar` takes).
        block: block size ``b`` in voxels (at most the exemplar's smallest side).
        extent: ``(D, H, W)`` voxels to cover (the body's bounding box in texture voxels).
        seed: the random offsets' seed.
        voxel: texture voxel size (m) for material coordinates.
        origin: the material point (m) at texture voxel ``(0, 0, 0)``.

    Attributes:
        offsets: int64 ``(n_d, n_h, n_w, 3)``: each block's start in the exemplar.
        blocks: ``(n_d, n_h, n_w)`` = ``ceil(extent / b)``.
        volume: None, or after :meth:`blend` the blended texture ``(3, D, H, W)`` the lookups read.
    """

    def __init__(
        self,
        exemplar,
        *,
        block: int = 64,
        extent=(64, 64, 64),
        seed: int = 0,
        voxel: float = 1.0,
        origin=(0.0, 0.0, 0.0),
    ):
        self.exemplar = (
            exemplar
            if torch.is_tensor(exemplar)
            and exemplar.is_floating_point()
            and exemplar.dim() == 4
            and exemplar.shape[0] == 3
            else as_exemplar(exemplar)
        )
        size = tuple(self.exemplar.shape[1:])
        if not isinstance(block, int) or block < 2 or block > min(size):
            raise ConfigError(
                "texture.block",
                f"an integer block size from 2 to the exemplar's smallest side ({min(size)} voxels)",
                got=block,
            )
        ext = tuple(int(e) for e in extent)
        if len(ext) != 3 or min(ext) < 1:
            raise ConfigError("texture.extent", "three positive voxel counts (D, H, W)", got=extent)
        if not voxel > 0:
            raise ConfigError("texture.voxel", "a positive voxel size (m)", got=voxel)
        self.block, self.extent, self.voxel = block, ext, float(voxel)
        self.origin = torch.tensor([float(c) for c in origin], dtype=torch.float64)
        self.blocks = tuple(math.ceil(e / block) for e in ext)
        gen = torch.Generator().manual_seed(int(seed))
        high = torch.tensor([s - block + 1 for s in size])  # offsets in [0, E - b]
        self.offsets = (torch.rand(*self.blocks, 3, generator=gen) * high).long().clamp_(max=high - 1)
        self.volume: torch.Tensor | None = None

    def blend(
        self, *, method: str = "3d", region: str = "seams", margin: int = 4, iters: int = 2000, tol: float = 1e-6
    ) -> dict:
        """Blend the block seams; later lookups read the blended volume (see the module docstring).

        Args:
            method: ``"3d"`` (:func:`~torchdeform.texture.seams.poisson_blend_3d`), ``"slices"``
                (Chen & He's per-slice 2-D blend, slices normal to ``D``) or ``"none"``.
            region: ``"seams"`` (only a band about the faces changes) or ``"all"``, as in
                :func:`~torchdeform.texture.seams.poisson_blend_3d`.
            margin: the band's half-width in voxels (``region="seams"``).
            iters: maximum conjugate-gradient iterations.
            tol: CG's relative residual.

        Returns:
            a report: ``method``, ``seam_before`` and ``seam_after`` (the seam measure
            :func:`~torchdeform.texture.seams.seam_jump` against the exemplar's mean gradient),
            ``histogram_before`` and ``histogram_after`` (Wasserstein-1 distance of the colour
            histograms to the exemplar's, colour units), ``iterations``, ``seconds``. With
            ``"none"`` (or a single block) the texture is left as it is and ``seam_after`` equals
            ``seam_before``.

        Example:
            >>> from torchdeform.texture import liver_exemplar
            >>> tex = SolidTexture(liver_exemplar(size=32), block=16, extent=(32, 32, 32), seed=0)
            >>> r = tex.blend(method="3d")
            >>> r["seam_after"] < r["seam_before"] / 3, tex.volume.shape
            (True, torch.Size([3, 32, 32, 32]))
        """
        import time

        from .seams import histogram_distance, poisson_blend_3d, poisson_blend_slices, seam_jump

        if method not in SEAM_METHODS:
            raise ConfigError("texture.seams", " or ".join(f'"{m}"' for m in SEAM_METHODS), got=method)
        t0 = time.perf_counter()
        self._set_volume(None)
        v = self.materialise()
        multi = any(n > 1 for n in self.blocks)
        before = seam_jump(v, self.block, reference=self.exemplar) if multi else 0.0
        report = dict(
            method=method,
            seam_before=before,
            seam_after=before,
            iterations=0,
            histogram_before=histogram_distance(v, self.exemplar),
        )
        if method != "none" and multi:
            blend = poisson_blend_3d if method == "3d" else poisson_blend_slices
            v, report["iterations"], _ = blend(
                v, self.block, region=region, margin=margin, iters=iters, tol=tol, return_info=True
            )
            report["seam_after"] = seam_jump(v, self.block, reference=self.exemplar)
            self._set_volume(v.clamp(0, 1))
        report["histogram_after"] = histogram_distance(v, self.exemplar)
        report["seconds"] = time.perf_counter() - t0
        return report

    def _set_volume(self, volume) -> None:
        """Read ``volume`` (or, with None, the exemplar through the offsets) from now on."""
        self.volume = volume
        self.__dict__.pop("_by_dtype", None)
        self.__dict__.pop("_atlas_by_dtype", None)

    # ------------------------------------------------------------------ lookup
    def _source(self, dtype, device=None) -> torch.Tensor:
        """The volume lookups read, in ``dtype`` on ``device`` (default: its own; copied once).

        The exemplar, or the blended texture.
        """
        cache = self.__dict__.setdefault("_by_dtype", {})
        src = self.exemplar if self.volume is None else self.volume
        device = src.device if device is None else torch.device(device)
        key = (dtype, str(device))
        if key not in cache:
            cache[key] = src.to(dtype=dtype, device=device)
        return cache[key]

    def _on(self, name: str, device) -> torch.Tensor:
        """The tensor attribute ``name`` (``"offsets"`` or ``"origin"``) on ``device``, copied once per device."""
        cache = self.__dict__.setdefault("_by_device", {})
        key = (name, str(torch.device(device)))
        if key not in cache:
            cache[key] = getattr(self, name).to(device)
        return cache[key]

    def _slice_atlas(self, dtype, device=None) -> tuple[torch.Tensor, int]:
        """The ``d`` slices of :meth:`_source` ``(3, d, h, w)`` tiled side by side in one image.

        Tile ``s`` (row ``s // cols``, column ``s % cols``, ``cols = ceil(sqrt(d))``) holds slice
        ``s`` plus one replicated row and column, so a bilinear read never reaches a neighbour tile.
        Square tiling keeps the image's coordinates small (about ``sqrt(d) h``), hence the float32
        rounding of ``grid_sample``'s normalised coordinates near 1e-4 voxel. Returns the image
        ``(1, 3, rows (h + 1), cols (w + 1))`` and ``cols``; built once per dtype and device.
        """
        cache = self.__dict__.setdefault("_atlas_by_dtype", {})
        ex = self._source(dtype, device)
        key = (dtype, str(ex.device))
        if key not in cache:
            d, h, w = ex.shape[1:]
            cols = math.ceil(math.sqrt(d))
            rows = math.ceil(d / cols)
            padded = F.pad(ex, (0, 1, 0, 1), mode="replicate")  # (3, d, h + 1, w + 1)
            padded = torch.cat([padded, padded.new_zeros(3, rows * cols - d, h + 1, w + 1)], 1)
            image = padded.reshape(3, rows, cols, h + 1, w + 1).permute(0, 1, 3, 2, 4)
            cache[key] = (image.reshape(1, 3, rows * (h + 1), cols * (w + 1)).contiguous(), cols)
        return cache[key]

    def exemplar_points(self, points: torch.Tensor) -> torch.Tensor:
        """Exemplar voxel coordinates ``(N, 3)`` of texture points ``(N, 3)`` (voxels, float)."""
        b = self.block
        cell = torch.div(points, b, rounding_mode="floor")
        n = self.blocks
        idx = [cell[:, a].long().clamp_(0, n[a] - 1) for a in range(3)]
        flat = (idx[0] * n[1] + idx[1]) * n[2] + idx[2]
        start = self._on("offsets", points.device).view(-1, 3).index_select(0, flat).to(points.dtype)  # (N, 3)
        return start + (points - b * cell)

    def colour(self, points: torch.Tensor, *, mode: str = "trilinear") -> torch.Tensor:
        """Colours ``(N, 3)`` at texture points ``(N, 3)`` (voxels); ``mode`` ``"trilinear"`` or ``"nearest"``.

        Lookups read the exemplar at :meth:`exemplar_points` or, after :meth:`blend`, the blended
        volume at ``points``. ``"nearest"`` is one 3-D ``grid_sample`` (the voxel nearest to each
        point, exactly). ``"trilinear"`` interpolates (clamped at the volume's border) as a blend along ``D`` of
        two bilinear lookups in adjacent slices of :meth:`_slice_atlas`: on the CPU the 2-D kernel
        is vectorised where the 3-D one is not (about 2x), and the points are split into one batch
        element per thread (``grid_sample`` shares out batch elements, not points).
        """
        if mode not in ("trilinear", "nearest"):
            raise ConfigError("texture.mode", '"trilinear" or "nearest"', got=mode)
        q = self.exemplar_points(points) if self.volume is None else points
        if mode == "nearest":
            ex = self._source(points.dtype, points.device)
            grid = to_grid_sample(q.T.reshape(1, 3, -1, 1, 1), ex.shape[1:], align_corners=True)
            out = F.grid_sample(ex[None], grid, mode="nearest", padding_mode="border", align_corners=True)
            return out.reshape(3, -1).T
        return self._trilinear(q)

    def _trilinear(self, q: torch.Tensor) -> torch.Tensor:
        """Trilinear colours ``(N, 3)`` at voxel coordinates ``q`` ``(N, 3)`` of :meth:`_source` (see :meth:`colour`)."""
        image, cols = self._slice_atlas(q.dtype, q.device)
        d, h, w = self._source(q.dtype, q.device).shape[1:]
        lim = torch.tensor([d - 1, h - 1, w - 1], dtype=q.dtype, device=q.device)
        q = torch.minimum(q.clamp(min=0), lim)  # padding "border"
        d0 = q[:, 0].floor().clamp_(max=max(d - 2, 0))
        frac = q[:, 0] - d0
        slab = torch.stack([d0, (d0 + 1).clamp_(max=d - 1)])  # (2, N) slices
        tile_row = torch.div(slab, cols, rounding_mode="floor")
        y = tile_row * (h + 1) + q[:, 1]
        x = (slab - tile_row * cols) * (w + 1) + q[:, 2]
        size = image.shape[-2:]
        grid = torch.stack([x * (2 / (size[1] - 1)) - 1, y * (2 / (size[0] - 1)) - 1], -1)  # (2, N, 2)
        n = q.shape[0]
        parts = torch.get_num_threads() if q.device.type == "cpu" and n >= 8192 else 1
        per = -(-n // parts)
        grid = F.pad(grid, (0, 0, 0, per * parts - n)).reshape(2, parts, per, 2).transpose(0, 1)
        out = F.grid_sample(
            image.expand(parts, -1, -1, -1), grid, mode="bilinear", padding_mode="border", align_corners=True
        )  # (parts, 3, 2, per)
        out = out.permute(1, 2, 0, 3).reshape(3, 2, -1)[:, :, :n]
        return torch.lerp(out[:, 0], out[:, 1], frac).T

    def at_material(self, X: torch.Tensor, *, mode: str = "trilinear") -> torch.Tensor:
        """Colours ``(N, 3)`` at material (rest) coordinates ``X`` ``(N, 3)`` (m)."""
        Xv = (X.double() - self._on("origin", X.device)) / self.voxel
        return self.colour(Xv.to(self.exemplar.dtype if X.dtype != torch.float64 else torch.float64), mode=mode)

    def materialise(self, *, lo=(0, 0, 0), hi=None) -> torch.Tensor:
        """The texture at the voxels ``lo <= p < hi`` (default: the whole extent), ``(3, d, h, w)``.

        Integer voxels read the exemplar exactly (each block a plain copy of its exemplar block).
        """
        hi = self.extent if hi is None else tuple(hi)
        axes = [torch.arange(int(a), int(b), dtype=torch.float32) for a, b in zip(lo, hi)]
        P = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return self.colour(P, mode="nearest").T.reshape(3, *[len(a) for a in axes])
