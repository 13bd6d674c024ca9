r"""Reading a tool's force series: the direction it works in, block means, and its presses (palpation).

Everything here is a function of numpy series sampled at the steps of a run (``t`` ``(T,)`` s, a
tool's force ``(T, 3)`` N, the force the tissue exerts on it as the hand feels it, its position
``(T, 3)`` m, its contact count ``(T,)``), such as :class:`~torchdeform.scene.tools.ToolRecorder`
keeps; nothing reads scene files.

* :func:`work_direction`: the unit vector ``u`` along which the tool works against the tissue, its
  directions of motion weighted by the power it puts into the tissue (down for a probe pressing
  into a surface, up for forceps lifting tissue). Along it the displacement is
  ``s = (p - p0) . u`` (m) and the force along the motion ``-F . u`` (N): the tissue's resistance.
* :func:`block_means`: a long series as the means over blocks of steps (the impulse per time, so
  no spike of a single step is lost or exaggerated); :func:`significant` rounds numbers for a
  summary.
* :func:`palpation`: the presses of a tool, force against indentation in each, and where along
  the line of presses the tissue is stiffest; :func:`plot_palpation` draws them.

Example:
    >>> import numpy as np
    >>> t = np.linspace(0.0, 1.0, 101)
    >>> position = np.stack([-1e-3 * t, 0 * t, 0 * t], 1)                 # moving down 1 mm
    >>> force = np.stack([50.0 * 1e-3 * t, 0 * t, 0 * t], 1)              # the tissue pushes back up
    >>> work_direction(t, position, force).tolist()
    [-1.0, 0.0, 0.0]
    >>> block_means(force[:, 0], 50).round(6).tolist(), significant([0.123456789, 2.0], digits=3)
    ([0.01225, 0.03725, 0.05], [0.123, 2.0])
"""

from __future__ import annotations

import math

import numpy as np

from ..outputs import figure, save_figure

__all__ = ["work_direction", "block_means", "significant", "palpation", "plot_palpation"]


def work_direction(t: np.ndarray, position: np.ndarray, force: np.ndarray) -> np.ndarray:
    """The unit vector ``(3,)`` along which a tool works against the tissue (zero if it never does).

    ``u`` is proportional to ``sum_t max(0, -F . v) v / |v|``: the tool's directions of motion,
    weighted by the power it puts into the tissue (``-F`` is its push on the tissue, ``v`` its
    velocity from ``position``). Down for a probe pressing into a surface, up for forceps lifting
    tissue; ``-sum F`` for a tool that does no work, e.g. one that stands still.

    Args:
        t: times ``(T,)`` s.
        position: the tool's positions ``(T, 3)`` m.
        force: the force it feels ``(T, 3)`` N.
    """
    v = np.gradient(position, t, axis=0) if len(t) > 1 else np.zeros_like(position)
    speed = np.linalg.norm(v, axis=1, keepdims=True)
    power = np.clip(-(force * v).sum(1, keepdims=True), 0, None)
    u = (power * v / np.where(speed > 0, speed, 1)).sum(0)
    if not np.linalg.norm(u) > 0:
        u = -force.sum(0)
    length = np.linalg.norm(u)
    return u / length if length > 0 else np.zeros(3)


def block_means(a: np.ndarray, size: int) -> np.ndarray:
    """Means over consecutive blocks of ``size`` rows of ``a`` ``(T, ...)``: ``(ceil(T / size), ...)``.

    The last block may be shorter; ``size <= 1`` returns ``a`` itself.
    """
    if size <= 1:
        return a
    n = len(a)
    starts = np.arange(0, n, size)
    sums = np.add.reduceat(a, starts, axis=0)
    counts = np.diff(np.append(starts, n)).reshape((-1,) + (1,) * (a.ndim - 1))
    return sums / counts


def significant(a, *, digits: int = 6):
    """Nested lists of floats with ``digits`` significant digits (keeps summary.json small)."""
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return a.tolist()
    return np.vectorize(lambda x: float(f"{x:.{digits}g}"), otypes=[np.float64])(a).tolist()


