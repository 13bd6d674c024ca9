"""Scene files (TOML) -> a model, an integrator and run settings, and the runner.

A scene file only builds the objects of the Python API: :class:`Scene` holds a
:class:`~torchdeform.sim.grid.Grid`, the keyword arguments of :class:`~torchdeform.sim.model.Model`
(``scene.model_args``), an :class:`~torchdeform.sim.integrators.Integrator` and the run settings;
:func:`demo_scene` builds the built-in demo with the API alone. :func:`run_scene` runs a
scene and writes ``trajectory.npz``, ``summary.json`` and ``energy.png``; with ``[[tools]]`` also
``tools.npz``, ``forces.png`` and the tools' force series in ``summary.json``
(:mod:`.tools`).

Units are SI (m, kg, s, N). Vectors are in channel order ``(D, H, W)``; axis D is "up" in
the built-in scenes (face ``"bottom"`` = ``"d-"``, ``"top"`` = ``"d+"``). Node indices are
``[i, j, k]`` along ``(D, H, W)``, from 0.

Keys
----
``[grid]`` (required)
    ``shape = [D, H, W]``  node counts, each >= 1 (or ``mesh``)
    ``mesh = "organ.stl"``  a closed triangle mesh voxelised into the node mask (instead of
    ``shape``; path relative to the scene file; mesh x, y, z -> D, H, W)
    ``spacing``  metres, one number or ``[sd, sh, sw]`` (required)
    ``topology``  6, 14, 18 or 26 neighbours (default 26)
    ``origin = [od, oh, ow]``  position of node [0, 0, 0] in metres (default 0; ``shape`` only)
    ``padding``  extra node layers around the mesh's bounding box (default 0; ``mesh`` only)
    ``scale``  metres per mesh unit, e.g. 0.001 for a mesh in mm (default 1; ``mesh`` only)
``[material]`` (required)
    ``stiffness``  spring stiffness k in N/m: a number, or one per direction class
    ``{axis = .., face = .., body = ..}`` (only the classes of the topology are needed)
    ``modulus``  instead of ``stiffness``: Y in N, each spring gets ``k = Y / l0``
    (resolution-independent); a number or a table as for ``stiffness``
    ``damping``  dashpot along each spring in N s/m (divided by l0 too with ``modulus``);
    a number or a class table (default: none)
    ``damping_mode``  ``"projected"`` (default) or ``"unprojected"`` (Radetzky)
    ``law``  ``"hooke"`` (default), ``"exponential"`` (``stiffening`` b) or ``"polynomial"``
    (``quadratic`` c2, ``cubic`` c3): strain-stiffening springs (:mod:`torchdeform.sim.laws`) whose
    small-strain stiffness is ``stiffness``; each parameter a number >= 0 or a class table (default 0)
    ``tissue``  instead of ``stiffness``: words of the fuzzy tissue library (:mod:`torchdeform.fuzzy`):
    a tissue (``"liver"``, ``"fat"``, ...), a consistency term (``"very_soft"`` ... ``"hard"``) or
    a consistency number 0..10; its Young's modulus E becomes ``k = E / lattice_modulus(grid)``
    (``k = E h / 2.7`` for 26 neighbours)
``[[regions]]`` (optional, repeatable; needs ``stiffness`` as one number or ``tissue``): a part of
    the body with its own stiffness, later regions on top of earlier ones
    ``sphere = {center = [d, h, w], radius = r}`` or ``box = {lo = [..], hi = [..]}`` (rest
    positions, m), and ``stiffness`` (N/m) or ``tissue`` (as in ``[material]``); a spring gets
    the harmonic mean of its two end nodes' stiffness
``[mass]`` (required, exactly one key)
    ``mass``  kg per node, or ``density``  kg/m^3 (lumped from cell volumes)
``[boundary]`` (optional)
    ``fixed``  a face name or a list of them: ``"bottom"``, ``"top"``, ``"d-"``, ``"d+"``,
    ``"h-"``, ``"h+"``, ``"w-"``, ``"w+"``
    ``fixed_nodes = [[i, j, k], ...]``  more fixed nodes
    ``home``  stiffness (N/m) of home springs to every node's rest position (Punak)
    ``anchors = {stiffness = .., every = ..}``  anchor springs (N/m) on every k-th node (Radetzky)
    ``decay``  global drag rate c in 1/s: ``v <- v exp(-c dt)`` each step
    ``gravity = [gd, gh, gw]``  m/s^2
``[[loads]]`` (optional, repeatable), one of
    ``node = [i, j, k]`` with ``force = [fd, fh, fw]`` (N), or
    ``face = "top"`` with ``traction = [td, th, tw]`` (Pa, lumped onto the face's nodes);
    both take ``start`` (s, default 0) and ``ramp`` (s to reach full strength, default 0)
``[[drags]]`` (optional, repeatable): a group of nodes moved rigidly along a path
    ``nodes = [[i, j, k], ...]`` or ``face = "top"`` or ``box = {lo = [..], hi = [..]}``
    (rest positions in metres, bounds included), and
    ``path = [[t, [od, oh, ow]], ...]``  offsets (m) from the rest position at increasing
    times (s), linear in between, held after the last
``[[tools]]`` (optional, repeatable): rigid tools touching the tissue (:mod:`torchdeform.interact`)
    ``name`` (default ``tool1``, ``tool2``, ...; unique: the keys of the force readings)
    ``shape``  ``"sphere"`` (``radius``), ``"capsule"`` (``radius``, ``half_length``, ``axis`` =
    ``"d"``, ``"h"`` or ``"w"``), ``"box"`` (``half_extents = [hd, hh, hw]``), ``"half_space"``
    (``normal``, default ``[1, 0, 0]``) or ``"mesh"`` (``file``, a closed mesh relative to the scene
    file, and ``resolution`` of its distance field, default 32); metres
    ``position = [d, h, w]`` (fixed, with an optional ``orientation = [rd, rh, rw]``, a rotation
    vector in radians) or ``path = [[t, [d, h, w]], ...]`` / ``[[t, [d, h, w], [rd, rh, rw]], ...]``
    (increasing times, linear in between, held after the last)
    ``contact``  ``"projection"`` (default; options ``friction``, ``direction`` = ``"normal"`` or
    ``"motion"``, ``hold``, ``haptic_gain``), ``"penalty"`` (``stiffness`` N/m, ``damping``) or
    ``"none"`` (with a grasp)
    ``grasp = {close = t1, open = t2, margin = m}``  forceps: what lies in the shape (plus
    ``margin``) at ``close`` follows the tool until ``open`` (s; ``inf`` for never)
``[strain_limit]`` (optional): ``min`` (0.9), ``max`` (1.1): bounds of every spring's length over
    its rest length; ``passes`` (4); ``update_velocity`` (true)
``[[cuts]]``, ``[[cautery]]``, ``[tear]``, ``[[coagulate]]`` (optional): topology changes between steps
    (:mod:`.topology`): blades (``origin``/``u``/``v``, ``triangle`` or ``edges``) cutting ``at`` a time,
    or a ``tool`` carrying an ``edge`` from ``start`` to ``stop``, with ``gape``; a ``tool`` burning
    nodes ``at`` a time or every step; springs tearing past ``max_strain`` or ``max_force``; a region
    (as in ``[[regions]]``) whose shape sets ``at`` a time, its damping times ``viscosity_factor``
``[integrator]`` (required)
    ``name``  ``"explicit"``, ``"symplectic"`` (default), ``"verlet"``, ``"rk4"``,
    ``"implicit"``, ``"projective"``, ``"adaptive"`` or ``"knoche"``
    ``dt``  seconds > 0, or ``"auto"`` (explicit integrators: ``safety`` x the stability bound)
    ``safety``  fraction of the bound used by ``dt = "auto"`` (default 0.9)
    ``steps``  number of steps >= 0 (required)
    ``dtype``  ``"float32"`` (default) or ``"float64"``;  ``device``  ``"cpu"`` (default), ``"cuda"``
    ``threads``  CPU threads of the run (default: torch's; small bodies run faster on one)
    options of ``verlet``: ``kd`` (per-step damping in [0, 1), default 0);
    of ``implicit``: ``cg_iters`` (100), ``cg_tol`` (1e-6), ``newton_iters`` (0);
    of ``projective``: ``iterations`` (10), ``tol`` (0), ``solver`` (``"auto"``, ``"cholesky"``,
    ``"cg"``, ``"jacobi"``), ``rho`` (0.95), ``relaxation`` (0.9), ``delay`` (1), ``cg_iters`` (50),
    ``cg_tol`` (1e-6);
    of ``adaptive`` (``dt``: the interval between recorded states; the steps are its own):
    ``rtol`` (1e-3), ``pair`` (``"bogacki_shampine"``), ``min_step``, ``max_step``;
    of ``knoche`` (needs ``topology = 6``): ``material`` (w in [0, 1], a number or a
    ``[D][H][W]`` array), ``eps`` (1e-3), ``gain`` (default 3 / D)
``[output]`` (optional)
    ``record_every``  steps between saved frames (default: about 100 frames)
    ``name``  title of the run (default: the file's name)
    ``palpation``  ``true`` (the first tool with a contact) or a tool's name: analyse its presses,
    write ``palpation.png`` and a ``"palpation"`` part of ``summary.json``
    ``surfaces = [t1, t2, ...]``  times (s) at which the closed surface of every connected piece is
    written as ``surface_<ms>ms_<label>.ply`` (with topology changes also ``topology.png`` and a
    ``"topology"`` part of ``summary.json``)
    ``animation``  ``true``: write ``animation.gif``, the textured surface beside the deformed
    volume render with the time and the tools' forces (as ``torchdeform run --animation``; see
    :func:`torchdeform.scene.animation.animate`)
``[volume]`` (optional): a volume filling the grid's bounding box, deformed by the final state;
    the run also writes ``volume_before.png``, ``volume_after.png``, ``volume_deformed.npy``
    ``file``  a volume file (.npy, .npz, .nii, .nrrd; relative to the scene file) or ``"phantom:N"``
    ``tf``  transfer-function preset or file (default ``"ct-soft"``); ``mode``  ``"dvr"``
    (default), ``"mip"`` or ``"average"``; ``view``  axis view (default ``"h"``)
``model = "chainmail"`` (optional top-level key, before any section): a ChainMail scene instead
    of a mass-spring one: ``[grid]``, ``[chainmail]`` (required), ``[boundary]`` (``fixed``,
    ``fixed_nodes``), ``[[drags]]`` (the picked elements and their paths), ``[output]``; see
    :func:`torchdeform.scene.chainmail.chainmail_scene` for the ``[chainmail]`` keys

Every problem is a :class:`~torchdeform.errors.ConfigError` naming the file, the line (found
by a text search, best effort), the dotted key (``integrator.dt``, ``loads[0].force``; array
tables count from 0) and what was expected.

Modules: :mod:`.reader` (files, located errors, typed values and the shared sections: the API a
new model kind builds on), :mod:`.mass_spring`, :mod:`.tools` (``[[tools]]``, ``[strain_limit]``
and the tool outputs of a run), :mod:`.topology` (cuts, cautery, tearing, coagulation and their outputs), :mod:`.chainmail`, :mod:`.run` (load and run),
:mod:`.animation` (a run's frames, textured surface beside the deformed volume, into an animated GIF),
:mod:`.commands` (``torchdeform run`` and ``demo``).

Example:
    >>> from torchdeform.scene import demo_scene, run_scene
    >>> scene = demo_scene()
    >>> scene.steps = 20
    >>> scene.volume = None              # skip the volume renders (about a second)
    >>> summary = run_scene(scene, getfixture("tmp_path"), progress=False)
    >>> summary["steps"], summary["frames"]
    (20, 3)
"""

from .chainmail import ChainMailScene, chainmail_scene
from .mass_spring import Scene, demo_scene, mass_spring_scene
from .reader import SECTIONS, Source, Table
from .run import energy_series, load_scene, one_line_warnings, plot_energy, report, run_scene, scene_volume_outputs
from .topology import TopologySet

__all__ = [
    "Scene",
    "ChainMailScene",
    "Source",
    "Table",
    "load_scene",
    "demo_scene",
    "run_scene",
    "mass_spring_scene",
    "chainmail_scene",
    "energy_series",
    "plot_energy",
    "one_line_warnings",
    "report",
    "scene_volume_outputs",
    "SECTIONS",
    "TopologySet",
]
