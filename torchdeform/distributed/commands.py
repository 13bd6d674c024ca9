"""``torchdeform sweep`` over ranks, and ``torchdeform run`` of one body split over ranks.

    torchdeform sweep SCENE.toml --set material.stiffness=1,2,4 --set integrator.dt=1e-4,2e-4 --out DIR
    torchdeform sweep SCENE.toml --points POINTS.csv --out DIR
    torchrun --nproc-per-node 4 -m torchdeform sweep SCENE.toml --set ... --out DIR
    torchrun --nproc-per-node 2 -m torchdeform run SCENE.toml --out DIR      (slabs along D, one halo layer)

Under ``torchrun``, ``run`` decomposes the scene's body (:mod:`torchdeform.distributed.domain`);
rank 0 writes the same outputs as one process, plus a ``"domain"`` part in ``summary.json`` (one
difference: with ``[[cuts]]``, the spring energies of frames before a cut are computed with the
final springs, where one process uses each frame's own).

Every rank checks every point's scene before any collective call, so bad input (a key that does
not exist, a value of the wrong type) ends every rank with exit status 2 and one line, printed
by rank 0 (``torchrun`` adds its own failure report after it). See
:mod:`torchdeform.distributed.sweep` for the rows, the records and the resume.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..options import integer

__all__ = ["add_arguments", "command", "rank_and_world", "run_command"]


def add_arguments(p) -> None:
    """The options of ``torchdeform sweep``."""
    p.add_argument("scene", help="the scene file (.toml, mass-spring)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="a scene key and its values (repeatable: the Cartesian product is swept)",
    )
    p.add_argument("--points", default=None, help="a CSV list of points instead (header: scene keys)")
    p.add_argument("--out", required=True, help="output folder (sweep.csv, sweep.png, records/)")
    p.add_argument(
        "--device", default=None, help="cpu or cuda (default: the scene's; cuda:<local rank> under torchrun)"
    )
    p.add_argument(
        "--batch",
        type=integer(lo=1),
        default=32,
        help="points simulated together when they differ only in "
        "material.stiffness/damping (default 32; 1: one by one)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def rank_and_world() -> tuple[int, int]:
    """``(rank, world size)`` from torchrun's environment (``RANK``, ``WORLD_SIZE``); ``(0, 1)`` without it."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))


def command(args) -> int:
    """Run the sweep; on rank 0 write the table and the plot. Returns the exit status."""
    return _on_every_rank(_sweep, args)


def run_command(args) -> int:
    """``torchdeform run``: one process as usual; under ``torchrun`` (2 or more ranks) the body split over ranks."""
    if rank_and_world()[1] <= 1:
        from ..scene.commands import run_command as run_one

        return run_one(args)
    return _on_every_rank(_run_decomposed, args)


def _on_every_rank(work, args) -> int:
    """``work(args, rank, world)``; a user's mistake is exit status 2 on every rank and one line, from rank 0."""
    from ..errors import TorchdeformError

    rank, world = rank_and_world()
    try:
        return work(args, rank, world)
    except TorchdeformError as e:
        if rank == 0:
            print(f"torchdeform: {e}", file=sys.stderr)
        else:  # torchrun stops the group when the first rank ends: let rank 0 print its line first
            import time

            time.sleep(2.0)
        return 2


def scene_cuts(scene) -> list:
    """``[(time, blade), ...]`` of a scene's ``[[cuts]]`` blades; anything else a decomposed run cannot do is refused."""
    from ..errors import ConfigError

    topo = scene.topology
    if scene.tools is not None and (scene.tools.tools or getattr(scene.tools, "strain_limit", None)):
        raise ConfigError(
            "tools",
            "no [[tools]] or [strain_limit] in a domain-decomposed run (they need the whole body); run it on one rank",
            got="tools",
        )
    if topo is None:
        return []
    for key, items in (
        ("cautery", topo.cautery),
        ("tear", topo.tear),
        ("coagulate", topo.coagulate),
        ("output.surfaces", topo.surfaces),
    ):
        if items:
            raise scene.source.error(
                key, "only [[cuts]] blades in a domain-decomposed run; run it on one rank", got=key
            )
    out = []
    for c in topo.cuts:
        if "blade" not in c:
            raise scene.source.error(
                c["key"] + ".tool",
                "a blade (origin/u/v, triangle, edges) in a domain-decomposed run, not a scalpel",
                got=c.get("tool"),
            )
        if c.get("gape"):
            raise scene.source.error(
                c["key"] + ".gape",
                "0 in a domain-decomposed run (pre-tension reaches springs beyond the one-layer halo)",
                got=c["gape"],
            )
        out.append((c["at"], c["blade"]))
    return out


