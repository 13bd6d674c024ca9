"""Loading and running scenes.

:func:`load_scene` (any model kind), :func:`run_scene` (writes ``trajectory.npz``,
``summary.json``, ``energy.png`` and, with a ``[volume]`` section, the deformed volume and its
renders), and the pieces the command line shows.
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from ..errors import TorchdeformError
from ..interact.tools import length
from ..options import one_line_warnings
from ..outputs import RunFolder, manifest, require_finite, save_figure, summary_json
from ..sim.engine import Engine, simulate
from ..sim.model import Model, State
from ..sim.stability import check_dt, time_step_bound
from ..sim.static import solve_static
from ..sim.threads import CpuSampler, after_step_threads, omp_threads, setup_threads
from .bodies import BodiesScene, bodies_report, bodies_scene, read_scene
from .chainmail import ChainMailScene, chainmail_scene
from .mass_spring import EXPLICIT, Scene, StaticSolve, StaticSolveError, mass_spring_scene
from .reader import volume_path
from .tools import ToolRecorder, support_series, tool_forces_at, tool_outputs

__all__ = [
    "load_scene",
    "run_scene",
    "energy_series",
    "plot_energy",
    "one_line_warnings",
    "report",
    "scene_volume_outputs",
    "scene_texture",
    "scene_texture_outputs",
    "scene_animation",
    "scene_engine",
    "settle_state",
]


def load_scene(path, *, surfaces: bool = False) -> Scene | ChainMailScene | BodiesScene:
    """Read a TOML scene file (see :mod:`torchdeform.scene` for its keys).

    The result is a :class:`Scene` (mass-spring, the default) or a :class:`ChainMailScene`
    (``model = "chainmail"``), or a :class:`~torchdeform.scene.bodies.BodiesScene` (``[[bodies]]``:
    several bodies, :mod:`torchdeform.scene.bodies`). The model is built once (on the CPU) to check
    every value.

    Args:
        path: the scene file (.toml); relative paths in it (mesh, volume) start from its folder.
        surfaces: make a body of labels' smooth surfaces (``scene.embedded``) even when the scene
            neither writes nor animates them (the viewer shows them).

    Raises:
        ConfigError: naming the file, the line (best effort), the dotted key and what was
            expected: syntax errors, unknown keys, wrong types, missing sections or keys, bad
            values, a missing or open mesh.

    Examples:
        >>> import torchdeform as td
        >>> path = getfixture("tmp_path") / "cube.toml"
        >>> _ = path.write_text('''
        ... [grid]
        ... shape = [4, 4, 6]
        ... spacing = 0.01
        ... [material]
        ... stiffness = 50.0
        ... [mass]
        ... density = 1000.0
        ... [boundary]
        ... fixed = "bottom"
        ... [integrator]
        ... name = "implicit"
        ... dt = 0.01
        ... steps = 10
        ... ''')
        >>> scene = td.load_scene(path)
        >>> scene.grid.shape, scene.integrator.name, scene.dt, scene.name
        ((4, 4, 6), 'implicit', 0.01, 'cube')
        >>> _ = path.write_text(path.read_text().replace("dt = 0.01", "dt = -1"))
        >>> try:
        ...     td.load_scene(path)
        ... except td.ConfigError as e:
        ...     print(e.key, "on line", e.line)
        integrator.dt on line 13
    """
    src, data = read_scene(path)
    base, name = Path(path).parent, Path(path).stem
    if "bodies" in data:
        return bodies_scene(src, data, base, name=name)
    if data.get("model") == "chainmail":
        return chainmail_scene(src, data, base, name=name)
    return mass_spring_scene(src, data, base, name=name, surfaces=surfaces)


def energy_series(model: Model, x: torch.Tensor, v: torch.Tensor, *, nodes_per_call: int = 1 << 16) -> dict:
    """Energies and largest displacement of recorded frames.

    Frames are evaluated a batch at a time, each batch of about ``nodes_per_call`` nodes. Batches of a
    small body run on one OpenMP thread: their work is too small to share, and two threads beside a
    busy process took 4-10 times longer than one (335 frames of 11^3 nodes: 0.04 s on one thread,
    0.14-0.4 s on two beside a busy process, 0.22 s frame by frame).

    Args:
        model: the :class:`~torchdeform.sim.model.Model` of the run.
        x: positions of the frames, ``(T, 3, D, H, W)`` (any device).
        v: velocities of the frames, ``(T, 3, D, H, W)``.
        nodes_per_call: nodes evaluated together (frames per batch: this over the body's nodes, at least 1).

    Returns:
        dict of ``(T,)`` float64 numpy arrays: ``kinetic``, ``elastic``, ``gravity`` (if the
        model has gravity), ``total`` (J), ``max_displacement`` (m, largest ``|x - X|``) and
        ``max_free_displacement`` (m, the same over nodes that are neither fixed nor dragged).

    Example:
        >>> import torch, torchdeform as td
        >>> m = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, density=1000.0)
        >>> x = m.X.expand(4, -1, -1, -1, -1).clone()
        >>> s = energy_series(m, x, torch.zeros_like(x))
        >>> s["total"].shape, float(s["total"].max())
        ((4,), 0.0)
    """
    out = {}
    free = ~model.constrained.view(1, *model.grid.shape)
    size = model.grid.num_nodes
    chunk = max(1, nodes_per_call // size)
    small = size <= nodes_per_call and model.device.type == "cpu"
    with torch.no_grad(), omp_threads(1 if small else torch.get_num_threads()):
        for a in range(0, len(x), chunk):
            xc = x[a : a + chunk].to(model.device, model.dtype)
            vc = v[a : a + chunk].to(model.device, model.dtype)
            terms = model.energy(State(xc, vc))
            u = length(xc - model.X)[:, 0]  # (T, D, H, W); Tensor.norm over 3 channels: 20x slower
            terms["max_displacement"] = u.flatten(1).amax(1)
            terms["max_free_displacement"] = (u * free).flatten(1).amax(1)
            for k, val in terms.items():
                out.setdefault(k, []).append(val.double().cpu())
    return {k: torch.cat(v).numpy() for k, v in out.items()}


def plot_energy(path, t: np.ndarray, series: dict, *, title: str = "") -> None:
    """Write a PNG: energies (J) and largest displacement (mm) over time (s)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    # fixed margins: a constrained layout draws the figure twice and doubled the plot's 0.15 s
    fig = Figure(figsize=(7, 6))
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True)
    fig.subplots_adjust(left=0.12, right=0.97, top=0.94, bottom=0.08, hspace=0.08)
    for k in ("kinetic", "elastic", "gravity", "total"):
        if k in series:
            top.plot(t, series[k], label=k, lw=2 if k == "total" else 1.2)
    top.set_ylabel("energy (J)")
    top.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3))  # short tick labels within the margin
    top.legend(loc="best", fontsize="small")
    top.grid(alpha=0.3)
    top.set_title(title)
    bottom.plot(t, series["max_displacement"] * 1e3, color="k", label="all nodes")
    bottom.plot(
        t, series["max_free_displacement"] * 1e3, color="tab:blue", ls="--", label="free nodes (not fixed or dragged)"
    )
    bottom.legend(loc="best", fontsize="small")
    bottom.set_ylabel("max displacement (mm)")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    save_figure(fig, path, dpi=100)


