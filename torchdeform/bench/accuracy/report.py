"""What ``torchdeform bench accuracy`` makes of its rows: the Pareto front, the recommendation, the text and the plot.

A row is on a scene's Pareto front when no other ``ok`` row of the scene is both faster and more
accurate (:func:`pareto_front`, :func:`mark_pareto`); the recommendation is, per scene and error
target, the fastest row that reaches the target (:func:`recommend`). :func:`static_orders` notes
the observed convergence order of the resolution sweep.
"""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path

from ...outputs import save_figure

__all__ = [
    "TARGETS",
    "pareto_front",
    "mark_pareto",
    "recommend",
    "recommendation_text",
    "report",
    "static_orders",
    "plot",
]

TARGETS = (1e-1, 1e-2, 1e-4)


def pareto_front(points) -> list[bool]:
    """Which points no other point beats on both coordinates.

    ``q`` dominates ``p`` when ``q <= p`` in both coordinates and ``q < p`` in at least one;
    points with a ``None`` or non-finite coordinate are never on the front and dominate nothing.

    Args:
        points: sequence of ``(error, time)`` pairs (any two "smaller is better" numbers).

    Returns:
        one bool per point, True on the front. ``O(P log P)``: sweep in order of time.
    """
    pts = [
        (i, p[0], p[1])
        for i, p in enumerate(points)
        if p[0] is not None and p[1] is not None and math.isfinite(p[0]) and math.isfinite(p[1])
    ]
    pts.sort(key=lambda q: (q[2], q[1]))
    front = [False] * len(points)
    best = math.inf  # smallest error among strictly faster points
    i = 0
    while i < len(pts):
        j = i
        while j < len(pts) and pts[j][2] == pts[i][2]:
            j += 1
        group_min = pts[i][1]  # the group is sorted by error
        if group_min < best:
            for idx, err, _ in pts[i:j]:
                front[idx] = err == group_min
        best = min(best, group_min)
        i = j
    return front


def mark_pareto(rows: list) -> None:
    """Set ``row["pareto"]`` per scene over the ``ok`` rows."""
    for scene in dict.fromkeys(r["scene"] for r in rows):
        sub = [r for r in rows if r["scene"] == scene and r["status"] == "ok"]
        for r, on in zip(sub, pareto_front([(r["error"], r["wall_s"]) for r in sub])):
            r["pareto"] = on


