"""The benchmarks of ``torchdeform bench``: one entry per benchmark, a help line and the module that runs it.

Each module has ``add_arguments(parser)`` and ``run(args) -> int``; it is imported when the command
line is built (benchmark modules import nothing heavy at module level).

A new benchmark is one module in :mod:`torchdeform.bench` and one entry here.
"""

from __future__ import annotations

import importlib

__all__ = ["BENCHES", "module"]

#: name -> (help line, module of :mod:`torchdeform.bench`)
BENCHES = {
    "speed": (
        "spring-step throughput (Msprings/s, node-steps/s, GB/s against the copy bandwidth), eager and compiled, "
        "against Warp; implicit Euler on a beam",
        "speed",
    ),
    "batch": (
        "many bodies in one batch: body-steps/s of an n^3 cube against the batch size, eager and compiled, "
        "and the speed-up per body over one",
        "batch",
    ),
    "accuracy": (
        "error against wall time of every integrator on standard scenes, a resolution sweep, Pareto front",
        "accuracy",
    ),
    "elasticity": (
        "an Elastic lattice body against finite elements (uniaxial E and nu, shear, cantilever, punch) at three "
        "resolutions, and ms per step of springs alone against springs with the volume term",
        "elasticity",
    ),
    "anatomy": (
        "a 256^3 label volume to a ready 64^3-class body, smooth label surfaces, and a 100k-triangle "
        "embedded surface per frame, against their targets",
        "anatomy",
    ),
    "fuzzy": (
        "Mamdani inputs per second (SUSILAP-G preset by default), eager and compiled, against scikit-fuzzy",
        "fuzzy",
    ),
    "volume": (
        "deform and render a 256^3 volume to a 256^2 image: frames per second, through the "
        "displacement field against building the warped volume first",
        "volume",
    ),
    "chainmail": (
        "ChainMail: time of a local pull against grid size and moved elements, Gibson, Enhanced and tensor",
        "chainmail",
    ),
    "interaction": (
        "a sphere tool pressing into an n^3 body: steps/s with contact and force readout "
        "(compiled), and the haptic loop's force rate on 64^3",
        "interaction",
    ),
    "bodies": (
        "two n^3 bodies, one resting on the other (base fixed) against the same two apart: steps/s of "
        "Bodies.step and how many times slower contact makes it",
        "bodies",
    ),
    "topology": (
        "a full cut between two layers of an n^3 body under its compiled step: springs removed vs "
        "the analytic count, cut time, step time before and after, recompilations",
        "topology",
    ),
    "texture": (
        "solid texture on meshes of Chen & He's model sizes: node colouring and triangle interiors "
        "against their GPU times, and a fresh cut face",
        "texture",
    ),
    "frame": (
        "interactive frames per second: one 26-neighbour step + the deformed surface (and optionally a "
        "volume render) on Punak's grid sizes, against his GeForce 8800 GTS rates",
        "frame",
    ),
    "viewer": (
        "the browser viewer's page in headless chromium: frames drawn and received per second on a 16^3 "
        "and a 32^3 body, optionally beside a busy process",
        "viewer",
    ),
    "distributed": (
        "a 64-point sweep and a 96^3 body split into slabs, on 1 and 2 ranks (torchrun, gloo): wall "
        "time, ms per step, communication share, halo bytes",
        "distributed",
    ),
    "endoscope": (
        "virtual endoscopy by the native ray marcher: frames per second of overview, endoscopic, VOI and "
        "deforming views of a 256x256x128 CT in a 700x600 window, against Radetzky's Table 3.1",
        "endoscope",
    ),
    "learn": (
        "a training iteration of Radetzky's per-spring run, eager and compiled: seconds, speed-up, and how "
        "far the learned values agree after each iteration",
        "learn",
    ),
}


def module(name: str):
    """The module of benchmark ``name`` (a key of :data:`BENCHES`)."""
    return importlib.import_module(f"{__package__}.{BENCHES[name][1]}")