def _bound_method(name: str) -> str:
    if name == "implicit":
        return "none: implicit Euler is unconditionally stable"
    if name == "knoche":
        return "none: relaxation, dt only advances the clock"
    return "power iteration on the spring stencil (linearised at rest)"


def run_scene(
    scene: Scene | ChainMailScene | BodiesScene, out_dir, *, progress: bool = True, device=None, force: bool = False
) -> dict:
    """Run a scene and write ``trajectory.npz``, ``summary.json`` and ``energy.png`` to ``out_dir``.

    The outputs are written whole or not at all (:class:`~torchdeform.outputs.RunFolder`): they are
    staged and moved into ``out_dir`` when the run ends well; ``summary.json`` lists them
    (``"outputs"``), and files of an earlier run into the same folder that this run did not write
    are removed. A run that fails (bad input, divergence, a full disk) leaves ``out_dir`` as it was.

    ``trajectory.npz``: ``t`` ``(T,)`` s (float64), ``x``, ``v`` ``(T, 3, D, H, W)`` (float32),
    rest positions ``X`` ``(3, D, H, W)``, ``node_mask`` ``(D, H, W)``, ``shape``, ``spacing``,
    ``origin``, ``topology``, ``dt``, ``integrator``, and the series of :func:`energy_series`
    (``kinetic``, ``elastic``, ``gravity``, ``total``, ``max_displacement``,
    ``max_free_displacement``, each ``(T,)``). The last frame is always the final state.

    A scene with tools (``scene.tools``) runs fresh contacts and grasps built from it, records every
    step's tool readings and also writes ``tools.npz``, ``forces.png``, the ``"tools"`` and
    ``"support_reaction_N"`` parts of ``summary.json`` and, with ``[output] palpation``,
    ``palpation.png`` (see :mod:`torchdeform.scene.tools`). A scene with topology changes
    (``scene.topology``) applies them between steps to a copy of the model and also writes
    ``topology.png``, the surfaces asked for (``.ply``) and the ``"topology"`` part of ``summary.json``
    (see :mod:`torchdeform.scene.topology`). ``scene.threads`` sets torch's CPU threads for the run.

    Args:
        scene: a :class:`Scene` (:func:`load_scene`, :func:`demo_scene` or your own).
        out_dir: output folder (created). It must be empty, hold an earlier run's outputs, or
            ``force`` must be set.
        progress: show a progress bar.
        device: run on this device instead of the scene's.
        force: write into a folder that holds other files (they are left alone).

    Returns:
        the summary (also written to ``summary.json``).

    Raises:
        DivergenceError: the run became unstable (naming step and a safe dt).

    Examples:
        >>> import json
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01)
        >>> scene = td.Scene(grid, dict(stiffness=50.0, damping=0.1, density=1000.0, gravity=(-9.81, 0, 0),
        ...                             fixed=grid.face("bottom")), steps=40, record_every=10, name="cube")
        >>> out = getfixture("tmp_path")
        >>> summary = td.run_scene(scene, out, progress=False)
        >>> summary["steps"], summary["frames"], summary["nodes"], summary["max_displacement_m"] > 0
        (40, 5, 64, True)
        >>> sorted(p.name for p in out.iterdir())
        ['energy.png', 'summary.json', 'trajectory.npz']
        >>> json.loads((out / "summary.json").read_text())["outputs"]
        ['energy.png', 'summary.json', 'trajectory.npz']
        >>> json.loads((out / "summary.json").read_text())["name"]
        'cube'
    """
    if not isinstance(scene, Scene):  # a ChainMail scene, or one of several bodies, runs itself
        with RunFolder(out_dir, force=force) as stage:
            return scene.run(stage, progress=progress, device=device)
    threads = torch.get_num_threads()
    if scene.threads:
        torch.set_num_threads(scene.threads)
    try:
        with RunFolder(out_dir, force=force) as stage:
            return _run(scene, stage, progress, device)
    finally:
        torch.set_num_threads(threads)


