r"""Planning a straight needle or endoscope path through a volume, and a fly-through along it.

In Radetzky's ROBO-SIM (001, ch. 3.4 and 5.3) the surgeon plans a minimally invasive approach on
the patient's images: an entry point on the skin and a target (a tumour), a straight rigid
instrument between them, checked against the structures it has to spare, and a virtual
endoscope that flies along the path. This module does that on a label volume (or a density
volume) in voxel coordinates.

**Coordinates and units.** Points are voxel coordinates ``(D, H, W)`` of the volume's array,
voxel centres at integers (voxel ``i`` covers ``[i - 1/2, i + 1/2)`` along its axis), as the
cameras use them. Physical lengths are millimetres: ``spacing`` gives the voxel size along
``(D, H, W)`` in mm (anisotropic allowed; the axes are taken as orthogonal). A path point ``p``
(voxels) lies at ``p * spacing`` mm.

* :class:`Trajectory`: a straight path from ``entry`` to ``target`` (or, with
  :meth:`Trajectory.from_points`, a polyline of segments: a bent path to fly along). Positions
  along it by the fraction ``s`` in ``[0, 1]`` of its length in voxels: ``at(s)``.
* :func:`check_trajectory`: what the path passes through and how close it comes to what it must
  avoid, in a :class:`TrajectoryReport`:

  - *Runs.* A label volume is looked up nearest-neighbour (the label of the voxel holding the
    point) at samples at most ``step`` voxels apart; consecutive samples with the same label form
    a run ``(label, name, entry mm, exit mm, length mm)``, its ends found by bisection between the
    two samples where the label changes (to 1e-6 of their gap), distances measured along the path
    in mm from the entry. A structure thinner than ``step`` along the path can be missed. Points
    outside the array form runs of label ``None`` (``"outside"``). A density volume (floats) is
    sampled trilinearly instead: the report holds its profile (distance mm, value).
  - *Clearance.* For each avoided label, the distance in mm from the path to the centres of that
    label's voxels, ``min_c min_t |(c - p(t)) * spacing|`` over the label's voxel centres ``c``
    and the path's points ``p(t)``; 0 when the path runs through one of its voxels (it is
    *crossed*). It is exact (up to rounding), not sampled: the nearest structure voxel to an
    outside point is always one of its boundary voxels (one with a 6-neighbour outside the
    label), so a k-d tree of the boundary voxels' centres in mm (:class:`scipy.spatial.cKDTree`)
    gives each sample's nearest distance ``r_a``; with ``b`` the best exact point-to-segment
    distance among the samples' 8 nearest centres and ``g`` the largest sample gap in mm, every
    centre that could be closer lies within ``b + g/2`` of a sample whose ``r_a <= b + g/2``: those
    centres are gathered and their exact distances to the segments taken. (A Euclidean distance
    transform with ``sampling=spacing``, interpolated along the path, gives the same value to
    within its interpolation error; the boundary-voxel tree is exact and small.)
  - ``ok``: no avoided label is crossed and every clearance is ``>= min_distance`` mm.

* :func:`fly_through`: frames of an :class:`~torchdeform.volume.endoscope.EndoscopeCamera` moving
  along the path from the entry to ``standoff`` voxels before the target, looking along the path
  (along each segment's direction on a polyline), rendered with
  :func:`~torchdeform.volume.interior.render_endoscope`; PNG frames and a GIF written atomically.

Shapes: points ``(3,)``; sets of points ``(N, 3)`` (float64 tensors); volumes ``(D, H, W)`` (or
``(1, 1, D, H, W)``).

Example:
    >>> import numpy as np
    >>> from torchdeform.volume.planning import Trajectory, check_trajectory
    >>> labels = np.zeros((20, 20, 20), np.uint8)
    >>> labels[:, :, 10:] = 1                                   # tissue from W = 9.5 on
    >>> labels[8:13, 8:13, 14:17] = 2                           # a vessel to spare
    >>> path = Trajectory((4.0, 4.0, 0.0), (4.0, 4.0, 18.0))   # along +W, 18 voxels
    >>> report = check_trajectory(labels, path, spacing=(1.0, 1.0, 0.5), names={1: "liver", 2: "vessel"},
    ...                           avoid=[2], min_distance=3.0)
    >>> [(r.name, round(r.entry_mm, 3), round(r.exit_mm, 3)) for r in report.runs]
    [('label 0', 0.0, 4.75), ('liver', 4.75, 9.0)]
    >>> c = report.clearances[0]
    >>> round(c.distance_mm, 4), c.crossed, report.ok          # sqrt(4^2 + 4^2) mm: D and H 4 voxels off
    (5.6569, False, True)
    >>> print("\n".join(report.lines()[:3]))
    path (4, 4, 0) -> (4, 4, 18) voxels, 9 mm, spacing (1, 1, 0.5) mm: ok
    label      from mm  to mm  length mm
    label 0      0.000  4.750      4.750
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..errors import ConfigError

__all__ = ["Trajectory", "Run", "Clearance", "TrajectoryReport", "check_trajectory", "fly_through"]

#: bisection steps that place a run's end between two samples (gap / 2^30)
_BISECT = 30
#: nearest boundary centres looked up per sample before the exact search
_KNN = 8


# ------------------------------------------------------------------ trajectory


def _point(value, key: str) -> np.ndarray:
    """One point ``(3,)`` float64 (voxels, ``(D, H, W)``), finite."""
    try:
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().double().numpy()
        p = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(key, "three coordinates (D, H, W) in voxels", got=_show(value)) from None
    if p.shape != (3,):
        raise ConfigError(key, "three coordinates (D, H, W) in voxels", got=_show(value))
    if not np.isfinite(p).all():
        raise ConfigError(key, "finite coordinates (D, H, W) in voxels (no NaN or inf)", got=p.tolist())
    return p


def _show(value):
    """A one-line form of a user's value for a message."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().tolist()
    elif isinstance(value, np.ndarray):
        value = value.tolist()
    text = repr(value).replace("\n", " ")
    return text if len(text) <= 80 else text[:77] + "..."


