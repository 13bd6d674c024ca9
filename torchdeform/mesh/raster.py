"""A small z-buffer rasteriser on torch: triangle meshes to shaded images, vectorised, CPU first.

For the surfaces of deformed bodies and the faces of cuts (:func:`~torchdeform.mesh.body_surface`,
:mod:`torchdeform.topology.surfaces`), in the demo and the browser viewer.

Pipeline
--------
1. **Project** every vertex with a :class:`Camera` to continuous pixel coordinates ``(x, y)``
   and a depth ``z`` (metres along the viewing direction, larger = farther).
2. **Cull** triangles whose screen area is zero and, for a perspective camera, triangles with a
   vertex at or behind the eye (``z <= 0``; they are dropped, not clipped).
3. **Cover**: each triangle's screen bounding box is expanded into (triangle, pixel) pairs, in
   chunks of triangles of at most ``chunk_pairs`` pairs (a loop over chunks, none over pixels).
   A pixel is covered when its centre lies inside or on the triangle: the three 2-D edge
   functions ``w_i`` (twice the signed areas of the sub-triangles opposite vertex ``i``) all have
   the sign of the triangle's area. Screen barycentrics are ``b_i = w_i / (w_0 + w_1 + w_2)``.
4. **Depth test** (z-buffer): the depth of the surface at the pixel centre is ``sum b_i z_i``
   (orthographic) or ``1 / sum(b_i / z_i)`` (perspective: ``1/z`` is linear on the screen).
   The nearest surface wins; exact ties go to the lower face index, so the result does not
   depend on chunking. Per chunk a deterministic ``scatter_reduce`` (``amin``) finds the winner.
5. **Shade** the winning face of each hit pixel once: perspective-correct barycentrics
   ``b'_i = (b_i / z_i) / sum_j (b_j / z_j)`` (the weights of the 3-D surface point; equal to
   ``b_i`` for the orthographic camera) interpolate the vertex colours, or the points where a
   colour callable (a solid texture) is evaluated; Lambert shading with the flat face normal
   ``n = normalise((v1 - v0) x (v2 - v0))`` (counter-clockwise = outward, as
   :func:`~torchdeform.mesh.marching_tetrahedra` and trimesh orient faces):
   ``shade = ambient + (1 - ambient) max(0, n . l)``, one-sided by default (a back face gets
   ``ambient``), ``|n . l|`` with ``two_sided=True`` (for open surfaces and cut faces seen from
   either side). ``image = colour * shade``; ``background`` where no triangle is hit.

Conventions
-----------
* World coordinates are those of the mesh (metres for the library's surfaces; mesh ``(x, y, z)``
  = grid axes ``(D, H, W)``, so the default ``up`` is ``(1, 0, 0)``, axis D up as in
  :class:`torchdeform.volume.OrbitCamera`).
* Camera frame: ``forward = normalise(target - eye)``, ``right = normalise(forward x up)``,
  ``up' = right x forward``.
* Images are ``(H, W, ...)`` with **row 0 at the top** (rows run downwards, against ``up'``) and
  column 0 at the left (columns run along ``right``), as PNG files and browsers show them.
* Pixel coordinates are continuous ``(x, y)`` = (column, row): pixel ``[i, j]`` covers
  ``j <= x < j + 1``, ``i <= y < i + 1`` and its **centre is** ``(j + 0.5, i + 0.5)``; coverage
  and interpolation are evaluated at pixel centres (one sample per pixel, no anti-aliasing).
* Perspective: ``fov_deg`` is the vertical field of view; focal length ``f = (H / 2) / tan(fov / 2)``
  pixels; ``x = W/2 + f X_c / Z_c``, ``y = H/2 - f Y_c / Z_c`` for camera coordinates
  ``(X_c, Y_c, Z_c)`` along ``(right, up', forward)``. Orthographic: ``ortho_height`` metres span
  the image height, ``x = W/2 + s X_c``, ``y = H/2 - s Y_c`` with ``s = H / ortho_height``.
  Pixels are square.
* dtype: float32 or float64, that of ``vertices``; CPU (any device where all inputs live).
  The image is differentiable with respect to colours, texture and the vertex positions of
  each pixel's face (through the barycentrics); visibility (which face) is not.

Example:
    >>> import torch
    >>> from torchdeform.mesh import Camera, rasterize
    >>> v = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    >>> f = torch.tensor([[0, 1, 2]])
    >>> cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=4.0, size=(8, 8))
    >>> out = rasterize(v, f, cam, ambient=0.2)
    >>> int((out["face"] == 0).sum()), round(float(out["image"][3, 4, 0]), 6), float(out["depth"][3, 4])
    (3, 1.0, 5.0)
"""