def recommend(rows: list, *, targets=TARGETS) -> list[dict]:
    """For each scene and error target, the fastest ``ok`` row whose error reaches it."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for target in targets:
            ok = [r for r in rows if r["scene"] == scene and r["status"] == "ok" and r["error"] <= target]
            best = min(ok, key=lambda r: r["wall_s"]) if ok else None
            out.append(
                dict(
                    scene=scene,
                    target=target,
                    method=best and best["method"],
                    param=best and best["param"],
                    dt=best and best["dt"],
                    steps=best and best["steps"],
                    error=best and best["error"],
                    wall_s=best and best["wall_s"],
                )
            )
    return out


def _fmt(x: float) -> str:
    """``1e-4`` rather than ``0.0001``."""
    m, e = f"{x:.0e}".split("e")
    return f"{x:g}" if 1e-2 <= x < 1e3 and float(m) != 1 else f"{m}e{int(e)}"


def recommendation_text(recs: list, *, targets=TARGETS) -> str:
    """The recommendation as printed: one line per scene, then the overall winner per target."""
    lines = ["recommendation (computed from the rows: fastest run reaching each error target):"]
    width = max(len(r["scene"]) for r in recs) if recs else 0
    for scene in dict.fromkeys(r["scene"] for r in recs):
        parts = []
        for r in (r for r in recs if r["scene"] == scene):
            if r["method"] is None:
                parts.append(f"<= {_fmt(r['target'])}: none reached")
            else:
                dt = "" if r["dt"] is None else f", dt {r['dt']:.2g} s"
                parts.append(f"<= {_fmt(r['target'])}: {r['method']} {r['param']}{dt} ({r['wall_s']:.2g} s)")
        lines.append(f"  {scene.ljust(width)}  " + "; ".join(parts))
    dyn = [r for r in recs if r["method"] not in (None, "static")]
    for target in targets:
        wins = {}
        for r in dyn:
            if r["target"] == target:
                wins[r["method"]] = wins.get(r["method"], 0) + 1
        if wins:
            ranked = ", ".join(
                f"{m} ({k} scene{'s' if k > 1 else ''})" for m, k in sorted(wins.items(), key=lambda kv: -kv[1])
            )
            lines.append(f"  error <= {_fmt(target)}: fastest is {ranked}")
    return "\n".join(lines)


def report(extra: dict) -> str:
    """The text after the table: references, methods, what was left out, the recommendation."""
    lines = [
        "",
        "error: " + extra["error"] + ".",
        "pareto *: no other run of the scene is both faster and more accurate.",
        "scaling: " + extra["scaling"] + ".",
        "",
        "references:",
    ]
    lines += [f"  {name}: {ref['text']}" for name, ref in extra["references"].items()]
    lines.append("methods:")
    lines += [f"  {name}: {text}" for name, text in extra["methods"].items()]
    for name, why in extra["skipped"].items():
        lines.append(f"  {name}: {why}")
    groups = {}
    for d in extra["not_run"]:
        groups.setdefault((d["scene"], d["reason"]), []).append(f"{d['method']} {d['param']}")
    if groups:
        lines.append("not run:")
        lines += [f"  {scene}: {', '.join(cases)} ({why})" for (scene, why), cases in groups.items()]
    lines += ["", recommendation_text(extra["recommendations"], targets=extra["targets"])]
    return "\n".join(lines)


def static_orders(rows: list) -> None:
    """Note the observed convergence order between successive resolutions of a static scene."""
    for scene in dict.fromkeys(r["scene"] for r in rows if r["method"] == "static"):
        sub = sorted(
            (r for r in rows if r["scene"] == scene and r["method"] == "static" and r["status"] == "ok"),
            key=lambda r: r["n"],
        )
        for a, b in pairwise(sub):
            if a["error"] > 0 and b["error"] > 0:
                order = math.log(a["error"] / b["error"]) / math.log((b["n"] - 1) / (a["n"] - 1))
                b["note"] = f"order {order:.2f} from n={a['n']}"


def plot(rows: list, path: Path, *, references: dict | None = None) -> None:
    """Log-log error against wall time.

    One panel per scene, one colour per method (points joined in order of dt, or n), the Pareto
    front as a black step line with ringed points, diverged runs as crosses along the top. ``rows``
    as returned by the bench; ``references`` names the reference in each panel's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colours = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(methods)}
    cols = min(3, max(1, len(scenes)))
    nrows = math.ceil(len(scenes) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.7 * nrows), squeeze=False)
    for ax in axes.flat[len(scenes) :]:
        ax.set_visible(False)
    handles = {}
    for ax, scene in zip(axes.flat, scenes):
        sub = [r for r in rows if r["scene"] == scene]
        ok = [r for r in sub if r["status"] == "ok" and r["error"] > 0]
        for m in methods:
            series = sorted((r for r in ok if r["method"] == m), key=lambda r: (r["dt"] or 0, r["n"] or 0))
            if series:
                (h,) = ax.plot(
                    [r["wall_s"] for r in series],
                    [r["error"] for r in series],
                    marker="o",
                    ms=4,
                    lw=1,
                    color=colours[m],
                    label=m,
                )
                handles[m] = h
        front = sorted((r["wall_s"], r["error"]) for r in ok if r["pareto"])
        if front:
            (h,) = ax.step(*zip(*front), where="post", color="k", lw=1, ls="--", label="Pareto front")
            ax.scatter(*zip(*front), s=70, facecolors="none", edgecolors="k", zorder=3)
            handles["Pareto front"] = h
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_formatter(NullFormatter())
        bad = [r for r in sub if r["status"] != "ok" and r["wall_s"]]
        if bad:
            top = ax.get_ylim()[1]
            for r in bad:
                ax.scatter([r["wall_s"]], [top], marker="x", color=colours[r["method"]], zorder=3)
            handles["diverged (drawn at the top)"] = ax.scatter([], [], marker="x", color="0.4")
            ax.set_ylim(top=top * 1.5)
        ref = (references or {}).get(scene, {})
        title = (
            scene
            if "method" not in ref
            else f"{scene}  (ref: {ref['method']}" + (f", n={ref['n']})" if ref.get("n") else ")")
        )
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("max position error / max displacement")
        ax.grid(True, which="major", alpha=0.3)
    fig.legend(
        list(handles.values()),
        list(handles),
        loc="lower right" if len(scenes) % cols else "upper right",
        fontsize=9,
        frameon=True,
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