class Trajectory:
    """A straight path from ``entry`` to ``target`` (voxel coordinates ``(D, H, W)``), or a polyline.

    Args:
        entry: the entry point ``(3,)`` in voxels (e.g. on the skin).
        target: the target point ``(3,)`` in voxels (e.g. the tumour's centre); not the entry.

    Attributes:
        vertices: the path's points ``(N, 3)`` [voxels], float64; ``N = 2`` for a straight path.
        entry, target: the first and the last vertex ``(3,)`` [voxels].
        segment_lengths: the lengths of the ``N - 1`` segments ``(N - 1,)`` [voxels].
        length: the path's length [voxels].
        direction: the unit vector ``(3,)`` from the entry to the target (the chord; on a straight
            path the path's direction; :meth:`tangent` gives a polyline's local direction).

    Raises:
        ConfigError: a point that is not three finite numbers, or ``target == entry`` (one line,
            naming ``trajectory.entry``, ``trajectory.target`` or ``trajectory.points[i]``).

    Examples:
        >>> path = Trajectory((0.0, 0.0, 0.0), (0.0, 3.0, 4.0))
        >>> path.length, path.direction.tolist(), path.at(0.5).tolist()
        (5.0, [0.0, 0.6, 0.8], [0.0, 1.5, 2.0])
        >>> path.points(spacing=2.0).shape                       # 4 points, 5/3 voxels apart
        torch.Size([4, 3])
        >>> round(path.length_mm(spacing=(1.0, 0.5, 0.5)), 6)     # 2.5 mm long
        2.5
        >>> bent = Trajectory.from_points([(0, 0, 0), (0, 0, 4), (0, 3, 4)])
        >>> bent.length, bent.at(0.75).tolist(), bent.tangent(0.75).tolist()
        (7.0, [0.0, 1.25, 4.0], [0.0, 1.0, 0.0])
        >>> Trajectory((1, 2, 3), (1, 2, 3))
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: trajectory.target: expected a point other than the entry (a path of zero length), got [1.0, 2.0, 3.0]
    """

    def __init__(self, entry, target):
        a = _point(entry, "trajectory.entry")
        b = _point(target, "trajectory.target")
        if np.array_equal(a, b):
            raise ConfigError(
                "trajectory.target", "a point other than the entry (a path of zero length)", got=b.tolist()
            )
        self._set(np.stack([a, b]))

    @classmethod
    def from_points(cls, points) -> Trajectory:
        """A path through ``points`` ``(N, 3)`` (voxels), ``N >= 2``: straight for 2, a polyline for more.

        Raises:
            ConfigError: fewer than two points, a point that is not three finite numbers, two
                consecutive equal points, or a last point equal to the first.
        """
        if isinstance(points, torch.Tensor):
            points = points.detach().cpu().double().numpy()
        try:
            seq = list(points)
        except TypeError:
            raise ConfigError(
                "trajectory.points", "a list of two or more points (D, H, W) in voxels", got=_show(points)
            ) from None
        if len(seq) < 2:
            raise ConfigError(
                "trajectory.points",
                "two or more points (D, H, W) in voxels (an entry and a target)",
                got=f"{len(seq)} point{'' if len(seq) == 1 else 's'}",
            )
        pts = np.stack([_point(p, f"trajectory.points[{i}]") for i, p in enumerate(seq)])
        for i in range(1, len(pts)):
            if np.array_equal(pts[i], pts[i - 1]):
                raise ConfigError(
                    f"trajectory.points[{i}]",
                    "a point other than the one before it (a segment of zero length)",
                    got=pts[i].tolist(),
                )
        if np.array_equal(pts[0], pts[-1]):
            raise ConfigError(
                f"trajectory.points[{len(pts) - 1}]",
                "a target other than the entry (the first point)",
                got=pts[-1].tolist(),
            )
        obj = cls.__new__(cls)
        obj._set(pts)
        return obj

    def _set(self, pts: np.ndarray) -> None:
        self._v = pts
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self._seg = seg
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def vertices(self) -> torch.Tensor:
        """The path's points ``(N, 3)`` [voxels]."""
        return torch.from_numpy(self._v.copy())

    @property
    def entry(self) -> torch.Tensor:
        """The first point ``(3,)`` [voxels]."""
        return torch.from_numpy(self._v[0].copy())

    @property
    def target(self) -> torch.Tensor:
        """The last point ``(3,)`` [voxels]."""
        return torch.from_numpy(self._v[-1].copy())

    @property
    def segment_lengths(self) -> torch.Tensor:
        """The segments' lengths ``(N - 1,)`` [voxels]."""
        return torch.from_numpy(self._seg.copy())

    @property
    def length(self) -> float:
        """The path's length [voxels]."""
        return float(self._cum[-1])

    @property
    def direction(self) -> torch.Tensor:
        """The unit vector ``(3,)`` from the entry to the target."""
        d = self._v[-1] - self._v[0]
        return torch.from_numpy(d / np.linalg.norm(d))

    @property
    def straight(self) -> bool:
        """True for a path of one segment."""
        return len(self._v) == 2

    def length_mm(self, *, spacing=(1.0, 1.0, 1.0)) -> float:
        """The path's length in mm for voxels of ``spacing`` mm along ``(D, H, W)``."""
        sp = _spacing(spacing)
        return float(np.linalg.norm(np.diff(self._v, axis=0) * sp, axis=1).sum())

    def _locate(self, s, key: str = "s"):
        """Segment index and the fraction along it of the path fraction(s) ``s``."""
        arr = s.detach().cpu().double().numpy() if isinstance(s, torch.Tensor) else np.asarray(s, dtype=np.float64)
        if not (np.isfinite(arr).all() and (arr >= 0).all() and (arr <= 1).all()):
            raise ConfigError(key, "a fraction of the path's length in [0, 1]", got=_show(s))
        u = arr * self._cum[-1]
        i = np.searchsorted(self._cum[1:-1], u, side="left").astype(np.int64)
        t = np.clip((u - self._cum[i]) / self._seg[i], 0.0, 1.0)
        return arr, i, t

    def at(self, s) -> torch.Tensor:
        """The point at fraction ``s`` of the path's length (voxels): ``(3,)``, or ``(*s.shape, 3)``.

        ``s = 0`` is the entry, ``s = 1`` the target; on a straight path ``entry + s (target - entry)``.
        """
        _, i, t = self._locate(s)
        p = self._v[i] + t[..., None] * (self._v[i + 1] - self._v[i])
        return torch.from_numpy(np.asarray(p, dtype=np.float64))

    def tangent(self, s) -> torch.Tensor:
        """The unit direction ``(3,)`` (or ``(*s.shape, 3)``) of the segment at fraction ``s``."""
        _, i, _ = self._locate(s)
        d = (self._v[i + 1] - self._v[i]) / self._seg[i][..., None]
        return torch.from_numpy(np.asarray(d, dtype=np.float64))

    def points(self, *, spacing: float = 1.0) -> torch.Tensor:
        """Points along the path ``(M, 3)`` (voxels), at most ``spacing`` voxels apart.

        Each segment is split into ``ceil(length / spacing)`` equal parts; every vertex (the entry,
        the bends, the target) is among the points, each once.
        """
        return torch.from_numpy(self._samples(spacing, key="spacing")[0])

    def _samples(self, step: float, *, key: str = "step"):
        """Points ``(M, 3)`` at most ``step`` voxels apart, every vertex included, and each point's segment."""
        step = _positive(step, key, "voxels")
        pts, seg = [self._v[:1]], [np.zeros(1, np.int64)]
        for k, n in enumerate(np.maximum(np.ceil(self._seg / step - 1e-9), 1).astype(np.int64)):
            t = np.arange(1, n + 1, dtype=np.float64) / n
            pts.append(self._v[k] + t[:, None] * (self._v[k + 1] - self._v[k]))
            seg.append(np.full(n, k, np.int64))
        return np.concatenate(pts), np.concatenate(seg)

    def __repr__(self) -> str:
        if self.straight:
            return f"Trajectory(entry={_fmt(self._v[0])}, target={_fmt(self._v[-1])}, length={self.length:.4g} voxels)"
        return f"Trajectory.from_points({[_fmt(p) for p in self._v]}, length={self.length:.4g} voxels)"