#: the spring fields a packed step shares with a scene's model under topology changes: all three,
#: as :meth:`~torchdeform.scene.topology.TopologySet.prepare` stores them per spring (a cut zeroes the
#: damping of what it removes, a gaping cut and coagulation change rest lengths, coagulation the damping)
TOPOLOGY_FIELDS = ("stiffness", "rest_length", "damping")


def scene_engine(scene: Scene, topology: bool) -> Engine:
    """The scene's :class:`~torchdeform.sim.engine.Engine`.

    With topology changes a packed step shares the model's node and spring fields (``editable``,
    :data:`TOPOLOGY_FIELDS`): a cut, tear, cautery or coagulation between steps edits the tensors
    the step reads, with no repacking or recompilation.
    """
    return Engine(mode=scene.engine, editable=TOPOLOGY_FIELDS if topology else False)


def _run(scene: Scene, out: Path, progress: bool, device) -> dict:
    """:func:`run_scene` of a mass-spring scene, with the scene's threads set."""
    if isinstance(scene.integrator, StaticSolve):
        return _run_static(scene, out, device)
    with omp_threads(setup_threads()):  # beside a busy process on one thread: its bound took 4 s on two
        model = scene.build(device=device)
        recorder = None
        if scene.tools is not None:  # fresh contacts and grasps: they keep state
            model = copy.copy(model)
            model.interactions = scene.tools.interactions()
            if scene.tools.tools:
                recorder = ToolRecorder(scene.tools.names, scene.steps, model.device, model.dtype)
        integrator = scene.integrator
        bound = time_step_bound(model, integrator=integrator)
        dt = scene.time_step(bound)
        if integrator.name in EXPLICIT:
            check_dt(model, dt, integrator, bound=bound)
        state = model.rest_state()
        settled = None
        if scene.settle:
            state, settled = settle_state(scene, model, dt)
    callback, events = recorder, None
    if scene.topology is not None:  # topology changes edit a copy of the model
        if scene.topology.checked_end is None:  # dt = "auto": the run's length is known now
            scene.topology.check(scene.steps * dt)
        model = scene.topology.prepare(model)
        embedded = embedded_surfaces(scene, model.grid, dtype=model.dtype) if scene.embedded else None  # cut with it
        events = scene.topology.events(
            model, dt, scene.steps * dt, out_dir=out, embedded=embedded, every=scene.frames_every
        )

    engine = scene_engine(scene, events is not None)
    start, cpu = time.perf_counter(), CpuSampler()  # how busy the machine is, measured over the run
    energies = None
    if events is not None:
        events.begin(state)
        # the springs change during the run: each frame's energies with the springs it was stepped with
        first = model.start(state)  # the recorded start: dragged nodes moving
        energies = [energy_series(model, first.x[:1], first.v[:1])]

        def frame_energy(step, st):
            if step % scene.frames_every == 0:
                energies.append(energy_series(model, st.x[:1], st.v[:1]))

        callback = _chain(recorder, frame_energy, events)
    final, rec = simulate(
        model,
        state,
        dt,
        scene.steps,
        integrator=integrator,
        record_every=scene.frames_every,
        progress=progress,
        warn=False,
        callback=callback,
        engine=engine,
    )
    wall = time.perf_counter() - start
    # outputs beside a busy process: one thread (run_scene restores)
    torch.set_num_threads(after_step_threads(since=cpu))
    series = None
    if energies is not None:
        if scene.steps % scene.frames_every:  # the final frame, appended by run_outputs
            energies.append(energy_series(model, final.x[:1], final.v[:1]))
        series = {k: np.concatenate([e[k] for e in energies]) for k in energies[0]}

    summary, (t, x, v, series) = run_outputs(
        scene, model, integrator, dt, bound, final, rec, wall, engine.summary(), out, series
    )
    if settled is not None:
        summary["settle"] = settled
    if recorder is not None:
        assert scene.tools is not None  # the recorder records the scene's tools
        summary.update(
            tool_outputs(
                scene.tools,
                recorder.series(),
                (t, support_series(model, t, x, v)),
                out,
                title=f"{scene.name}: {integrator.name}, dt = {dt:.3g} s",
            )
        )
    if events is not None:
        summary["topology"] = events.outputs(final, out, title=f"{scene.name}: {integrator.name}, dt = {dt:.3g} s")
    texture = _final_state_outputs(scene, model, final, out, summary, None if events is None else events.pieces())
    if scene.camera_view is not None:
        summary["camera"] = _endoscope_outputs(scene, model, t, x, out, progress)
    versions = events.embedded_versions if events is not None else None
    surfaces = embedded_outputs(scene, model.grid, t, x, out, summary, versions=versions) if scene.embedded else None
    if scene.animation:
        labels = events.pieces() if events is not None else None
        tools = None if recorder is None else recorder.series()
        summary["animation"] = scene_animation(
            scene,
            model,
            t,
            x,
            v,
            out,
            labels=labels,
            tools=tools,
            texture=texture,
            progress=progress,
            surfaces=surfaces,
        )
    finish_outputs(summary, out, t, series, f"{scene.name}: {integrator.name}, dt = {dt:.3g} s")
    return summary