from __future__ import annotations

import bisect
import math

import torch

from ..errors import ConfigError

__all__ = ["Camera", "rasterize", "save_png"]


def _vec3(value, key: str) -> tuple:
    try:
        t = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        t = ()
    if len(t) != 3 or not all(math.isfinite(c) for c in t):
        raise ConfigError(key, "three finite numbers (x, y, z)", got=value)
    return t


class Camera:
    """An orthographic or perspective pinhole camera looking from ``eye`` at ``target``.

    Args:
        eye: camera position ``(3,)`` (metres, world coordinates).
        target: the point looked at ``(3,)``; it projects to the image centre.
        up: a direction ``(3,)`` that appears upwards in the image (need not be orthogonal to the
            viewing direction, must not be parallel to it). Default ``(1, 0, 0)``: axis D up.
        fov_deg: vertical field of view in degrees (0 < fov < 180): a perspective camera.
        ortho_height: height of the view in metres: an orthographic camera. Give exactly one of
            ``fov_deg`` and ``ortho_height``.
        size: image ``(H, W)`` in pixels.

    Attributes:
        perspective: bool.
        focal: pixels per unit of ``X_c / Z_c`` (perspective) or per metre (orthographic).
        size: ``(H, W)``.

    Raises:
        ConfigError: a bad vector, size, field of view or height; ``eye == target``; ``up``
            parallel to the viewing direction; both or neither of ``fov_deg`` and ``ortho_height``.

    Example:
        >>> cam = Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=90.0, size=(4, 6))
        >>> cam.perspective, round(cam.focal, 9)          # (H / 2) / tan(45 deg) pixels
        (True, 2.0)
    """

    def __init__(self, eye, target, *, up=(1.0, 0.0, 0.0), fov_deg=None, ortho_height=None, size=(256, 256)):
        self.eye, self.target, self.up = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
        try:
            s = tuple(int(v) for v in size)
        except (TypeError, ValueError):
            s = ()
        if len(s) != 2 or min(s) < 1:
            raise ConfigError("size", "an image size (H, W) of positive integers", got=size)
        self.size = s
        if (fov_deg is None) == (ortho_height is None):
            raise ConfigError(
                "camera",
                "exactly one of fov_deg (perspective) and ortho_height (orthographic)",
                got={"fov_deg": fov_deg, "ortho_height": ortho_height},
            )
        if fov_deg is not None:
            fov = float(fov_deg)
            if not 0.0 < fov < 180.0:
                raise ConfigError("fov_deg", "a vertical field of view in degrees, 0 < fov < 180", got=fov_deg)
            self.perspective, self.fov_deg, self.ortho_height = True, fov, None
            self.focal = (s[0] / 2) / math.tan(math.radians(fov) / 2)
        else:
            height = float(ortho_height)
            if not (math.isfinite(height) and height > 0):
                raise ConfigError("ortho_height", "a positive view height in metres", got=ortho_height)
            self.perspective, self.fov_deg, self.ortho_height = False, None, height
            self.focal = s[0] / height
        e, t, u = (torch.tensor(a, dtype=torch.float64) for a in (self.eye, self.target, self.up))
        fwd = t - e
        if float(fwd.norm()) == 0.0:
            raise ConfigError("target", "a point different from the eye", got=target)
        fwd = fwd / fwd.norm()
        right = torch.linalg.cross(fwd, u)
        if float(right.norm()) < 1e-9 * float(u.norm()) or float(u.norm()) == 0.0:
            raise ConfigError("up", "a direction not parallel to target - eye", got=up)
        right = right / right.norm()
        self._frame = torch.stack([right, torch.linalg.cross(right, fwd), fwd])  # rows: right, up', forward

    def __repr__(self) -> str:
        lens = f"fov_deg={self.fov_deg}" if self.perspective else f"ortho_height={self.ortho_height}"
        return f"Camera(eye={self.eye}, target={self.target}, up={self.up}, {lens}, size={self.size})"

    def frame(self, *, dtype=torch.float64, device=None) -> tuple:
        """The camera frame: ``eye (3,)`` and the rows ``right, up', forward`` as ``(3, 3)``.

        Example:
            >>> eye, R = Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=1.0).frame()
            >>> eye.tolist(), R[1].tolist(), R[2].tolist()                 # eye, up', forward
            ([0.0, 0.0, 2.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0])
        """
        return (torch.tensor(self.eye, dtype=dtype, device=device), self._frame.to(dtype=dtype, device=device))

    def project(self, points) -> tuple:
        """Pixel coordinates and depths of points.

        Args:
            points: ``(N, 3)`` world coordinates (metres), float32 or float64.

        Returns:
            ``(pixels (N, 2), depth (N,))`` in the dtype of ``points``: continuous pixel
            coordinates ``(x, y)`` = (column, row), pixel centres at ``+0.5`` (row 0 at the top);
            depth in metres along the viewing direction (``Z_c``; positive in front of the eye).
            A perspective camera gives ``inf``/``nan`` pixels for points at depth 0.

        Example:
            >>> cam = Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=90.0, size=(4, 6))
            >>> pix, z = cam.project(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]))
            >>> pix.tolist(), z.tolist()
            ([[3.0, 2.0], [4.0, 1.0]], [2.0, 2.0])
        """
        p = torch.as_tensor(points)
        if not p.is_floating_point():
            p = p.double()
        if p.ndim != 2 or p.shape[1] != 3:
            raise ConfigError("points", "an (N, 3) array of points", got=tuple(p.shape))
        eye, R = self.frame(dtype=p.dtype, device=p.device)
        c = (p - eye) @ R.T  # (N, 3) camera coordinates
        H, W = self.size
        xy = c[:, :2] / c[:, 2:3] * self.focal if self.perspective else c[:, :2] * self.focal
        pix = torch.stack([W / 2 + xy[:, 0], H / 2 - xy[:, 1]], dim=1)
        return pix, c[:, 2]


