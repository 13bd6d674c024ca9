"""Parameter sweeps over a scene file: the Cartesian product of ``--set`` values, one row per point.

A *point* sets some dotted scene keys (``material.stiffness``, ``integrator.dt``, ...) to values;
every other key is the scene file's. Each point's scene is built (and so checked) before any
runs, then simulated; its row holds the values, the summary figures of the run and its wall
time. Finished points are recorded as they finish (one JSON line each in ``DIR/records/``), so a
rerun of the same sweep into the same folder runs only the missing ones (after a crash or a
preempted job).

**Batches.** Points whose scenes differ only in ``material.stiffness`` and ``material.damping``
(with a fixed ``integrator.dt``: ``"auto"`` follows the stiffness) run as one batched model: the
parameters stacked along the leading batch axis, one simulation for the batch (:func:`batches`,
at most ``batch`` points each). A batch that diverges runs again point by point, so that each
row says which point diverged. ``wall_s`` is the batch's wall time shared among its points.

Under ``torchrun`` the batches are spread over the ranks (batch ``j`` on rank ``j mod N``); the
rows are gathered to rank 0 with ``torch.distributed`` (gloo), which writes the table
(``sweep.csv``) and the plot (``sweep.png``). Each rank writes its own record file, so ``DIR``
must be on storage every rank sees for a resume across machines.

Figures per point: ``max_displacement_m`` and ``peak_displacement_m`` (largest node displacement
over the recorded frames, as in a run's ``summary.json``), ``max_free_displacement_m``,
``kinetic_J`` and ``total_J`` (final energies), ``steps``, ``dt_s``, ``engine``, ``batch`` (the
points simulated together), ``wall_s`` and ``status`` (``ok`` or the one-line divergence message).

Scenes with tools or topology changes are not swept yet (a clear error names them).

Examples:
    >>> from torchdeform.distributed.sweep import parse_set, product
    >>> parse_set("material.stiffness=1,2.5,4e3")
    ('material.stiffness', [1, 2.5, 4000.0])
    >>> product([("material.stiffness", [1, 2]), ("integrator.dt", [1e-4, 2e-4])])[1]
    {'material.stiffness': 1, 'integrator.dt': 0.0002}
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import time
from pathlib import Path

from ..checks import read_text
from ..errors import ConfigError, DivergenceError
from ..scene.commands import check_key  # shared with ``torchdeform run --set``
from ..scene.reader import parse_set, parse_value

__all__ = [
    "parse_set",
    "parse_value",
    "product",
    "read_points",
    "check_key",
    "point_scene",
    "run_point",
    "run_batch",
    "batches",
    "point_id",
    "done_points",
    "record",
    "write_table",
    "FIGURES",
    "BATCHED",
]

#: the summary figures of a point's row, after its values
FIGURES = (
    "status",
    "max_displacement_m",
    "peak_displacement_m",
    "max_free_displacement_m",
    "kinetic_J",
    "total_J",
    "steps",
    "dt_s",
    "engine",
    "batch",
    "wall_s",
)
#: the keys whose points run batched (stacked along the models' batch axis)
BATCHED = ("material.stiffness", "material.damping")


def product(sets: list) -> list:
    """The Cartesian product of ``[(key, values), ...]``: one dict per point, the last key varying fastest."""
    keys = [k for k, _ in sets]
    return [dict(zip(keys, combo)) for combo in itertools.product(*(v for _, v in sets))]


def read_points(path) -> list:
    """A list file of points: CSV, a header of dotted keys, one point per row (values as :func:`parse_value`)."""
    path = Path(path)
    with io.StringIO(read_text(path, "--points", what="CSV file"), newline="") as fh:
        rows = list(csv.reader(fh))
    rows = [r for r in rows if any(c.strip() for c in r)]
    if len(rows) < 2:
        raise ConfigError("--points", "a header of scene keys and at least one row", got=str(path))
    keys = [k.strip() for k in rows[0]]
    points = []
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(keys):
            raise ConfigError(
                f"--points line {n}", f"{len(keys)} values (one per key of the header)", got=",".join(row)
            )
        points.append({k: parse_value(v) for k, v in zip(keys, row)})
    return points


def point_id(values: dict) -> str:
    """The identity of a point: its values as canonical JSON (what resumes match on)."""
    return json.dumps(values, sort_keys=True)


def point_scene(src, data: dict, base: Path, name: str, values: dict):
    """The :class:`~torchdeform.scene.Scene` of ``data`` with ``values`` set (built, so checked).

    A bad value raises a :class:`ConfigError` naming ``--set KEY`` and the value.
    """
    from ..scene.commands import build_with_values
    from ..scene.mass_spring import mass_spring_scene
    from ..scene.reader import with_values

    scene = build_with_values(src, with_values(data, values), base, name, values, build=mass_spring_scene)
    if scene.tools is not None or scene.topology is not None:
        raise ConfigError(
            "sweep", "a scene without [[tools]], [strain_limit] or topology sections (not swept yet)", got=src.path
        )
    return scene


def run_point(scene, *, device=None) -> dict:
    """Simulate ``scene`` (no files written): the figures of :data:`FIGURES` (a batch of one)."""
    return run_batch([scene], device=device)[0]


def _figures(model, rec, final, b: int) -> dict:
    """The figures of batch entry ``b`` of a run of ``model`` (that entry's own, unbatched model)."""
    import torch

    from ..scene.run import energy_series

    x = torch.cat([rec["x"][:, b], final.x[b : b + 1].detach().cpu()])
    v = torch.cat([rec["v"][:, b], final.v[b : b + 1].detach().cpu()])
    series = energy_series(model, x, v)
    return dict(
        status="ok",
        max_displacement_m=float(series["max_displacement"].max()),
        peak_displacement_m=float(series["max_displacement"].max()),
        max_free_displacement_m=float(series["max_free_displacement"].max()),
        kinetic_J=float(series["kinetic"][-1]),
        total_J=float(series["total"][-1]),
    )


def batches(points: list, scenes: list, size: int) -> list:
    """Group point indices into batches of at most ``size``.

    A batch holds points equal but for :data:`BATCHED` keys, with a numeric ``dt``, in the order of
    their first point; every other point is a batch of its own.
    """
    groups, order = {}, []
    for i, (p, scene) in enumerate(zip(points, scenes)):
        if size > 1 and scene.dt != "auto":
            key = point_id({k: v for k, v in p.items() if k not in BATCHED})
        else:
            key = ("alone", i)
        if key not in groups or len(groups[key][-1]) >= size:
            groups.setdefault(key, []).append([])
            order.append(groups[key][-1])
        groups[key][-1].append(i)
    return order


def run_batch(scenes: list, *, device=None) -> list:
    """Simulate scenes that differ only in spring stiffness and damping as one batched model.

    Returns one row per scene (:data:`FIGURES`); a batch that diverges runs point by point.
    """
    import copy

    import torch

    from ..scene.run import scene_engine
    from ..sim.engine import simulate
    from ..sim.stability import time_step_bound

    models = [s.build(device=device) for s in scenes]
    model = models[0]
    if len(models) > 1:  # the spring parameters stacked along the batch axis
        model = copy.copy(model)
        shape = torch.broadcast_shapes(*(m.stiffness.shape for m in models))
        model.stiffness = torch.cat([m.stiffness.expand(shape) for m in models])
        if any(m.damping is not None for m in models):
            model.damping = torch.cat(
                [(torch.zeros_like(m.stiffness) if m.damping is None else m.damping).expand(shape) for m in models]
            )
    scene = scenes[0]
    dt = scene.time_step(min(time_step_bound(m, integrator=scene.integrator) for m in models))
    engine = scene_engine(scene, False)
    start = time.perf_counter()
    try:
        final, rec = simulate(
            model,
            model.rest_state(batch=len(models)),
            dt,
            scene.steps,
            integrator=scene.integrator,
            record_every=scene.frames_every,
            progress=False,
            warn=False,
            engine=engine,
        )
    except DivergenceError as e:
        if len(scenes) > 1:
            return [run_point(s, device=device) for s in scenes]
        row = dict.fromkeys(FIGURES)
        row.update(
            status=f"diverged: {str(e).splitlines()[0]}",
            steps=scene.steps,
            dt_s=dt,
            batch=1,
            wall_s=time.perf_counter() - start,
        )
        return [row]
    wall = (time.perf_counter() - start) / len(models)
    rows = []
    for b, m in enumerate(models):
        row = dict.fromkeys(FIGURES)
        row.update(
            _figures(m, rec, final, b), steps=scene.steps, dt_s=dt, engine=engine.ran, wall_s=wall, batch=len(models)
        )
        rows.append(row)
    return rows


def done_points(out: Path) -> dict:
    """The recorded points of a sweep folder: ``{point id: row}`` (every rank's record file)."""
    done = {}
    for path in sorted((out / "records").glob("rank*.jsonl")):
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:  # a line cut by a crash: that point runs again
                continue
            done[row["id"]] = row["row"]
    return done


def record(out: Path, rank: int, pid: str, row: dict) -> None:
    """Append one finished point to this rank's record file (flushed: a crash loses at most that line)."""
    path = out / "records" / f"rank{rank}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps({"id": pid, "row": row}) + "\n")
        fh.flush()


def write_table(out: Path, keys: list, rows: list) -> Path:
    """``out/sweep.csv``: one row per point (its values, then :data:`FIGURES`), written atomically."""
    path = out / "sweep.csv"
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=["point", *keys, *FIGURES])
        w.writeheader()
        for i, row in enumerate(rows):
            w.writerow({"point": i, **row})
    tmp.replace(path)
    return path