#: seconds of damped settling for ``settle = true`` where the static solve does not converge
SETTLE_TIME = 0.2


def settle_state(scene: Scene, model: Model, dt: float) -> tuple:
    """The state a run with ``[integrator] settle`` starts from: the body at rest under gravity alone.

    Loads and tools are left out (they start with the run); fixed and dragged nodes stay where they
    are at ``t = 0``. The static solve (:func:`~torchdeform.sim.static.solve_static`, float64, relative
    residual 1e-6) gives the equilibrium; where it does not converge (a body that is not held, a term
    it does not support), damped steps of the scene's integrator and ``dt`` do, for ``settle`` seconds
    (``SETTLE_TIME`` for ``true``) with a velocity decay of 20 / that time. Velocities are then zero
    and the time 0.

    Returns:
        ``(state, info)``: the start state and ``{"method": "static" | "steps", ...}`` for ``summary.json``.
    """
    args = {**scene.model_args, "loads": None, "interactions": None}
    rest = model.rest_state()
    start = time.perf_counter()
    info: dict = {}
    x = None
    held = any(args.get(k) is not None for k in ("fixed", "home", "anchors")) or bool(args.get("drags"))
    try:
        if not held:  # nothing holds the body: it falls, there is no equilibrium to solve for
            raise TorchdeformError("a body held by nothing has no static equilibrium")
        body = Model(scene.grid, **args, dtype=torch.float64, device=model.device)
        eq, res = solve_static(
            body, state=State(body.X.clone(), torch.zeros_like(body.X), t=0.0), tol=1e-6, max_iter=30
        )
        if res["converged"] and bool(torch.isfinite(eq.x).all()):
            x = eq.x.to(model.dtype)
            info = {"method": "static", "residual": res["residual"], "iterations": res["iterations"]}
    except TorchdeformError:
        x = None
    if x is None:
        seconds = SETTLE_TIME if scene.settle is True else float(scene.settle)
        decay = max(float(args.get("decay") or 0.0), 20.0 / seconds)
        body = Model(scene.grid, **{**args, "decay": decay}, dtype=model.dtype, device=model.device)
        end, _ = simulate(body, rest, dt, None, duration=seconds, integrator=scene.integrator, warn=False)
        x = end.x.detach()
        info = {"method": "steps", "time_s": seconds, "decay_per_s": decay}
    info["wall_time_s"] = time.perf_counter() - start
    return model.start(State(x, torch.zeros_like(x), t=0.0)), info


def embedded_surfaces(scene: Scene, grid, *, dtype=torch.float32, device=None) -> dict:
    """The scene's embedded surfaces on the run's lattice, ``{name: EmbeddedSurface}`` (``dtype``, ``device``)."""
    from ..mesh.embed import EmbeddedSurface

    assert scene.embedded is not None
    return {name: EmbeddedSurface(v, f, grid, dtype=dtype, device=device) for name, (v, f) in scene.embedded.items()}


def embedded_outputs(scene: Scene, grid, t, x, out: Path, summary: dict, *, versions: list | None = None):
    """The scene's embedded surfaces on the run's lattice; with ``write_surfaces``, one file per recorded frame.

    Writes ``surfaces/frame_NNNN.glb`` (or ``.ply``): every surface at frame ``NNNN`` of
    ``trajectory.npz`` (:func:`~torchdeform.mesh.embed.save_surfaces`), and adds ``"embedded_surfaces"``
    to the summary (names, vertices, triangles, frames, format, seconds; after cuts also ``cut_at_s``,
    the times the cuts changed them, and ``after_cuts``, their final vertices and triangles).

    Args:
        scene: the :class:`Scene` (its ``embedded`` surfaces, ``write_surfaces``, ``surface_format``).
        grid: the run's grid.
        t: frame times ``(T,)`` (s).
        x: node positions of the frames ``(T, 3, D, H, W)`` (m).
        out: the output folder.
        summary: the run's summary (gets ``"embedded_surfaces"``).
        versions: the surfaces of a run whose cuts cut them,
            :attr:`~torchdeform.scene.topology.TopologyEvents.embedded_versions` (``[(t, {name:
            surface})]``, the first at the start); each frame shows the last version cut at or
            before its time. None or empty: the scene's surfaces, uncut.

    Returns:
        the :class:`~torchdeform.mesh.embed.EmbeddedSurface` s (for the animation): a list, or after
        cuts a function of the frame index giving that frame's list.
    """
    from ..mesh.embed import save_surfaces

    start = time.perf_counter()
    if not versions:
        versions = [(None, embedded_surfaces(scene, grid, dtype=x.dtype))]
    first, last = versions[0][1], versions[-1][1]
    info: dict = {
        "surfaces": {n: {"vertices": s.num_vertices, "triangles": s.num_faces} for n, s in first.items()},
        "frames": 0,
        "format": scene.surface_format,
    }
    if len(versions) > 1:
        info["cut_at_s"] = [tv for tv, _ in versions[1:]]
        info["after_cuts"] = {n: {"vertices": s.num_vertices, "triangles": s.num_faces} for n, s in last.items()}
    times = np.array([-np.inf] + [tv for tv, _ in versions[1:]])

    def at(i: int) -> dict:  # the surfaces of frame i: cut by everything applied by its time
        tol = 1e-9 * max(1.0, abs(float(t[i])))
        return versions[int(np.searchsorted(times, float(t[i]) + tol, side="right")) - 1][1]

    if scene.write_surfaces:
        folder = out / "surfaces"
        folder.mkdir(exist_ok=True)
        for i in range(len(t)):
            save_surfaces(folder / f"frame_{i:04d}.{scene.surface_format}", at(i), x[i])
        info["frames"] = len(t)
    info["wall_time_s"] = time.perf_counter() - start
    summary["embedded_surfaces"] = info
    if len(versions) == 1:
        return list(first.values())
    return lambda i: list(at(i).values())