def _episodes(touching: np.ndarray, min_steps: int) -> list:
    """``[(start, stop), ...]`` of the runs of ``touching``; gaps shorter than a tenth of both runs are bridged."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], touching.astype(np.int8), [0]])))
    runs = [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]
    merged = []
    for a, b in runs:
        if merged and a - merged[-1][1] < 0.1 * min(b - a, merged[-1][1] - merged[-1][0]):
            merged[-1] = (merged[-1][0], b)
        else:
            merged.append((a, b))
    return [(a, b) for a, b in merged if b - a >= min_steps]


def _smooth(a: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average of odd ``width`` (shorter at the ends)."""
    if width <= 1 or len(a) < 3:
        return a
    kernel = np.ones(width)
    return np.convolve(a, kernel, "same") / np.convolve(np.ones_like(a), kernel, "same")


def palpation(
    t: np.ndarray,
    force: np.ndarray,
    position: np.ndarray,
    contacts: np.ndarray,
    *,
    velocity: np.ndarray | None = None,
    curve_points: int = 100,
) -> dict:
    """The presses of a tool: force against indentation at each point, and where the tissue is stiffest.

    A press is a run of steps in which the tool touches the tissue (``contacts > 0``; gaps shorter
    than a tenth of the runs beside them are bridged, runs under 10 steps dropped). In each press,
    from the tool's position ``p_on`` at first contact, the press direction ``n`` points to the
    deepest position ``p_max`` (the farthest from ``p_on``), the indentation is
    ``delta = (p - p_on) . n`` and the force ``F_n = -F . n`` (N, the tissue pushing back). On the
    loading branch (first contact to ``p_max`` while the tool moves inwards, ``velocity . n > 0``: the
    step at which it turns round is left out; ``F_n`` smoothed over about 2 % of the branch): the peak
    force, the indentation there, the slope of ``F_n`` against ``delta`` (N/m, a least-squares line
    through ``delta_max / 2 .. delta_max``), ``p_max``, and the branch as the force-indentation
    curve. Positions along the line of presses are
    ``(p_max - p_max[0]) . e`` with ``e`` the unit vector from the first press to the last.

    Args:
        t: times ``(T,)`` s.
        force: the force the tool feels ``(T, 3)`` N.
        position: the tool's position ``(T, 3)`` m.
        contacts: nodes touched per step ``(T,)``.
        velocity: the tool's velocity ``(T, 3)`` m/s (that of the path segment entered at each time),
            or None: forward differences of ``position``.
        curve_points: points per force-indentation curve in the result.

    Returns:
        ``{"points": [{"position_m", "along_m", "t_s" (start, end), "indentation_m", "peak_force_N",
        "stiffness_N_per_m", "curve": {"indentation_m", "force_N"}}, ...], "stiffest": {...}}``;
        ``stiffest`` is the press with the largest peak force (``index``, ``along_m``,
        ``position_m``, ``peak_force_N``, ``ratio_to_median``) or None when there is no press.

    Examples:
        >>> import numpy as np
        >>> t = np.linspace(0, 2, 2001)
        >>> depth = np.clip(1 - abs((t % 1) - 0.5) * 4, 0, None) * 1e-3          # two presses, 1 mm deep
        >>> position = np.stack([-depth, np.zeros_like(t), np.floor(t) * 0.01], 1)
        >>> stiffness = np.where(t < 1, 100.0, 300.0)                           # N/m: the second is stiffer
        >>> force = np.stack([stiffness * depth, 0 * t, 0 * t], 1)              # the tissue pushes up
        >>> r = palpation(t, force, position, depth > 0)
        >>> [round(p["stiffness_N_per_m"]) for p in r["points"]], r["stiffest"]["index"], r["stiffest"]["along_m"]
        ([100, 300], 1, 0.01)
    """
    t, force, position = np.asarray(t, float), np.asarray(force, float), np.asarray(position, float)
    points = []
    for a, b in _episodes(np.asarray(contacts) > 0, min_steps=10):
        p = position[a:b]
        offset = p - p[0]
        k = int(np.argmax(np.linalg.norm(offset, axis=1)))
        depth = float(np.linalg.norm(offset[k]))
        if depth == 0:
            continue
        n = offset[k] / depth
        inward = (velocity[a:b] @ n) > 0 if velocity is not None else np.diff(offset @ n, append=-np.inf) > 0
        while k > 0 and not inward[k]:  # the loading branch ends where the tool
            k -= 1  # last moved inwards (not at its turn)
        delta = (offset @ n)[: k + 1]
        f = _smooth(-(force[a : a + k + 1] @ n), 2 * max(1, (k + 1) // 100) + 1)
        peak = int(np.argmax(f))
        upper = np.flatnonzero(delta >= 0.5 * depth)
        slope = (
            float(np.polyfit(delta[upper], f[upper], 1)[0])
            if len(upper) >= 2 and np.ptp(delta[upper]) > 0
            else float("nan")
        )
        keep = np.unique(np.linspace(0, k, min(curve_points, k + 1)).round().astype(int))  # the loading branch
        points.append(
            {
                "position_m": significant(p[k]),
                "t_s": significant([t[a], t[b - 1]]),
                "indentation_m": depth,
                "peak_force_N": float(f[peak]),
                "peak_indentation_m": float(delta[peak]),
                "stiffness_N_per_m": slope if math.isfinite(slope) else None,
                "curve": {"indentation_m": significant(delta[keep]), "force_N": significant(f[keep])},
            }
        )
    if points:
        first, last = np.array(points[0]["position_m"]), np.array(points[-1]["position_m"])
        line = last - first
        e = line / np.linalg.norm(line) if np.linalg.norm(line) > 0 else np.zeros(3)
        for q in points:
            q["along_m"] = float(f"{float((np.array(q['position_m']) - first) @ e):.6g}")
        peaks = np.array([q["peak_force_N"] for q in points])
        i = int(np.argmax(peaks))
        stiffest = {
            "index": i,
            "along_m": points[i]["along_m"],
            "position_m": points[i]["position_m"],
            "peak_force_N": float(peaks[i]),
            "ratio_to_median": float(peaks[i] / np.median(peaks)) if np.median(peaks) > 0 else None,
        }
    else:
        stiffest = None
    return {"points": points, "stiffest": stiffest}


def plot_palpation(path, result: dict, *, title: str = "") -> None:
    """Write ``palpation.png``: left force-indentation per press, right peak force and slope along the line.

    Args:
        path: the PNG file.
        result: the ``"palpation"`` part of the summary (:func:`palpation` plus ``"tool"``).
        title: the figure's title.
    """
    from matplotlib import colormaps

    fig = figure(figsize=(11, 4.5))
    left, right = fig.subplots(1, 2)
    points = result["points"]
    cmap = colormaps["viridis"]
    for i, q in enumerate(points):
        colour = cmap(i / max(1, len(points) - 1))
        left.plot(
            np.array(q["curve"]["indentation_m"]) * 1e3,
            q["curve"]["force_N"],
            color=colour,
            lw=1.2,
            label=f"{q['along_m'] * 1e3:.1f} mm",
        )
    left.set_xlabel("indentation (mm)")
    left.set_ylabel("force (N)")
    left.set_title(f"force-indentation, {result['tool']}")
    left.grid(alpha=0.3)
    if points:
        left.legend(loc="upper left", fontsize="x-small", title="position", title_fontsize="x-small")
        along = np.array([q["along_m"] for q in points]) * 1e3
        peaks = np.array([q["peak_force_N"] for q in points])
        right.plot(along, peaks, "o-", color="tab:red", label="peak force")
        best = result["stiffest"]
        right.annotate(
            f"stiffest: {best['along_m'] * 1e3:.1f} mm",
            (best["along_m"] * 1e3, best["peak_force_N"]),
            textcoords="offset points",
            xytext=(8, -4),
            ha="left",
            fontsize="small",
        )
        right.margins(y=0.12)
        twin = right.twinx()
        slopes = [np.nan if q["stiffness_N_per_m"] is None else q["stiffness_N_per_m"] for q in points]
        twin.plot(along, slopes, "s--", color="tab:blue", label="slope")
        twin.set_ylabel("slope of the loading half (N/m)", color="tab:blue")
        right.legend(loc="upper left", fontsize="small")
        twin.legend(loc="upper right", fontsize="small")
    right.set_xlabel("position along the line of presses (mm)")
    right.set_ylabel("peak force (N)", color="tab:red")
    right.set_title("peak force along the line")
    right.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    save_figure(fig, path, dpi=100)