def plot(out: Path, keys: list, rows: list) -> Path | None:
    """``out/sweep.png``: the final displacement against the first numeric key (one line per other combination)."""
    numeric = [k for k in keys if all(isinstance(r[k], (int, float)) and not isinstance(r[k], bool) for r in rows)]
    if not numeric or not rows:
        return None
    from ..outputs import axes, save_plot

    xkey, others = numeric[0], [k for k in keys if k != numeric[0]]
    fig, ax = axes(figsize=(6.5, 4.5))
    groups = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in others), []).append(r)
    # more lines than the 10 colours of the cycle: the colours come from a colormap in the order of the
    # combinations (similar combinations, similar colours), and the marker changes too
    import matplotlib

    cmap = matplotlib.colormaps["viridis" if len(groups) > 10 else "tab10"]
    markers = "osD^v<>ph*"
    for n, (combo, sel) in enumerate(groups.items()):  # in the order of the points
        sel = sorted((r for r in sel if r["status"] == "ok"), key=lambda r: r[xkey])
        label = ", ".join(f"{k} = {v}" for k, v in zip(others, combo)) or None
        colour = cmap(n / max(1, len(groups) - 1)) if len(groups) > 10 else cmap(n % 10)
        ax.plot(
            [r[xkey] for r in sel],
            [r["max_displacement_m"] * 1e3 for r in sel],
            marker=markers[n % len(markers)],
            color=colour,
            label=label,
        )
    positive = all(r[xkey] > 0 for r in rows)
    if positive and max(r[xkey] for r in rows) > 10 * min(r[xkey] for r in rows):
        ax.set_xscale("log")
    ax.set_xlabel(xkey)
    ax.set_ylabel("final max displacement (mm)")
    ax.set_title(f"sweep: {len(rows)} points")
    ax.grid(True, which="both", alpha=0.3)
    if groups and any(c for c in groups):
        if len(groups) > 4:  # beside the plot, not over the lines
            fig.set_size_inches(6.5 + 3.2 * (1 + len(groups) // 24), 4.5)
            ax.legend(fontsize=7, ncol=1 + len(groups) // 24, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        else:
            ax.legend(fontsize=7)
    save_plot(fig, out, "sweep.png")
    return out / "sweep.png"