def _final_state_outputs(scene: Scene, model: Model, final: State, out: Path, summary: dict, pieces=None):
    """The texture and volume outputs of the final state (``[texture]``, ``[volume]``); the texture or None.

    ``pieces``: the labels ``(D, H, W)`` of a cut body's pieces, or None (one piece).
    """
    grid = model.grid
    texture = None
    if scene.texture:
        texture, seams = scene_texture(scene.texture, grid)
        labels = pieces if pieces is not None else torch.where(grid.nodes(), 0, -1)
        summary["texture"] = scene_texture_outputs(texture, grid, final.x[:1], labels, out)
        summary["texture"]["seams"] = seams
    if scene.volume:
        spec = dict(scene.volume)
        cut = None if pieces is None else (grid, pieces)  # a cut body: a carved render
        summary["volume"] = scene_volume_outputs(
            spec.pop("file"), final.x[:1], model.X, grid.spacing, out, cut=cut, **spec
        )
    return texture


def _endoscope_outputs(scene: Scene, model: Model, t, x, out: Path, progress: bool) -> dict:
    """``[camera]``: the endoscope's view of the deformed ``[volume]`` at the recorded frames (:mod:`.camera`)."""
    from .camera import load_scene_endoscope, scene_endoscope

    meshes = embedded_surfaces(scene, model.grid, dtype=torch.float64) if scene.embedded else None
    rig = load_scene_endoscope(scene, meshes=meshes)
    assert rig is not None  # the scene has a [camera]
    return scene_endoscope(rig, t, x, model.X, out, progress=progress)


def _run_static(scene: Scene, out: Path, device) -> dict:
    """:func:`run_scene` of a scene whose integrator is a :class:`StaticSolve`: one static solve.

    Writes what a run writes for its final state: ``trajectory.npz`` with two frames (the rest state
    and the equilibrium, both at the solve's time, velocities zero), ``summary.json`` (with a
    ``"static"`` part: residual, convergence, iterations), ``energy.png`` and the ``[volume]`` and
    ``[texture]`` outputs. A solve that does not converge raises :class:`StaticSolveError` before
    anything is written.
    """
    model = scene.build(device=device)
    solve = cast(StaticSolve, scene.integrator)
    t = float(solve.time or 0.0)
    tol = solve.tolerance(model.dtype)
    rest = model.rest_state()
    start = time.perf_counter()
    final, info = solve_static(
        model,
        state=State(rest.x, rest.v, t=t),
        tol=tol,
        max_iter=solve.max_iter,
        cg_iters=solve.cg_iters,
        cg_tol=solve.cg_tol,
    )
    wall = time.perf_counter() - start
    if not info["converged"] or not bool(torch.isfinite(final.x).all()):
        key = "integrator.max_iter" if math.isfinite(info["residual"]) else "integrator.tol"
        line = scene.source.line_of(key) or scene.source.line_of("integrator") if scene.source.path else None
        where = f"{scene.source.path}:{line}: " if scene.source.path and line else ""
        raise StaticSolveError(
            f"{where}{key}: the static solve did not converge: relative residual {info['residual']:.3g} > tol "
            f"{tol:.3g} after {info['iterations']} Newton iterations (max_iter = {solve.max_iter}); raise "
            "max_iter or tol, or hold the body (fixed nodes, home springs) so that it has one equilibrium; "
            "nothing was written"
        )
    rec = {
        "t": torch.tensor([t, t], dtype=torch.float64),
        "x": torch.stack([rest.x, final.x]).detach().cpu(),
        "v": torch.zeros((2, *final.x.shape), dtype=final.x.dtype),
    }
    engine = {"requested": "static", "ran": "static", "why": "a static solve: Newton iterations, eager"}
    summary, (t_rec, _, _, series) = run_outputs(scene, model, solve, 0.0, math.inf, final, rec, wall, engine, out)
    summary.update(
        steps=0,
        dt_s=None,
        dt_auto=False,
        stability_bound_method="none: a static solve takes no time steps",
        steps_per_s=None,
        static={
            "converged": True,
            "residual": info["residual"],
            "tol": tol,
            "iterations": info["iterations"],
            "cg_iterations": info["cg_iterations"],
            "max_iter": solve.max_iter,
            "time_s": t,
        },
    )
    _final_state_outputs(scene, model, final, out, summary)
    finish_outputs(summary, out, t_rec, series, f"{scene.name}: static equilibrium")
    return summary


