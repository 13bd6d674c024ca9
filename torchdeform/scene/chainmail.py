"""ChainMail scenes (``model = "chainmail"`` in a scene file).

The ``[chainmail]`` section and the runner that moves the drag groups frame by frame, relaxes,
and writes the same outputs as a mass-spring run (``trajectory.npz``, ``summary.json``,
``energy.png``).
"""

from __future__ import annotations

import json
import time
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..chainmail import METHODS, RELAX_MODES, ChainMail, Limits, limit_violation, relax_energy, tissue_limits
from ..outputs import figure, manifest, save_figure
from ..sim.grid import Grid
from .reader import SECTIONS, Table, drags_section, faces, grid_section, node_list

__all__ = ["ChainMailScene", "chainmail_scene"]


@dataclass(eq=False)
class ChainMailScene:
    """A ChainMail scene (``model = "chainmail"`` in a scene file, see :func:`chainmail_scene`).

    Each of ``frames`` frames moves every drag group rigidly to its path's offset at the frame's
    time (``t`` from 0 to the last waypoint), then relaxes ``relax_steps`` times (drag groups and
    fixed elements held). :meth:`run` writes ``trajectory.npz``, ``summary.json`` and ``energy.png``.
    """

    grid: Grid
    limits: Limits
    _: KW_ONLY
    method: str = "gibson"
    fixed: torch.Tensor | None = None
    drags: list = field(default_factory=list)
    frames: int = 20
    relax_steps: int = 0
    relax_mode: str = "centroid"
    relax_moved_only: bool = False
    on_blocked: str = "scale"
    name: str = "chainmail"
    source: object = None

    def run(self, out_dir, *, progress: bool = True, device=None) -> dict:
        """Run the scene; returns the summary (also written to ``summary.json``).

        ``device`` is not used (the sequential ChainMail runs on the CPU).
        """
        out = Path(out_dir)
        cm = ChainMail(self.grid, self.limits, fixed=self.fixed, method=self.method)
        end = max((float(d.path[-1][0]) for d in self.drags), default=0.0)
        times = np.linspace(0.0, end, self.frames + 1)
        hold = torch.zeros(self.grid.shape, dtype=torch.bool)
        groups = []
        for d in self.drags:
            m = torch.as_tensor(d.nodes, dtype=torch.bool)
            hold |= m
            idx = [tuple(int(v) for v in r) for r in m.nonzero()]
            groups.append((d, idx))
        X = self.grid.rest_positions(dtype=torch.float64)
        frames = [X[0].float().numpy()]
        energy, violation, moved, fraction = [0.0], [0.0], [0], [1.0]
        start = time.perf_counter()
        for t in tqdm(times[1:], desc=self.name, unit="frame", disable=not progress, leave=False):
            n_moved, frac = 0, 1.0
            for d, idx in groups:
                target = np.asarray(d.offset(float(t)), dtype=np.float64)
                current = cm.displacement(dtype=torch.float64)[0][(slice(None),) + idx[0]].numpy()
                delta = target - current
                if np.any(delta != 0):
                    r = cm.move(idx, delta, on_blocked=self.on_blocked)
                    n_moved, frac = n_moved + r.moved, min(frac, r.fraction)
            if self.relax_steps:
                cm.relax(steps=self.relax_steps, mode=self.relax_mode, only_moved=self.relax_moved_only, hold=hold)
            x = cm.positions()
            frames.append(x[0].float().numpy())
            energy.append(float(relax_energy(x, self.grid, limits=self.limits, mode=self.relax_mode)[0]))
            violation.append(float(limit_violation(x, self.grid, self.limits)[0]))
            moved.append(n_moved)
            fraction.append(frac)
        wall = time.perf_counter() - start
        x = np.stack(frames)
        disp = np.linalg.norm(x - X[0].float().numpy()[None], axis=1).reshape(len(x), -1).max(1)
        g = self.grid
        np.savez(
            out / "trajectory.npz",
            t=times,
            x=x,
            X=X[0].float().numpy(),
            node_mask=g.nodes().numpy(),
            shape=np.array(g.shape),
            spacing=np.array(g.spacing),
            origin=np.array(g.origin),
            model="chainmail",
            method=self.method,
            energy=np.array(energy),
            max_displacement=disp,
            max_violation=np.array(violation),
            moved=np.array(moved),
            fraction=np.array(fraction),
        )
        dt = float(times[1] - times[0]) if len(times) > 1 else 0.0
        summary = {
            "name": self.name,
            "scene": getattr(self.source, "path", None),
            "model": "chainmail",
            "integrator": {
                "name": f"chainmail-{self.method}",
                "relax_steps": self.relax_steps,
                "relax_mode": self.relax_mode,
            },
            "steps": self.frames,
            "dt_s": dt,
            "dt_auto": False,
            "simulated_time_s": float(times[-1]),
            "time_step_bound_s": None,
            "stability_bound_method": "none: ChainMail is geometric",
            "wall_time_s": wall,
            "steps_per_s": self.frames / wall if wall > 0 else None,
            "nodes": g.num_nodes,
            "grid": {"shape": list(g.shape), "spacing": list(g.spacing), "origin": list(g.origin), "topology": 6},
            "frames": len(times),
            "max_displacement_m": float(disp.max()),  # the peak over the run
            "final_displacement_m": float(disp[-1]),
            "peak_displacement_m": float(disp.max()),
            "max_violation_m": float(max(violation)),
            "blocked_frames": int(sum(f < 1.0 for f in fraction)),
            "final_relax_energy_m2": energy[-1],
        }
        _plot_scene(out / "energy.png", times, energy, disp, f"{self.name}: ChainMail ({self.method})")
        summary["outputs"] = manifest(out)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary


def _plot_scene(path, t, energy, disp, title):
    fig = figure(figsize=(7, 5))
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(t, energy, marker=".")
    top.set_ylabel("relaxation energy (m^2)")
    top.set_title(title)
    top.grid(alpha=0.3)
    bottom.plot(t, np.asarray(disp) * 1e3, color="k", marker=".")
    bottom.set_ylabel("max displacement (mm)")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    save_figure(fig, path, dpi=100)


def chainmail_scene(src, data: dict, base, *, name: str = "chainmail") -> ChainMailScene:
    """Build a :class:`ChainMailScene` from a parsed scene file with ``model = "chainmail"``.

    Called by :func:`torchdeform.scene.load_scene`. ``[chainmail]`` keys: ``method``
    (``"gibson"`` default, or ``"enhanced"``); the limits as ratios of the spacing
    ``compression`` (0.9), ``stretch`` (1.1), ``shear`` (0.1), or
    ``tissue`` (a name of the fuzzy tissue library or a consistency 0..10) with
    ``reference_stress`` (Pa, 300); ``frames`` (20); ``relax_steps`` (0), ``relax_mode``
    (``"centroid"`` or ``"goal"``), ``relax_moved_only`` (false); ``on_blocked`` (``"scale"``
    or ``"error"``). ``[grid]`` as for mass-spring scenes (the topology is ignored: ChainMail
    links face neighbours); ``[boundary]`` ``fixed`` and ``fixed_nodes``; ``[[drags]]`` the
    picked groups and their paths; ``[output]`` ``name``.
    """
    unused = [k for k in data if k not in ("model", "grid", "chainmail", "boundary", "drags", "output")]
    if unused:
        raise src.error(unused[0], 'no such section in a scene with model = "chainmail"', got=unused[0])
    grid = grid_section(Table(src, "grid", data["grid"], SECTIONS["grid"]), base)
    t = Table(src, "chainmail", data["chainmail"], SECTIONS["chainmail"])
    method = t.text("method", '"gibson" or "enhanced"', default="gibson", choices=METHODS)
    if t.has("tissue"):
        for k in ("compression", "stretch", "shear"):
            t.only_with(k, "tissue")
        tissue = t.raw("tissue", "a tissue name or a consistency value in [0, 10]")
        with src.located(t.key("tissue")):
            limits = tissue_limits(
                grid,
                tissue,
                reference_stress=t.num(
                    "reference_stress", "a positive stress in Pa", default=300.0, lo=0, lo_open=True
                ),
            )
    else:
        t.only_with("reference_stress", "compression")
        comp = t.num(
            "compression", "a ratio in (0, 1] (minimum distance / spacing)", default=0.9, lo=0, hi=1, lo_open=True
        )
        stretch = t.num("stretch", "a ratio >= 1 (maximum distance / spacing)", default=1.1, lo=1)
        shear = t.num("shear", "a ratio >= 0 (shear limit / spacing)", default=0.1, lo=0)
        with src.located(t.name):
            limits = Limits.from_material(grid, compression=comp, stretch=stretch, shear=shear)
    fixed = None
    if "boundary" in data:
        b = Table(src, "boundary", data["boundary"], ("fixed", "fixed_nodes"))
        if b.has("fixed"):
            fixed = faces(b, "fixed", grid)
        if b.has("fixed_nodes"):
            nodes = node_list(b, "fixed_nodes", grid)
            fixed = nodes if fixed is None else fixed | nodes
    drags = drags_section(src, data["drags"], grid) if "drags" in data else []
    out = Table(src, "output", data.get("output", {}), ("name",))
    scene = ChainMailScene(
        grid,
        limits,
        method=method,
        fixed=fixed,
        drags=drags,
        frames=t.integer("frames", "an integer >= 1 (moves along the drag paths)", default=20, lo=1),
        relax_steps=t.integer("relax_steps", "an integer >= 0", default=0),
        relax_mode=t.text("relax_mode", '"centroid" or "goal"', default="centroid", choices=RELAX_MODES),
        relax_moved_only=t.flag("relax_moved_only", default=False),
        on_blocked=t.text("on_blocked", '"scale" or "error"', default="scale", choices=("scale", "error")),
        name=out.text("name", "a string", default=name),
        source=src,
    )
    if fixed is not None:
        for n, d in enumerate(drags):
            if bool((torch.as_tensor(d.nodes, dtype=torch.bool) & fixed).any()):
                raise src.error(f"drags[{n}].nodes", "free elements (a dragged element is fixed)")
    with src.located(t.name):
        ChainMail(grid, limits, fixed=fixed, method=method)  # checks method, node mask, rest state
    return scene