def _edges(s0, s1, s2, px, py):
    """The three 2-D edge functions at ``(px, py)``; ``s_k`` are ``(..., 2)`` screen vertices."""

    def edge(a, b):
        return (b[..., 0] - a[..., 0]) * (py - a[..., 1]) - (b[..., 1] - a[..., 1]) * (px - a[..., 0])

    return edge(s1, s2), edge(s2, s0), edge(s0, s1)


def _check_mesh(vertices, faces, colors, texcoords):
    v = torch.as_tensor(vertices)
    if not v.is_floating_point():
        v = v.double()
    if v.ndim != 2 or v.shape[1] != 3:
        raise ConfigError("vertices", "an (V, 3) array of floats", got=tuple(v.shape))
    f = torch.as_tensor(faces, device=v.device)
    if f.ndim != 2 or f.shape[1] != 3 or f.is_floating_point() or f.dtype == torch.bool:
        raise ConfigError("faces", "an (F, 3) integer array of vertex indices", got=(tuple(f.shape), str(f.dtype)))
    f = f.long()
    if f.numel() and (int(f.min()) < 0 or int(f.max()) >= len(v)):
        raise ConfigError("faces", f"vertex indices in [0, {len(v)})", got=(int(f.min()), int(f.max())))
    if colors is not None and not callable(colors):
        colors = torch.as_tensor(colors, dtype=v.dtype, device=v.device)
        if colors.shape != (len(v), 3):
            raise ConfigError("colors", f"per-vertex RGB ({len(v)}, 3) or a callable", got=tuple(colors.shape))
    if texcoords is not None:
        texcoords = torch.as_tensor(texcoords, dtype=v.dtype, device=v.device)
        if texcoords.ndim != 2 or len(texcoords) != len(v):
            raise ConfigError("texcoords", f"one point per vertex ({len(v)}, C)", got=tuple(texcoords.shape))
    return v, f, colors, texcoords