def finish_outputs(summary: dict, out: Path, t: np.ndarray, series: dict, title: str) -> None:
    """Write ``energy.png`` (:func:`plot_energy`) and, last, ``summary.json`` (series on one line each).

    ``summary["outputs"]`` becomes the list of files in ``out`` (the run's manifest).
    """
    plot_energy(out / "energy.png", t, series, title=title)
    summary["outputs"] = manifest(out)
    text = summary_json(summary, series_on_one_line="tools" in summary)
    (out / "summary.json").write_text(text + "\n")


def run_outputs(
    scene: Scene,
    model: Model,
    integrator,
    dt: float,
    bound: float,
    final,
    rec: dict,
    wall: float,
    engine_summary: dict,
    out: Path,
    series: dict | None = None,
) -> tuple:
    """Write ``trajectory.npz`` of a run; return the summary's common part and ``(t, x, v, series)``.

    ``rec`` is :func:`~torchdeform.sim.engine.simulate`'s record of the whole body (the last frame
    is appended when the run did not end on one); ``series`` that of :func:`energy_series`, computed
    here with ``model`` unless given (a run whose springs changed gives each frame's own).
    """
    t, x, v = rec["t"].numpy(), rec["x"][:, 0], rec["v"][:, 0]
    if scene.steps % scene.frames_every:
        t = np.append(t, final.t)
        x = torch.cat([x, final.x[:1].detach().cpu()])
        v = torch.cat([v, final.v[:1].detach().cpu()])
    if series is None:
        series = energy_series(model, x, v)
    cause = "the run diverged between two divergence checks"
    for name, value in (("x", x), ("v", v), *series.items()):
        require_finite(f"trajectory.npz: {name}", value, what="frame, ..." if name in "xv" else "frame", cause=cause)
    grid = model.grid
    np.savez(
        out / "trajectory.npz",
        t=t,
        x=x.float().numpy(),
        v=v.float().numpy(),
        X=model.X[0].float().cpu().numpy(),
        node_mask=grid.nodes().numpy(),
        shape=np.array(grid.shape),
        spacing=np.array(grid.spacing),
        origin=np.array(grid.origin),
        topology=grid.topology,
        dt=dt,
        integrator=integrator.name,
        **series,
    )

    options = {k: v for k, v in vars(integrator).items() if isinstance(v, (int, float, str)) and not k.startswith("_")}
    summary = {
        "name": scene.name,
        "scene": scene.source.path,
        "integrator": {"name": integrator.name, **options},
        "steps": scene.steps,
        "dt_s": dt,
        "dt_auto": scene.dt == "auto",
        "simulated_time_s": float(final.t),
        "time_step_bound_s": bound if math.isfinite(bound) else None,
        "stability_bound_method": _bound_method(integrator.name),
        "wall_time_s": wall,
        "steps_per_s": scene.steps / wall if wall > 0 else None,
        "engine": engine_summary,
        "nodes": grid.num_nodes,
        "springs": grid.num_springs,
        "grid": {
            "shape": list(grid.shape),
            "spacing": list(grid.spacing),
            "origin": list(grid.origin),
            "topology": grid.topology,
        },
        "dtype": str(model.dtype).replace("torch.", ""),
        "device": str(model.device),
        **({"threads": scene.threads} if scene.threads else {}),
        "frames": len(t),
        "final_energy_J": {k: float(series[k][-1]) for k in ("kinetic", "elastic", "gravity", "total") if k in series},
        # the largest over the run (the peak); the last frame's under its own name
        "max_displacement_m": float(series["max_displacement"].max()),
        "final_displacement_m": float(series["max_displacement"][-1]),
        "peak_displacement_m": float(series["max_displacement"].max()),
        "max_free_displacement_m": float(series["max_free_displacement"].max()),
        "final_free_displacement_m": float(series["max_free_displacement"][-1]),
    }
    return summary, (t, x, v, series)


def _chain(*callbacks):
    """One ``callback(step, state)`` calling each of ``callbacks`` that is not None, in order."""
    callbacks = [c for c in callbacks if c is not None]

    def call(step, state):
        for c in callbacks:
            c(step, state)

    return call


