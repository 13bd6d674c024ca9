"""Benchmarks: ``torchdeform bench <name>``.

==========  ================================================================================
speed       spring-step throughput of symplectic Euler on a damped cube: Msprings/s,
            node-steps/s and ms/step for n^3 grids, topologies, eager and compiled, dtypes,
            thread counts, against NVIDIA Warp's CPU backend; implicit Euler on a beam
accuracy    error against wall time of every integrator on four standard scenes and a
            resolution sweep, with the Pareto front and a recommendation
elasticity  an Elastic lattice body against finite elements (scikit-fem) at three
            resolutions, and the step time of its volume term against springs alone
fuzzy       Mamdani inputs per second, eager and compiled, against scikit-fuzzy
volume      deform and render a 256^3 volume: frames per second of each rendering path
chainmail   time of a local ChainMail pull against grid size and moved elements
bodies      two n^3 bodies, one resting on the other against the same two apart: steps/s
            of ``Bodies.step`` and how many times slower contact makes it
==========  ================================================================================

Each benchmark is one module here with ``add_arguments(parser)`` and ``run(args) -> int`` (a
subpackage where it is large: :mod:`.accuracy`), and one entry of
:data:`~torchdeform.bench.registry.BENCHES`; :mod:`.common` holds what they share,
:mod:`.warp_baseline` the NVIDIA Warp comparison of ``speed``. Only the command line
(:mod:`torchdeform.cli`) imports this package: the library never depends on its benchmarks.

Output conventions shared by every benchmark: the table goes to stdout; with ``--json``
stdout carries exactly one JSON document and nothing else (progress, warnings and compiler
chatter go to stderr); ``--out DIR`` writes ``<name>.csv`` and ``<name>.png``.

Example:
    torchdeform bench speed --quick
    torchdeform bench speed --sizes 16,32,64 --topologies 6,26 --threads 2 --out bench-out
"""

__all__: list = []