def _fmt(p) -> str:
    return "(" + ", ".join(f"{float(c):.4g}" for c in p) + ")"


def _positive(value, key: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ConfigError(key, f"a positive number of {unit}", got=_show(value))
    if not (math.isfinite(float(value)) and float(value) > 0):
        raise ConfigError(key, f"a positive number of {unit}", got=value)
    return float(value)


def _spacing(spacing, key: str = "spacing") -> np.ndarray:
    """Voxel size along ``(D, H, W)`` in mm, ``(3,)`` float64; a number means the same on every axis."""
    try:
        sp = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise ConfigError(key, "three positive voxel sizes (D, H, W) in mm", got=_show(spacing)) from None
    if not (np.isfinite(sp).all() and (sp > 0).all()):
        raise ConfigError(key, "three positive voxel sizes (D, H, W) in mm", got=sp.tolist())
    return sp


# ------------------------------------------------------------------ report


class Run(NamedTuple):
    """A stretch of the path in one label.

    ``label`` (None outside the volume), its ``name``, and where it starts and ends along the path
    (``entry_mm``, ``exit_mm``, ``length_mm``: mm from the path's entry).
    """

    label: int | None
    name: str
    entry_mm: float
    exit_mm: float
    length_mm: float


class Clearance(NamedTuple):
    """How close the path comes to an avoided label.

    ``distance_mm``: the distance [mm] from the path to the centres of the label's voxels (0 when
    ``crossed``; inf when the label is not in the volume, ``present`` False); ``at_mm``: where along
    the path [mm from the entry] the closest approach (or the first crossing) is; ``point``: that
    point in voxels ``(D, H, W)``; ``voxel``: the label's voxel nearest to it (None when crossed or
    absent).
    """

    label: int
    name: str
    distance_mm: float
    crossed: bool
    present: bool
    at_mm: float | None
    point: tuple | None
    voxel: tuple | None


class TrajectoryReport(NamedTuple):
    """The result of :func:`check_trajectory`.

    Attributes:
        trajectory: the checked :class:`Trajectory`.
        spacing: voxel size ``(D, H, W)`` [mm].
        kind: ``"labels"`` or ``"density"``.
        length_mm: the path's length [mm].
        runs: the :class:`Run` s in path order (labels; empty for a density volume).
        clearances: one :class:`Clearance` per avoided label, in the order given.
        min_distance: the required clearance [mm].
        ok: no avoided label crossed and every clearance ``>= min_distance``.
        problems: one sentence per reason that ``ok`` is False.
        profile: for a density volume, ``(distance_mm (M,), value (M,))`` numpy arrays of the
            trilinear samples (NaN outside the volume); None for labels.
    """

    trajectory: Trajectory
    spacing: tuple
    kind: str
    length_mm: float
    runs: list
    clearances: list
    min_distance: float
    ok: bool
    problems: list
    profile: tuple | None

    def lines(self) -> list:
        """The report as lines of text: a header, the table of runs, the clearances, the problems."""
        t = self.trajectory
        sp = "(" + ", ".join(f"{s:g}" for s in self.spacing) + ")"
        where = (
            f"path {_fmt(t._v[0])} -> {_fmt(t._v[-1])} voxels"
            if t.straight
            else f"path of {len(t._v) - 1} segments {_fmt(t._v[0])} -> {_fmt(t._v[-1])} voxels"
        )
        out = [f"{where}, {self.length_mm:.4g} mm, spacing {sp} mm: {'ok' if self.ok else 'NOT ok'}"]
        if self.kind == "labels":
            width = max([len("label")] + [len(r.name) for r in self.runs])
            out.append(f"{'label':<{width}}  from mm  to mm  length mm")
            for r in self.runs:
                out.append(f"{r.name:<{width}}  {r.entry_mm:7.3f}  {r.exit_mm:5.3f}  {r.length_mm:9.3f}")
        elif self.profile is not None:
            v = self.profile[1]
            inside = v[np.isfinite(v)]
            if inside.size:
                out.append(
                    f"density along the path: min {inside.min():.4g}, mean {inside.mean():.4g}, max {inside.max():.4g} "
                    f"({inside.size} of {v.size} samples inside the volume)"
                )
            else:
                out.append("density along the path: the path lies outside the volume")
        for c in self.clearances:
            if not c.present:
                out.append(f"avoid {c.name}: not in the volume")
            elif c.crossed:
                out.append(f"avoid {c.name}: CROSSED at {c.at_mm:.3f} mm")
            else:
                flag = "" if c.distance_mm >= self.min_distance else f" (< {self.min_distance:g} mm)"
                out.append(f"avoid {c.name}: {c.distance_mm:.3f} mm at {c.at_mm:.3f} mm along the path{flag}")
        out.extend(f"problem: {p}" for p in self.problems)
        return out

    def to_dict(self) -> dict:
        """The report as plain JSON-able values (an absent label's distance as None)."""
        t = self.trajectory
        d = {
            "entry": t._v[0].tolist(),
            "target": t._v[-1].tolist(),
            "points": t._v.tolist(),
            "spacing_mm": list(self.spacing),
            "kind": self.kind,
            "length_mm": self.length_mm,
            "runs": [r._asdict() for r in self.runs],
            "clearances": [
                {
                    **c._asdict(),
                    "distance_mm": c.distance_mm if math.isfinite(c.distance_mm) else None,
                    "point": list(c.point) if c.point is not None else None,
                    "voxel": list(c.voxel) if c.voxel is not None else None,
                }
                for c in self.clearances
            ],
            "min_distance_mm": self.min_distance,
            "ok": self.ok,
            "problems": list(self.problems),
        }
        if self.profile is not None:
            dist, val = self.profile
            d["profile"] = {
                "distance_mm": [float(x) for x in dist],
                "value": [float(x) if math.isfinite(x) else None for x in val],
            }
        return d


# ------------------------------------------------------------------ check


def _volume_array(volume, key: str = "volume") -> np.ndarray:
    if isinstance(volume, torch.Tensor):
        volume = volume.detach().cpu().numpy()
    try:
        arr = np.asarray(volume)
    except (TypeError, ValueError):
        raise ConfigError(key, "an array (D, H, W) of labels or densities", got=type(volume).__name__) from None
    if arr.ndim == 5 and arr.shape[:2] == (1, 1):
        arr = arr[0, 0]
    if arr.ndim != 3 or min(arr.shape) < 1 or arr.dtype.kind not in "biuf":
        raise ConfigError(
            key, "a numeric array (D, H, W) (or (1, 1, D, H, W)) of labels or densities", got=f"{arr.dtype} {arr.shape}"
        )
    return arr


def check_trajectory(
    labels_or_volume,
    trajectory,
    *,
    spacing=None,
    names=None,
    avoid=None,
    min_distance: float = 0.0,
    step: float = 0.25,
    kind: str = "auto",
) -> TrajectoryReport:
    """What a straight (or polyline) path passes through, and how close it comes to what it must avoid.

    The method is in the module's description (:mod:`torchdeform.volume.planning`).

    Args:
        labels_or_volume: an integer label volume ``(D, H, W)`` (looked up nearest-neighbour), or a
            density volume (floats, sampled trilinearly); numpy, torch or an
            :class:`~torchdeform.anatomy.images.Image` (its array; its spacing in mm by default).
        trajectory: a :class:`Trajectory`, or its points ``(N, 3)`` in voxels ``(D, H, W)``.
        spacing: voxel size along ``(D, H, W)`` in mm (a number for all three); default: an
            ``Image``'s spacing (metres -> mm), else 1 mm.
        names: ``{label: name}`` for the report (default ``"label <n>"``).
        avoid: a label or labels the path must not cross and must keep ``min_distance`` mm from
            (label volumes only).
        min_distance: the clearance required from every avoided label [mm], ``>= 0``.
        step: the largest gap between samples along the path [voxels].
        kind: ``"auto"`` (integer or boolean arrays are labels, floating ones densities),
            ``"labels"`` (float arrays holding whole numbers) or ``"density"``.

    Returns:
        A :class:`TrajectoryReport`.

    Raises:
        ConfigError: a bad volume, trajectory, spacing, step, min_distance, kind or avoid (one
            line naming the key).

    Example:
        >>> import numpy as np
        >>> lab = np.zeros((9, 9, 9), np.int16); lab[:, :, 5:] = 3
        >>> rep = check_trajectory(lab, [(4, 4, 0), (4, 4, 8)], names={3: "bone"}, avoid=3, min_distance=1.0)
        >>> rep.ok, rep.problems
        (False, ['crosses bone from 4.500 mm'])
    """
    spacing_default = (1.0, 1.0, 1.0)
    if hasattr(labels_or_volume, "array") and hasattr(labels_or_volume, "affine"):
        spacing_default = tuple(float(s) * 1e3 for s in np.asarray(labels_or_volume.spacing, dtype=np.float64))
        labels_or_volume = labels_or_volume.array
    arr = _volume_array(labels_or_volume)
    sp = _spacing(spacing_default if spacing is None else spacing)
    traj = trajectory if isinstance(trajectory, Trajectory) else Trajectory.from_points(trajectory)
    step = _positive(step, "step", "voxels")
    if isinstance(min_distance, bool) or not isinstance(min_distance, int | float | np.integer | np.floating):
        raise ConfigError("min_distance", "a number of mm >= 0", got=_show(min_distance))
    if not (math.isfinite(float(min_distance)) and float(min_distance) >= 0):
        raise ConfigError("min_distance", "a number of mm >= 0", got=min_distance)
    min_distance = float(min_distance)
    if kind not in ("auto", "labels", "density"):
        raise ConfigError("kind", "one of 'auto', 'labels', 'density'", got=kind)
    if kind == "auto":
        kind = "labels" if arr.dtype.kind in "biu" else "density"
    names = dict(names or {})
    avoid_list = _avoid(avoid)
    if kind == "labels" and arr.dtype.kind == "f":
        if not np.isfinite(arr).all() or not np.array_equal(arr, np.round(arr)):
            raise ConfigError("volume", "whole-number labels (kind='labels')", got="non-integer or non-finite values")
        arr = arr.astype(np.int64)
    if kind == "density":
        if not np.isfinite(arr).all():
            raise ConfigError(
                "volume", "finite densities (no NaN or inf)", got=f"{int((~np.isfinite(arr)).sum())} non-finite voxels"
            )
        if avoid_list:
            raise ConfigError(
                "avoid", "labels to avoid in a label volume (this volume holds densities: kind='density')", got=avoid
            )

    def name(label):
        if label is None:
            return "outside"
        return str(names.get(label, f"label {label}"))

    pts, _ = traj._samples(step)
    gaps = np.linalg.norm(np.diff(pts, axis=0) * sp, axis=1)
    dist = np.concatenate([[0.0], np.cumsum(gaps)])
    length_mm = float(dist[-1])

    runs, clearances, problems, profile = [], [], [], None
    if kind == "density":
        from scipy.ndimage import map_coordinates

        values = map_coordinates(arr.astype(np.float64), pts.T, order=1, mode="nearest")
        outside = ((pts < -0.5) | (pts > np.asarray(arr.shape) - 0.5)).any(axis=1)
        values[outside] = np.nan
        profile = (dist, values)
    else:
        lab, ins = _lookup(arr, pts)
        change = np.nonzero((lab[1:] != lab[:-1]) | (ins[1:] != ins[:-1]))[0]
        cuts = _bisect(arr, pts, dist, change, lab, ins)
        starts = np.concatenate([[0.0], cuts])
        ends = np.concatenate([cuts, [length_mm]])
        firsts = np.concatenate([[0], change + 1])
        for a, b, i in zip(starts, ends, firsts, strict=True):
            label = int(lab[i]) if ins[i] else None
            runs.append(Run(label, name(label), float(a), float(b), float(b - a)))
        for label in avoid_list:
            c = _clearance(arr, sp, traj, pts, dist, label, name(label), runs, lab, ins)
            clearances.append(c)
            if c.crossed:
                spans = [r for r in runs if r.label == label]
                problems.append(
                    f"crosses {c.name} from {spans[0].entry_mm:.3f} mm"
                    + (f" ({len(spans)} times)" if len(spans) > 1 else "")
                )
            elif c.present and c.distance_mm < min_distance:
                problems.append(
                    f"passes {c.distance_mm:.3f} mm from {c.name} at {c.at_mm:.3f} mm, less than {min_distance:g} mm"
                )
    return TrajectoryReport(
        trajectory=traj,
        spacing=tuple(float(s) for s in sp),
        kind=kind,
        length_mm=length_mm,
        runs=runs,
        clearances=clearances,
        min_distance=min_distance,
        ok=not problems,
        problems=problems,
        profile=profile,
    )


def _avoid(avoid) -> list:
    if avoid is None:
        return []
    items = [avoid] if isinstance(avoid, int | np.integer) else avoid
    try:
        items = list(items)
    except TypeError:
        raise ConfigError("avoid", "a label or a list of labels (integers)", got=_show(avoid)) from None
    for x in items:
        if isinstance(x, bool) or not isinstance(x, int | np.integer):
            raise ConfigError("avoid", "a label or a list of labels (integers)", got=_show(avoid))
    return [int(x) for x in dict.fromkeys(items)]


def _lookup(arr: np.ndarray, pts: np.ndarray):
    """Nearest-neighbour labels ``(M,)`` int64 and inside flags ``(M,)`` of points ``(M, 3)``."""
    idx = np.floor(pts + 0.5).astype(np.int64)
    ins = ((idx >= 0) & (idx < np.asarray(arr.shape))).all(axis=1)
    lab = np.zeros(len(pts), np.int64)
    ii = idx[ins]
    lab[ins] = arr[ii[:, 0], ii[:, 1], ii[:, 2]]
    return lab, ins


def _bisect(arr, pts, dist, change, lab, ins) -> np.ndarray:
    """Distances [mm] along the path where the label changes between samples ``change`` and ``change + 1``."""
    if change.size == 0:
        return np.zeros(0)
    a, b = pts[change], pts[change + 1]
    key_lab, key_in = lab[change], ins[change]
    lo, hi = np.zeros(len(change)), np.ones(len(change))
    for _ in range(_BISECT):
        mid = 0.5 * (lo + hi)
        ml, mi = _lookup(arr, a + mid[:, None] * (b - a))
        same = (mi == key_in) & ((ml == key_lab) | ~mi)
        lo = np.where(same, mid, lo)
        hi = np.where(same, hi, mid)
    t = 0.5 * (lo + hi)
    return dist[change] + t * (dist[change + 1] - dist[change])


def _segment_distance(c: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Distances ``(K,)`` from points ``c`` ``(K, 3)`` to the segment ``a``-``b`` (all in mm), and ``t`` ``(K,)``.

    ``t`` is the fraction along the segment of each point's closest point.
    """
    ab = b - a
    t = np.clip(((c - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(c - (a + t[:, None] * ab), axis=1), t


def _clearance(arr, sp, traj, pts, dist, label, name, runs, lab, ins) -> Clearance:
    mask = arr == label
    if not mask.any():
        return Clearance(label, name, math.inf, False, False, None, None, None)
    hit = ins & (lab == label)
    if hit.any():
        first = next(r for r in runs if r.label == label)
        return Clearance(
            label,
            name,
            0.0,
            True,
            True,
            first.entry_mm,
            tuple(float(x) for x in _point_at_mm(traj, sp, first.entry_mm)),
            None,
        )
    from scipy.ndimage import binary_erosion
    from scipy.spatial import cKDTree

    boundary = mask & ~binary_erosion(mask)  # the only candidates for the nearest voxel to an outside point
    vox = np.argwhere(boundary)
    centres = vox * sp
    tree = cKDTree(centres)
    pmm = pts * sp
    k = min(_KNN, len(centres))
    r, nn = tree.query(pmm, k=k)
    r, nn = r.reshape(len(pts), k), nn.reshape(len(pts), k)
    vmm = traj._v * sp
    best = _best(vmm, centres, np.unique(nn))
    half_gap = 0.5 * float(np.max(np.linalg.norm(np.diff(pmm, axis=0), axis=1), initial=0.0))
    radius = best[0] + half_gap + 1e-9 * (1.0 + best[0])
    near = r[:, 0] <= radius
    more = tree.query_ball_point(pmm[near], radius)
    extra = np.unique(np.concatenate([np.asarray(m, np.int64) for m in more] + [np.zeros(0, np.int64)]))
    if extra.size:
        b2 = _best(vmm, centres, extra)
        if b2[0] < best[0]:
            best = b2
    d, j, seg, t = best
    a, b = traj._v[seg], traj._v[seg + 1]
    p = a + t * (b - a)
    at = float(np.linalg.norm((p - a) * sp) + np.linalg.norm(np.diff(traj._v[: seg + 1], axis=0) * sp, axis=1).sum())
    return Clearance(label, name, float(d), False, True, at, tuple(float(x) for x in p), tuple(int(x) for x in vox[j]))


def _best(vmm: np.ndarray, centres: np.ndarray, idx: np.ndarray):
    """The closest of the centres ``idx`` to the polyline ``vmm`` (mm): ``(distance, centre, segment, t)``."""
    best = (math.inf, -1, 0, 0.0)
    for s in range(len(vmm) - 1):
        d, t = _segment_distance(centres[idx], vmm[s], vmm[s + 1])
        i = int(np.argmin(d))
        if d[i] < best[0]:
            best = (float(d[i]), int(idx[i]), s, float(t[i]))
    return best


def _point_at_mm(traj: Trajectory, sp: np.ndarray, s_mm: float) -> np.ndarray:
    """The path's point (voxels) ``s_mm`` mm from the entry."""
    seg_mm = np.linalg.norm(np.diff(traj._v, axis=0) * sp, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_mm)])
    i = int(np.clip(np.searchsorted(cum[1:-1], s_mm, side="left"), 0, len(seg_mm) - 1))
    t = float(np.clip((s_mm - cum[i]) / seg_mm[i], 0.0, 1.0))
    return traj._v[i] + t * (traj._v[i + 1] - traj._v[i])