def report(summary: dict, out_dir) -> str:
    """One line for the CLI: what ran, how fast, and where the outputs are."""
    if "bodies" in summary:
        return bodies_report(summary, out_dir)
    files = summary.get("outputs") or ["trajectory.npz", "summary.json", "energy.png"]
    if "static" in summary:
        st = summary["static"]
        return (
            f"{summary['name']}: static equilibrium in {st['iterations']} Newton iterations ({st['cg_iterations']} CG) "
            f"in {summary['wall_time_s']:.2f} s, relative residual {st['residual']:.2g} (tol {st['tol']:.2g}), "
            f"max displacement {summary['max_displacement_m'] * 1e3:.3g} mm; wrote {', '.join(files)} to {out_dir}"
        )
    bound = summary["time_step_bound_s"]
    bound = f" (bound {bound:.3g} s)" if bound else ""
    tools = ""
    if "tools" in summary:
        tools = ", max tool force " + ", ".join(
            f"{name} {entry['max_force_N']:.3g} N" for name, entry in summary["tools"].items()
        )
    if "topology" in summary:
        topo = summary["topology"]
        tools += (
            f", {topo['springs_removed_by_cuts'] + topo['springs_removed_by_tear']} springs cut or torn, "
            f"{topo['cautery_nodes_removed']} nodes burnt, {topo['components']} piece(s)"
        )
    stiffest = (summary.get("palpation") or {}).get("stiffest")
    if stiffest:
        tools += (
            f", stiffest press at {stiffest['along_m'] * 1e3:.3g} mm along the line ({stiffest['peak_force_N']:.3g} N)"
        )
    engine = summary.get("engine") or {}
    ran = f" ({engine['ran']}" if engine.get("ran") else ""
    if ran and engine.get("compile_s") is not None:
        ran += f", {'C kernel' if engine['ran'] == 'native' else 'compile'} {engine['compile_s']:.1f} s"
    ran += ")" if ran else ""
    return (
        f"{summary['name']}: {summary['steps']} {summary['integrator']['name']} steps of "
        f"{summary['dt_s']:.3g} s{bound} in {summary['wall_time_s']:.2f} s{ran}, max displacement "
        f"{summary['max_displacement_m'] * 1e3:.3g} mm (peak), final displacement "
        f"{summary.get('final_displacement_m', summary['max_displacement_m']) * 1e3:.3g} mm{tools}; "
        f"wrote {', '.join(files)} to {out_dir}"
    )


def scene_volume_outputs(
    volume, x, X, spacing, out_dir, *, tf: str = "ct-soft", mode: str = "dvr", view: str = "h", base=None, cut=None
) -> dict:
    """Deform a scene's volume by its final node positions and write its renders.

    Writes ``volume_before.png``, ``volume_after.png`` and ``volume_deformed.npy`` to ``out_dir``.
    The volume fills the node grid's bounding box (:func:`~torchdeform.volume.node_offsets`).
    For a body whose topology changed (``cut``), ``volume_after.png`` is the carved render: each
    piece (side of a cut) samples the volume through its own displacement, so an opening shows
    empty (:func:`~torchdeform.topology.surfaces.cut_pieces`).

    Args:
        volume: a file name (relative to ``base``), ``"phantom"`` or ``"phantom:N"``.
        x: final node positions ``(1, 3, n_d, n_h, n_w)`` (m).
        X: rest node positions ``(1, 3, n_d, n_h, n_w)`` (m).
        spacing: node spacing (m).
        out_dir: the output folder.
        tf: transfer-function preset or file.
        mode: ``"dvr"``, ``"mip"`` or ``"average"``.
        view: axis view, ``"d"``, ``"h"``, ``"w"``, ``"-d"``, ``"-h"`` or ``"-w"``.
        base: the folder a volume file name is relative to, or None.
        cut: ``(grid, labels (n_d, n_h, n_w))`` of the pieces, or None.

    Returns:
        a summary dict for ``summary.json``.
    """
    from ..volume import load_volume, node_offsets, render, save_png, save_volume, to_image, warp

    name = volume if isinstance(volume, np.ndarray) else str(volume)
    path = volume_path(name, base)
    vol = torch.from_numpy(load_volume(path, key="volume.file"))
    out = Path(out_dir)
    with torch.no_grad():
        offsets = node_offsets(x.double().cpu(), X.double().cpu(), spacing, tuple(vol.shape)).float()
        # with return_info, warp returns (volume, info dict)
        deformed, info = cast("tuple[torch.Tensor, dict]", warp(vol, offsets, return_info=True))
        flip = view in ("h", "-h", "w", "-w")
        save_png(
            out / "volume_before.png", to_image(render(vol, tf=tf, mode=mode, view=view, engine="auto"), flip_up=flip)
        )
        if cut is None:
            after = render(vol, tf=tf, mode=mode, view=view, offsets=offsets, engine="auto")
        else:
            from ..topology import cut_pieces

            pieces = [
                (o.float(), m)
                for o, m in cut_pieces(cut[0], x.double().cpu(), cut[1].cpu(), tuple(vol.shape), X=X.double().cpu())
            ]
            after = render(vol, tf=tf, mode=mode, view=view, pieces=pieces, fill=float(vol.min()))  # the gap: "air"
        save_png(out / "volume_after.png", to_image(after, flip_up=flip))
    save_volume(out / "volume_deformed.npy", deformed.numpy())
    return {
        "volume": name if isinstance(name, str) else "the CT of the labels, on the lattice's box",
        "shape": list(vol.shape),
        "max_offset_voxels": float(offsets.abs().max()),
        "folded_fraction": info["folded"],
        "outputs": ["volume_before.png", "volume_after.png", "volume_deformed.npy"],
    }