def _run_decomposed(args, rank: int, world: int) -> int:
    import torch

    from ..checks import usable_device
    from ..errors import ConfigError
    from ..outputs import RunFolder
    from ..scene.mass_spring import EXPLICIT, Scene
    from ..scene.run import finish_outputs, load_scene, report, run_outputs
    from ..sim.stability import check_dt, time_step_bound
    from .domain import SUPPORTED_INTEGRATORS, decomposed_simulate, slab_rows

    if args.device is not None:
        usable_device(
            args.device.replace("cuda", f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}")
            if args.device == "cuda"
            else args.device,
            key="--device",
        )
    folder = RunFolder(args.out, force=args.force)
    folder.check()  # every rank, before any collective
    scene = load_scene(args.scene)
    if not isinstance(scene, Scene):
        several = type(scene).__name__ == "BodiesScene"
        raise ConfigError(
            "bodies" if several else "model",
            "a scene of one mass-spring body in a domain-decomposed run"
            + (" (a scene of several bodies runs in one process: torchdeform run without torchrun)" if several else ""),
            got="[[bodies]]" if several else "chainmail",
        )
    if getattr(args, "animation", False) or scene.animation or scene.volume or scene.texture:
        raise ConfigError(
            "run",
            "no animation, [volume] or [texture] in a domain-decomposed run (yet); run it on one rank",
            got="torchrun",
        )
    integrator = scene.integrator
    if integrator.name not in SUPPORTED_INTEGRATORS:
        raise scene.source.error(
            "integrator.name",
            f"one of {', '.join(SUPPORTED_INTEGRATORS)} in a domain-decomposed run",
            got=integrator.name,
        )
    cuts = scene_cuts(scene)
    slab_rows(scene.grid.shape[0], world)  # more ranks than rows: refused before any work
    device = args.device or scene.device or "cpu"
    if str(device) == "cuda":  # one GPU per rank on each machine
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
    model = scene.build(device=device)
    bound = time_step_bound(model, integrator=integrator)
    dt = scene.time_step(bound)
    if scene.topology is not None and scene.topology.checked_end is None:
        scene.topology.check(scene.steps * dt)
    if integrator.name in EXPLICIT and rank == 0:
        check_dt(model, dt, integrator, bound=bound)
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("nccl" if model.device.type == "cuda" else "gloo")
    if model.device.type == "cuda":
        torch.cuda.set_device(model.device)
    try:
        run = decomposed_simulate(
            model,
            model.rest_state(),
            dt,
            scene.steps,
            integrator=integrator,
            record_every=scene.frames_every,
            progress=not args.quiet,
            cuts=cuts,
        )
        parts = [None] * world
        dist.all_gather_object(parts, run.summary())
        if rank == 0:
            engine = {
                "requested": scene.engine,
                "ran": "eager",
                "why": f"domain-decomposed over {world} ranks",
                "eager_ms_per_step": None,
                "native_ms_per_step": None,
                "compile_s": None,
                "force_form": None,
                "threads": None,
            }
            with folder as out:
                summary, (t, _, _, series) = run_outputs(
                    scene, run.whole, integrator, dt, bound, run.final, run.record, run.wall_s, engine, out
                )
                # (spring energies of every frame use the final springs here: before a cut they differ
                # from a one-process run, which records each frame's own)
                summary["domain"] = {
                    "ranks": world,
                    "axis": "D",
                    "halo_rows": 1,
                    "per_rank": parts,
                    "comm_share": max(p["comm_share"] for p in parts),
                    "spring_energies": "final springs" if cuts else "as one process",
                }
                finish_outputs(
                    summary, out, t, series, f"{scene.name}: {integrator.name}, dt = {dt:.3g} s, {world} ranks"
                )
            print(report(summary, args.out))
    finally:
        dist.barrier()
        dist.destroy_process_group()
    return 0