def rasterize(
    vertices,
    faces,
    camera: Camera,
    *,
    colors=None,
    texcoords=None,
    light=None,
    ambient: float = 0.2,
    background=(1.0, 1.0, 1.0),
    two_sided: bool = False,
    normals=None,
    specular: float = 0.0,
    shininess: float = 40.0,
    chunk_pairs: int = 1 << 21,
) -> dict:
    """Render a triangle mesh with a z-buffer: visibility, barycentrics, colours and Lambert shading.

    Args:
        vertices: ``(V, 3)`` world coordinates (metres), float32 or float64 (sets the dtype).
        faces: ``(F, 3)`` integer vertex indices, counter-clockwise seen from outside.
        camera: a :class:`Camera`; its ``size`` is the image size ``(H, W)``.
        colors: ``None`` (white), per-vertex RGB ``(V, 3)`` in ``[0, 1]``, or a callable
            ``points (P, C) -> RGB (P, 3)`` (a solid texture) evaluated at the interpolated
            ``texcoords`` of each hit pixel.
        texcoords: ``(V, C)`` the points (or any per-vertex attribute) a colour callable receives,
            interpolated per pixel; default the vertices. For a deformed body pass its rest
            positions so that the texture moves with the tissue.
        light: direction ``(3,)`` from the surface towards a directional light (normalised here);
            default ``None``: a headlight, ``-forward`` of the camera.
        ambient: the shade of an unlit face, in ``[0, 1]``.
        background: RGB ``(3,)`` where no triangle is hit.
        two_sided: shade with ``|n . l|`` instead of ``max(0, n . l)``.
        normals: ``(V, 3)`` per-vertex normals, interpolated per pixel and renormalised (smooth
            shading); default ``None``: each face's own normal (flat shading).
        specular: the weight of a white Blinn-Phong highlight, ``specular (n . h)^shininess`` with
            ``h`` half-way between the light and the viewer (0: none; about 0.3 looks wet).
        shininess: the highlight's exponent (larger: smaller, sharper highlights).
        chunk_pairs: at most this many (triangle, pixel) candidate pairs per chunk (memory bound;
            one triangle larger than this is a chunk of its own).

    Returns:
        dict of

        * ``image`` ``(H, W, 3)``: RGB, ``colour * (ambient + (1 - ambient) max(0, n . l))`` plus the
          highlight (clipped to 1);
        * ``depth`` ``(H, W)``: metres along the viewing direction, ``inf`` where nothing is hit;
        * ``face`` ``(H, W)`` int64: index of the visible face, ``-1`` where nothing is hit;
        * ``bary`` ``(H, W, 3)``: barycentric weights of the visible 3-D point in its face's
          vertices (perspective-correct), zeros where nothing is hit.

        Row 0 is the top of the image; see the module notes for pixel centres.

    Raises:
        ConfigError: bad shapes, indices out of range, ``ambient`` outside ``[0, 1]``, a zero
            ``light``.

    Example:
        >>> import trimesh
        >>> s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        >>> cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=2.5, size=(64, 64))
        >>> out = rasterize(torch.as_tensor(s.vertices), torch.as_tensor(s.faces), cam)
        >>> out["image"].shape, out["face"].dtype, round(float(out["depth"][32, 32]), 2)
        (torch.Size([64, 64, 3]), torch.int64, 4.0)
    """
    v, f, colors, texcoords = _check_mesh(vertices, faces, colors, texcoords)
    ambient = float(ambient)
    if not 0.0 <= ambient <= 1.0:
        raise ConfigError("ambient", "a number in [0, 1]", got=ambient)
    bg = torch.tensor(_vec3(background, "background"), dtype=v.dtype, device=v.device)
    H, W = camera.size
    dtype, device = v.dtype, v.device

    # 1-2: project, cull
    pix, z = camera.project(v.detach())
    s = pix[f]  # (F, 3, 2) screen vertices
    zf = z[f]  # (F, 3)
    area = _edges(s[:, 0], s[:, 1], s[:, 2], s[:, 0, 0], s[:, 0, 1])[0]  # twice the signed area
    keep = (area != 0) & torch.isfinite(s).all(2).all(1)
    if camera.perspective:
        keep &= (zf > 0).all(1)
    # pixel index ranges [lo, hi] whose centres fall in each bounding box
    lo = torch.ceil(s.amin(1) - 0.5)
    hi = torch.floor(s.amax(1) - 0.5)
    lim = torch.tensor([W - 1, H - 1], dtype=dtype, device=device)
    lo = torch.maximum(lo, torch.zeros_like(lo))
    hi = torch.minimum(hi, lim)
    n = (hi - lo + 1).clamp(min=0)
    counts = torch.where(keep, n[:, 0] * n[:, 1], torch.zeros_like(area)).long()
    faces_hit = torch.nonzero(counts > 0).flatten()
    x0, y0, nx = lo[:, 0].long(), lo[:, 1].long(), n[:, 0].long()

    # 3-4: cover and depth-test, chunk by chunk (faces in increasing index: ties keep the lower one)
    zbuf = torch.full((H * W,), math.inf, dtype=dtype, device=device)
    fbuf = torch.full((H * W,), -1, dtype=torch.long, device=device)
    big = torch.iinfo(torch.long).max
    # the chunk ends on the host, read once: no host sync per chunk
    cum = torch.cumsum(counts[faces_hit], 0).tolist()
    start = 0
    while start < len(cum):
        base = cum[start - 1] if start else 0
        stop = max(bisect.bisect_right(cum, base + int(chunk_pairs)), start + 1)
        pairs = cum[stop - 1] - base
        fc = faces_hit[start:stop]
        cnt = counts[fc]
        fi = torch.repeat_interleave(fc, cnt, output_size=pairs)  # (P,) face of each pair
        first = torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt, output_size=pairs)
        local = torch.arange(pairs, device=device) - first
        col = x0[fi] + local % nx[fi]
        row = y0[fi] + local // nx[fi]
        px, py = col.to(dtype) + 0.5, row.to(dtype) + 0.5
        sf = s[fi]
        w0, w1, w2 = _edges(sf[:, 0], sf[:, 1], sf[:, 2], px, py)
        sgn = torch.sign(area[fi])
        inside = (w0 * sgn >= 0) & (w1 * sgn >= 0) & (w2 * sgn >= 0)
        fi, col, row = fi[inside], col[inside], row[inside]
        b = torch.stack([w0[inside], w1[inside], w2[inside]], 1) / area[fi, None]
        depth = 1.0 / (b / zf[fi]).sum(1) if camera.perspective else (b * zf[fi]).sum(1)
        pid = row * W + col
        zc = torch.full((H * W,), math.inf, dtype=dtype, device=device).scatter_reduce(0, pid, depth, "amin")
        win = depth == zc[pid]
        fcw = torch.full((H * W,), big, dtype=torch.long, device=device).scatter_reduce(0, pid[win], fi[win], "amin")
        better = zc < zbuf
        zbuf = torch.where(better, zc, zbuf)
        fbuf = torch.where(better, fcw, fbuf)
        start = stop

    # 5: barycentrics, depth, colour and shade of the winning face at every hit pixel
    hit = torch.nonzero(fbuf >= 0).flatten()
    fh = fbuf[hit]
    pix_v, z_v = camera.project(v)  # with autograd, if any
    sv, zv = pix_v[f[fh]], z_v[f[fh]]  # (P, 3, 2), (P, 3)
    px = (hit % W).to(dtype) + 0.5
    py = torch.div(hit, W, rounding_mode="floor").to(dtype) + 0.5
    b = torch.stack(_edges(sv[:, 0], sv[:, 1], sv[:, 2], px, py), 1)
    b = b / b.sum(1, keepdim=True)
    if camera.perspective:
        q = b / zv
        depth = 1.0 / q.sum(1)
        b = q * depth[:, None]
    else:
        depth = (b * zv).sum(1)
    tri = v[f[fh]]  # (P, 3, 3)
    if normals is None:
        normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    else:
        nv = torch.as_tensor(normals, dtype=dtype, device=device)
        if nv.shape != v.shape:
            raise ConfigError("normals", f"per-vertex normals {tuple(v.shape)}", got=tuple(nv.shape))
        normal = (b[:, :, None] * nv[f[fh]]).sum(1)
    normal = normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-30)
    if light is None:
        ldir = -camera.frame(dtype=dtype, device=device)[1][2]
    else:
        ldir = torch.tensor(_vec3(light, "light"), dtype=dtype, device=device)
        if float(ldir.norm()) == 0.0:
            raise ConfigError("light", "a non-zero direction towards the light", got=light)
        ldir = ldir / ldir.norm()
    ndotl = normal @ ldir
    shade = ambient + (1.0 - ambient) * (ndotl.abs() if two_sided else ndotl.clamp(min=0.0))
    highlight = None
    if specular > 0:
        point = (b[:, :, None] * tri).sum(1)
        eye, axes = camera.frame(dtype=dtype, device=device)
        forward = axes[2]
        view = (eye - point) if camera.perspective else -forward.expand_as(point)
        view = view / view.norm(dim=1, keepdim=True).clamp_min(1e-30)
        n = torch.where((normal * view).sum(1, keepdim=True) < 0, -normal, normal) if two_sided else normal
        half = ldir + view
        half = half / half.norm(dim=1, keepdim=True).clamp_min(1e-30)
        highlight = float(specular) * (n * half).sum(1).clamp(min=0.0) ** float(shininess)
    if colors is None:
        rgb = torch.ones(len(hit), 3, dtype=dtype, device=device)
    elif callable(colors):
        tc = v if texcoords is None else texcoords
        rgb = torch.as_tensor(colors((b[:, :, None] * tc[f[fh]]).sum(1)), dtype=dtype, device=device)
        if rgb.shape != (len(hit), 3):
            raise ConfigError("colors", f"a callable returning RGB ({len(hit)}, 3)", got=tuple(rgb.shape))
    else:
        rgb = (b[:, :, None] * colors[f[fh]]).sum(1)

    lit = rgb * shade[:, None]
    if highlight is not None:
        lit = (lit + highlight[:, None]).clamp(max=1.0)
    image = bg.expand(H * W, 3).index_put((hit,), lit)
    depth_img = torch.full((H * W,), math.inf, dtype=dtype, device=device).index_put((hit,), depth)
    bary = torch.zeros(H * W, 3, dtype=dtype, device=device).index_put((hit,), b)
    return {
        "image": image.reshape(H, W, 3),
        "depth": depth_img.reshape(H, W),
        "face": fbuf.reshape(H, W),
        "bary": bary.reshape(H, W, 3),
    }


def save_png(path, image) -> None:
    """Write an RGB image ``(H, W, 3)`` with values in ``[0, 1]`` (tensor or array) as an 8-bit PNG.

    Values are clamped to ``[0, 1]`` and rounded to ``0..255``; row 0 is the top of the picture.
    The file is written by :func:`torchdeform.volume.save_png` (PIL).

    Example:
        >>> import tempfile, pathlib
        >>> from PIL import Image
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "a.png"
        >>> save_png(path, torch.full((2, 3, 3), 0.5))
        >>> Image.open(path).size, Image.open(path).getpixel((0, 0))
        ((3, 2), (128, 128, 128))
    """
    from ..volume.images import save_png as write_png

    img = torch.as_tensor(image).detach().cpu()
    if img.ndim != 3 or img.shape[2] != 3:
        raise ConfigError("image", "an RGB image (H, W, 3)", got=tuple(img.shape))
    write_png(path, (img.double().clamp(0, 1) * 255 + 0.5).to(torch.uint8).contiguous().numpy())