def scene_texture(spec: dict, grid):
    """The solid texture of a scene's ``[texture]`` section, its seams blended as ``spec["seams"]`` asks.

    Built once per run; ``textured.png`` and the animation both read it.

    Args:
        spec: ``{"exemplar": (3, E, E, E), "block", "seed", "voxel", "seams"}`` (``seams``: a method of
            :meth:`~torchdeform.texture.SolidTexture.blend`).
        grid: the grid (the texture covers its rest box, :func:`~torchdeform.texture.mapping.body_texture`).

    Returns:
        ``(texture, seams)``: the :class:`~torchdeform.texture.SolidTexture` and the blend's report
        (None without blending).
    """
    from ..texture.mapping import body_texture

    tex = body_texture(grid, exemplar=spec["exemplar"], block=spec["block"], seed=spec["seed"], voxel=spec["voxel"])
    seams = tex.blend(method=spec["seams"]) if spec.get("seams", "none") != "none" else None
    return tex, seams


def scene_texture_outputs(tex, grid, x, labels, out_dir) -> dict:
    """Write ``textured.png``: the final surfaces (one per piece) coloured by a solid texture.

    Colours are looked up at every pixel's material coordinates, so cut faces show the interior
    (:func:`~torchdeform.texture.render_textured`).

    Args:
        tex: the scene's texture (:func:`scene_texture`).
        grid: the grid.
        x: final positions ``(1, 3, D, H, W)`` (m).
        labels: pieces ``(D, H, W)`` (negative outside the body).
        out_dir: the output folder.

    Returns:
        a summary dict for ``summary.json``.
    """
    from ..mesh import save_png
    from ..texture import render_textured
    from ..texture.mapping import framing_camera
    from ..topology import cut_surfaces

    pieces = cut_surfaces(grid, x.detach().double().cpu(), labels.cpu())
    camera = framing_camera(
        torch.cat([torch.as_tensor(p.vertices) for p in pieces]), direction=(1.3, -1.1, 0.9), fov_deg=38.0
    )
    save_png(Path(out_dir) / "textured.png", render_textured(pieces, tex, camera, light=(1.0, -0.5, 0.6))["image"])
    return {
        "exemplar_voxels": list(tex.exemplar.shape[1:]),
        "block": tex.block,
        "blocks": list(tex.blocks),
        "voxel_m": tex.voxel,
        "pieces": len(pieces),
        "outputs": ["textured.png"],
    }


def scene_animation(
    scene: Scene,
    model: Model,
    t: np.ndarray,
    x: torch.Tensor,
    v: torch.Tensor,
    out_dir,
    *,
    labels=None,
    tools: dict | None = None,
    texture=None,
    progress: bool = False,
    surfaces=None,
) -> dict:
    """Write ``scene.animation`` (a GIF): the run's textured surface beside its deformed volume render.

    See :func:`torchdeform.scene.animation.animate`. The volume panel shows the scene's ``[volume]``
    (none without one), the texture is its ``[texture]`` (else the procedural liver, seams blended),
    the scene's tools are drawn where they are, and ``surfaces`` (embedded surfaces) replace the
    lattice's own surface. The
    caption shows the time and the force of every tool (``tools``) and, for a scene with drags, the
    force the drags exert to hold their nodes (:func:`~torchdeform.scene.animation.drag_forces`).
    A cut body is drawn as the final pieces (``labels``) in every frame, its volume uncarved.

    Args:
        scene: the :class:`Scene`.
        model: the model of the run.
        t: frame times ``(T,)`` (s).
        x: positions ``(T, 3, D, H, W)`` (m).
        v: velocities ``(T, 3, D, H, W)`` (m/s).
        out_dir: the output folder.
        labels: pieces ``(D, H, W)`` (negative outside), or None (the whole body).
        tools: :meth:`ToolRecorder.series` of the run, or None.
        texture: the scene's texture (:func:`scene_texture`), or None (the procedural liver).
        progress: show a progress bar.
        surfaces: :class:`~torchdeform.mesh.embed.EmbeddedSurface` s, or None.

    Returns:
        a summary dict for ``summary.json``: ``file``, ``frames``, ``size`` ``[height, width]``, ``panel``,
        ``bytes``, ``wall_time_s``.
    """
    from .animation import animate, drag_forces

    start = time.perf_counter()
    grid = model.grid
    assert scene.animation is not None  # the file name of the animation asked for
    forces = {}
    if tools is not None:
        assert scene.tools is not None  # the series are those of the scene's tools
        forces.update(tool_forces_at(tools, scene.tools.names, t))
    if model.drags:
        forces["drag" if len(model.drags) == 1 else "drags"] = drag_forces(model, x, v, t)
    volume: dict[str, Any] = {}
    if scene.volume:  # the volume panel only where the scene has a volume
        volume = dict(scene.volume)
        name, base = volume.pop("file"), volume.pop("base", None)
        volume["volume"] = volume_path(name, base)
    info = animate(
        grid,
        t,
        x,
        Path(out_dir) / scene.animation,
        surfaces=surfaces,
        labels=labels,
        texture=texture,
        forces=forces,
        progress=progress,
        size=scene.image_size,
        camera=scene.camera,
        camera_up=scene.camera_up,
        tools=scene.tools.tools if scene.tools is not None else None,
        **volume,
    )
    return {k: info[k] for k in ("file", "frames", "size", "panel", "bytes")} | {
        "wall_time_s": time.perf_counter() - start
    }
