"""``torchdeform sweep``: a parameter sweep over a scene file, on one process or spread over ranks.

    torchdeform sweep SCENE.toml --set material.stiffness=1,2,4 --set integrator.dt=1e-4,2e-4 --out DIR
    torchdeform sweep SCENE.toml --points POINTS.csv --out DIR
    torchrun --nproc-per-node 4 -m torchdeform sweep SCENE.toml --set ... --out DIR

Every rank checks every point's scene before any collective call, so bad input (a key that does
not exist, a value of the wrong type) ends every rank with exit status 2 and one line, printed
by rank 0 (``torchrun`` adds its own failure report after it). See
:mod:`torchdeform.distributed.sweep` for the rows, the records and the resume.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["add_arguments", "command", "rank_and_world"]


def add_arguments(p) -> None:
    """The options of ``torchdeform sweep``."""
    p.add_argument("scene", help="the scene file (.toml, mass-spring)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a scene key and its values (repeatable: the Cartesian product is swept)")
    p.add_argument("--points", default=None, help="a CSV list of points instead (header: scene keys)")
    p.add_argument("--out", required=True, help="output folder (sweep.csv, sweep.png, records/)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the scene's; cuda:<local rank> under torchrun)")
    p.add_argument("--batch", type=int, default=32, help="points simulated together when they differ only in "
                                                         "material.stiffness/damping (default 32; 1: one by one)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def rank_and_world() -> tuple[int, int]:
    """``(rank, world size)`` from torchrun's environment (``RANK``, ``WORLD_SIZE``); ``(0, 1)`` without it."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))


def command(args) -> int:
    """Run the sweep; on rank 0 write the table and the plot. Returns the exit status."""
    from ..errors import TorchdeformError
    rank, world = rank_and_world()
    try:
        return _sweep(args, rank, world)
    except TorchdeformError as e:
        if rank == 0:
            print(f"torchdeform: {e}", file=sys.stderr)
        return 2


def _points(args) -> tuple[list, list]:
    from ..errors import ConfigError
    from .sweep import check_key, parse_set, product, read_points
    if bool(args.set) == bool(args.points):
        raise ConfigError("sweep", "--set KEY=V1,V2,... (repeatable) or --points FILE.csv, not both", None)
    if args.points:
        points = read_points(args.points)
        keys = list(points[0])
    else:
        sets = [parse_set(s) for s in args.set]
        keys = [k for k, _ in sets]
        if len(set(keys)) != len(keys):
            raise ConfigError("--set", "each key once", ", ".join(keys))
        points = product(sets)
    for k in keys:
        check_key(k)
    return keys, points


def _sweep(args, rank: int, world: int) -> int:
    import torch

    from ..errors import ConfigError
    from ..scene.reader import read
    from .sweep import batches, done_points, plot, point_id, point_scene, record, run_batch, write_table
    if args.batch < 1:
        raise ConfigError("--batch", "a whole number >= 1", args.batch)
    keys, points = _points(args)
    src, data = read(args.scene)
    if data.get("model", "mass-spring") != "mass-spring":
        raise ConfigError("sweep", "a mass-spring scene file", data.get("model"))
    base, name = Path(args.scene).parent, Path(args.scene).stem
    scenes = [point_scene(src, data, base, name, p) for p in points]          # every point checked first
    ids = [point_id(p) for p in points]
    if len(set(ids)) != len(ids):
        raise ConfigError("sweep", "distinct points", "a point given twice")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError("--out", "a folder", str(out))
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
            print(f"sweep: {len(points)} points in {len(work)} batch{'es' if len(work) != 1 else ''} over {world} "
                  f"rank{'s' if world > 1 else ''}"
                  + (f", {skipped} already done (records in {out / 'records'})" if skipped else ""), file=sys.stderr)
        out.mkdir(parents=True, exist_ok=True)
        rows = {}
        from tqdm.auto import tqdm
        with tqdm(total=sum(map(len, mine)), desc=f"sweep (rank {rank})" if world > 1 else "sweep", unit="point",
                  disable=args.quiet or rank != 0 or None, file=sys.stderr) as bar:
            for batch in mine:
                for i, row in zip(batch, run_batch([scenes[i] for i in batch], device)):
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
        if group:                     # leave together: a rank that tears down early can abort its peers
            torch.distributed.barrier()
            torch.distributed.destroy_process_group()
    return 0


def _init(world: int) -> bool:
    """Join torchrun's process group (gloo: rows are Python objects) when there are several ranks."""
    if world <= 1:
        return False
    import torch.distributed as dist
    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return True