# ------------------------------------------------------------------ fly-through


def fly_through(
    volume,
    trajectory,
    *,
    frames: int = 24,
    size=(256, 256),
    fov: float = 100.0,
    tf=None,
    offsets=None,
    standoff: float = 0.0,
    out=None,
    fps: float = 12.0,
    progress: bool = True,
    inside: str = "require",
    far: float = math.inf,
    distortion: float = 0.0,
    **render_kw,
) -> list:
    """Frames of a virtual endoscope flying along ``trajectory`` from the entry towards the target.

    Frame ``i`` of ``n`` has the camera at fraction ``s_i = i / (n - 1)`` of the way from the entry
    to the point ``standoff`` voxels before the target (``s_0 = 0``: the entry), looking along the
    path (on a straight path: towards the target; on a polyline: along the segment it is on), up
    as close to ``+D`` as the view direction allows.

    Args:
        volume: a density volume ``(D, H, W)`` or ``(B, C, D, H, W)``, as
            :func:`~torchdeform.volume.interior.render_endoscope` takes it.
        trajectory: a :class:`Trajectory` or its points ``(N, 3)`` [voxels, ``(D, H, W)``].
        frames: the number of frames, ``>= 1``.
        size: image ``(h, w)`` [pixels].
        fov: the endoscope's field of view [degrees].
        tf: the transfer function (a :class:`~torchdeform.volume.TransferFunction`, a preset name or
            a file; default the renderer's), passed to ``render_endoscope``.
        offsets: node offsets ``(3, n_d, n_h, n_w)`` [voxels] deforming the volume, or None,
            passed to ``render_endoscope``.
        standoff: stop this many voxels before the target (along the path), ``0 <= standoff < length``.
        out: a folder (created if needed) for ``frame_000.png``, ... and ``fly_through.gif``;
            each file is written atomically. None: write nothing.
        fps: the GIF's frame rate [frames/s].
        progress: show a tqdm progress bar.
        inside: the camera's ``inside``: ``"require"`` (every camera position inside the volume's
            box) or ``"allow"`` (a path that starts outside the volume).
        far: the camera's depth of view [voxels along the ray] (the volume of interest).
        distortion: the camera's barrel coefficient ``k1``.
        **render_kw: further keywords of ``render_endoscope`` (``light``, ``step``, ``engine`` ...).

    Returns:
        The frames: a list of uint8 RGB arrays ``(h, w, 3)``
        (:func:`~torchdeform.volume.images.to_image` of each rendering).

    Raises:
        ConfigError: bad frames, standoff, fps or out (one line naming the key); the camera's and
            the renderer's own checks.

    Example:
        >>> import torch
        >>> vol = torch.zeros(16, 16, 16); vol[:, :, 12:] = 1.0          # a wall at the far end
        >>> path = Trajectory((8.0, 8.0, 2.0), (8.0, 8.0, 10.0))
        >>> imgs = fly_through(vol, path, frames=3, size=(16, 16), progress=False)
        >>> len(imgs), imgs[0].shape, imgs[0].dtype.name
        (3, (16, 16, 3), 'uint8')
    """
    from tqdm.auto import tqdm

    from .endoscope import EndoscopeCamera
    from .images import save_gif, save_png, to_image
    from .interior import render_endoscope

    traj = trajectory if isinstance(trajectory, Trajectory) else Trajectory.from_points(trajectory)
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        raise ConfigError("frames", "a whole number of frames >= 1", got=frames)
    frames = int(frames)
    if isinstance(standoff, bool) or not isinstance(standoff, int | float | np.integer | np.floating):
        raise ConfigError("standoff", "a number of voxels >= 0 and less than the path's length", got=_show(standoff))
    standoff = float(standoff)
    if not (math.isfinite(standoff) and 0.0 <= standoff < traj.length):
        raise ConfigError(
            "standoff", f"a number of voxels >= 0 and less than the path's length ({traj.length:.4g})", got=standoff
        )
    fps = _positive(fps, "fps", "frames per second")
    folder = None
    if out is not None:
        folder = Path(out)
        if folder.exists() and not folder.is_dir():
            raise ConfigError("out", "a folder (this path is a file)", got=str(folder))
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ConfigError("out", f"a folder that can be created ({e.strerror})", got=str(folder)) from None
    end = 1.0 - standoff / traj.length
    fractions = [end * i / (frames - 1) if frames > 1 else 0.0 for i in range(frames)]
    digits = max(3, len(str(frames - 1)))
    images = []
    for i, s in enumerate(tqdm(fractions, disable=not progress, desc="fly-through", unit="frame")):
        position = traj.at(s)
        direction = traj.tangent(s) if not traj.straight else traj.direction
        camera = EndoscopeCamera(
            position=tuple(float(x) for x in position),
            direction=tuple(float(x) for x in direction),
            up=_up(direction),
            fov=fov,
            size=size,
            inside=inside,
            far=far,
            distortion=distortion,
        )
        with torch.no_grad():
            image = render_endoscope(volume, camera, tf=tf, offsets=offsets, **render_kw)
        rgb = to_image(image)
        images.append(rgb)
        if folder is not None:
            save_png(folder / f"frame_{i:0{digits}d}.png", rgb)
    if folder is not None:
        save_gif(folder / "fly_through.gif", images, fps=fps)
    return images


def _up(direction) -> tuple:
    """An up vector for a camera looking along ``direction``: +D unless it looks (nearly) along D, then +H."""
    d = np.asarray(direction, dtype=np.float64)
    return (1.0, 0.0, 0.0) if abs(d[0]) < 0.99 else (0.0, 1.0, 0.0)