def _points(args) -> tuple[list, list]:
    from ..errors import ConfigError
    from .sweep import check_key, parse_set, product, read_points

    if bool(args.set) == bool(args.points):
        raise ConfigError("sweep", "--set KEY=V1,V2,... (repeatable) or --points FILE.csv, not both", got=None)
    if args.points:
        points = read_points(args.points)
        keys = list(points[0])
    else:
        sets = [parse_set(s) for s in args.set]
        keys = [k for k, _ in sets]
        if len(set(keys)) != len(keys):
            raise ConfigError("--set", "each key once", got=", ".join(keys))
        points = product(sets)
    for k in keys:
        check_key(k)
    return keys, points


def _sweep(args, rank: int, world: int) -> int:
    import torch

    from ..errors import ConfigError
    from ..scene.bodies import read_scene
    from .sweep import batches, done_points, plot, point_id, point_scene, record, run_batch, write_table

    keys, points = _points(args)
    src, data = read_scene(args.scene)
    if "bodies" in data:
        raise ConfigError(
            "sweep",
            "a scene of one body (a [[bodies]] scene is not swept yet; torchdeform run --set takes its keys)",
            got=str(args.scene),
        )
    if data.get("model", "mass-spring") != "mass-spring":
        raise ConfigError("sweep", "a mass-spring scene file", got=data.get("model"))
    base, name = Path(args.scene).parent, Path(args.scene).stem
    scenes = [point_scene(src, data, base, name, p) for p in points]  # every point checked first
    ids = [point_id(p) for p in points]
    if len(set(ids)) != len(ids):
        raise ConfigError("sweep", "distinct points", got="a point given twice")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError("--out", "a folder", got=str(out))
    device = args.device
    if device is None and world > 1 and torch.cuda.is_available():
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
    done = done_points(out)
    todo = [i for i in range(len(points)) if ids[i] not in done]
    work = batches([points[i] for i in todo], [scenes[i] for i in todo], args.batch)
    mine = [[todo[j] for j in batch] for n, batch in enumerate(work) if n % world == rank]
    group = _init(world)
    try:
        if rank == 0:
            skipped = sum(i in done for i in ids)
            print(
                f"sweep: {len(points)} points in {len(work)} batch{'es' if len(work) != 1 else ''} over {world} "
                f"rank{'s' if world > 1 else ''}"
                + (f", {skipped} already done (records in {out / 'records'})" if skipped else ""),
                file=sys.stderr,
            )
        out.mkdir(parents=True, exist_ok=True)
        rows = {}
        from tqdm.auto import tqdm

        with tqdm(
            total=sum(map(len, mine)),
            desc=f"sweep (rank {rank})" if world > 1 else "sweep",
            unit="point",
            disable=args.quiet or rank != 0 or None,
            file=sys.stderr,
        ) as bar:
            for batch in mine:
                for i, row in zip(batch, run_batch([scenes[i] for i in batch], device=device)):
                    record(out, rank, ids[i], row)
                    rows[ids[i]] = row
                bar.update(len(batch))
        if group:
            gathered = [None] * world
            torch.distributed.all_gather_object(gathered, rows)
            for part in gathered:
                rows.update(part)
        if rank == 0:
            table = [{**p, **(rows.get(pid) or done[pid])} for p, pid in zip(points, ids)]
            path = write_table(out, keys, table)
            plot(out, keys, table)
            bad = sum(r["status"] != "ok" for r in table)
            print(f"wrote {path} ({len(table)} points" + (f", {bad} diverged" if bad else "") + ")", file=sys.stderr)
    finally:
        if group:  # leave together: a rank that tears down early can abort its peers
            torch.distributed.barrier()
            torch.distributed.destroy_process_group()
    return 0


def _init(world: int) -> bool:
    """Join torchrun's process group (gloo: rows are Python objects) when there are several ranks."""
    if world <= 1:
        return False
    # imported before the group exists: torch._dynamo (which a compiled sweep step imports) keeps
    # references to the groups alive at its import, and a rank could abort at exit (see
    # torchdeform.distributed.data_parallel.process_group)
    import torch._dynamo  # noqa: F401
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return True
