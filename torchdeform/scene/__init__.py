"""Scene files (TOML) -> a model, an integrator and run settings, and the runner.

A scene file only builds the objects of the Python API: :class:`Scene` holds a
:class:`~torchdeform.sim.grid.Grid`, the keyword arguments of :class:`~torchdeform.sim.model.Model`
(``scene.model_args``), an :class:`~torchdeform.sim.integrators.Integrator` and the run settings;
:func:`cube_scene` builds a small dragged cube with the API alone, :func:`demo_scene` reads the built-in
demo (a liver pressed by a probe). :func:`run_scene` runs a
scene and writes ``trajectory.npz``, ``summary.json`` and ``energy.png``; with ``[[tools]]`` also
``tools.npz``, ``forces.png`` and the tools' force series in ``summary.json``
(:mod:`.tools`).

Units are SI (m, kg, s, N). Vectors are in channel order ``(D, H, W)``; axis D is "up" in
the built-in scenes (face ``"bottom"`` = ``"d-"``, ``"top"`` = ``"d+"``). Node indices are
``[i, j, k]`` along ``(D, H, W)``, from 0. A body of labels is in the image's patient frame
instead (LPS metres; :mod:`torchdeform.anatomy`). Keys that switch something on take ``true`` or
``false`` only (a string such as ``"no"`` is refused), and tissue names match in any case
(``"Liver"`` is ``"liver"``).

Keys
----
Each section below lists its keys as ``key``: meaning (default). The scene-file reference of the
documentation is generated from this list.

``[grid]`` (required):

- ``shape = [D, H, W]``: node counts, each >= 1 (or ``mesh``)
- ``mesh = "organ.stl"``: a closed triangle mesh voxelised into the node mask (instead of
  ``shape``; path relative to the scene file; mesh x, y, z -> D, H, W unless ``up`` says otherwise)
- ``up``: the mesh axis that points up, which becomes the lattice's axis D ("up", as in box scenes,
  where ``"bottom"`` is ``"d-"``): ``"x"`` (default: x, y, z -> D, H, W), ``"y"`` (y, z, x -> D, H, W),
  ``"z"`` (z, x, y -> D, H, W; most CAD and scanner meshes), or ``"-x"``, ``"-y"``, ``"-z"`` (the same
  turned upside down); the turn is a rotation, so the mesh keeps its inside (``mesh`` only)
- ``spacing``: metres, one number or ``[sd, sh, sw]`` (required). A body less than 1 mm or more than
  1 m across warns, naming the key: lengths are in metres (``spacing = 2`` meant as mm is a block
  metres wide; 2 mm is 0.002)
- ``topology``: 6, 14, 18 or 26 neighbours (26)
- ``origin = [od, oh, ow]``: position of node [0, 0, 0] in metres (0; ``shape`` only)
- ``padding``: extra node layers around the mesh's bounding box (0; ``mesh`` only)
- ``scale``: metres per mesh unit, e.g. 0.001 for a mesh in mm (1; ``mesh`` only)
- ``labels = "labels.nii.gz"``: instead of ``shape``: a label volume (NIfTI, NRRD, ``.npz``,
  ``.npy`` with ``label_spacing``, a DICOM series folder; relative to the scene file) or
  ``"phantom"`` / ``"phantom:VOXEL"`` (the procedural abdomen, :mod:`torchdeform.anatomy.phantom`);
  the body is made of its labels (:func:`torchdeform.anatomy.body_from_labels`: positions are LPS
  metres of the image's patient frame, axes D, H, W = x, y, z; nearest-voxel node labels; cells
  sampled about once per voxel, moduli in series across labels, modulus and mass scaled by each
  cell's fill). ``spacing`` is then one number (cubic cells), ``topology`` 14, 18 or 26, and the
  materials come from ``[[tissues]]``
- ``label_spacing``: the voxel size in metres of a ``.npy`` label volume (one or three numbers)
- ``surface_labels = [1, 2]``: the labels whose smooth surfaces are embedded (every label of the
  body; ``labels`` only)

``[material]`` (required):

- ``stiffness``: spring stiffness k in N/m: a number, or one per direction class
  ``{axis = .., face = .., body = ..}`` (only the classes of the topology are needed)
- ``spring_modulus``: instead of ``stiffness``: Y in N, each spring gets ``k = Y / l0``
  (resolution-independent); a number or a table as for ``stiffness``. (``modulus``, its old
  name, still works with a warning.) A stiffness or spring modulus whose lattice would have a
  Young's modulus outside 10 Pa - 10 MPa warns: that is no soft tissue, a unit is probably mixed up
- ``youngs_modulus``, ``poisson_ratio``: instead of ``stiffness``: the elastic solid of Young's
  modulus E (Pa, > 0) and Poisson ratio nu in [0.25, 0.5) (:class:`torchdeform.Elastic`: springs
  assembled from the cells plus a per-cell volume term; 14, 18 or 26 neighbours, cubic cells)
- ``tissue``: instead of ``stiffness``: words of the fuzzy tissue library (:mod:`torchdeform.fuzzy`,
  ``fuzzy/tissues.toml``), and the elastic solid they name (as ``youngs_modulus``): a tissue
  (``"liver"``, ``"fat"``, ...) gives the library's Young's modulus E (Pa, from its fuzzy system),
  Poisson ratio nu (0.475-0.49, nearly incompressible, with its source) and density; a consistency
  term (``"very_soft"`` ... ``"hard"``) or a consistency number 0..10 gives E and nu = 0.45 (no
  tissue, no measured ratio: nearly incompressible) and no density. ``poisson_ratio`` given beside
  ``tissue`` replaces the library's (0.45 doubles the explicit time step of 0.49). Unless
  ``damping`` is given, each spring gets the tissue's Kelvin-Voigt dashpot ``c = k eta / E`` (N s/m:
  spring stiffness k in N/m times the retardation time eta / E in s, eta the system's viscosity in
  Pa s): every spring relaxes with the same time, about 0.2-0.4 ms for the library's tissues (stiff
  for explicit integrators: ``dt = "auto"`` accounts for it). (Equal springs of Young's modulus E,
  as ``tissue`` gave before: ``stiffness = E h / 2.7`` for 26 neighbours, ``lattice_modulus``.)
- ``damping``: dashpot along each spring in N s/m (divided by l0 too with ``spring_modulus``);
  a number or a class table (none; for ``tissue``, Kelvin-Voigt as above)
- ``damping_mode``: ``"projected"`` (default) or ``"unprojected"`` (Radetzky)
- ``law``: ``"hooke"`` (default), ``"exponential"`` (``stiffening`` b) or ``"polynomial"``
  (``quadratic`` c2, ``cubic`` c3): strain-stiffening springs (:mod:`torchdeform.sim.laws`) whose
  small-strain stiffness is ``stiffness``; each parameter a number >= 0 or a class table (0)

``[[tissues]]`` (with ``[grid] labels``, repeatable; one per label of the image, label 0 is
background unless given): ``label`` (an integer) and one of

- ``tissue`` (as in ``[material]``) or ``youngs_modulus`` (Pa) with ``poisson_ratio`` (0.45) and
  ``density`` (kg/m^3, 1000): the label's material; library tissues bring their Kelvin-Voigt
  damping unless ``[material] damping`` is given (``[material]`` may hold only ``damping`` and
  ``damping_mode`` then; there is no ``[mass]`` and no ``[[regions]]``)
- ``fixed = true``: the label's nodes do not move (bone); a material beside it is optional (the
  stiffest tissue's)
- ``background = true``: the label is left out (air, the rest of the torso)

``[[surfaces]]`` (optional, repeatable): your own closed mesh embedded in the lattice
(:class:`torchdeform.mesh.EmbeddedSurface`), written and animated like the label surfaces of a body
of labels (``[output] surfaces = "embedded"``, ``animation``) and cut by ``[[cuts]]``:

- ``file``: a closed triangle mesh (``.stl``, ``.obj``, ``.ply``, ...; relative to the scene file;
  mesh x, y, z -> D, H, W, as for ``[grid] mesh``) (required)
- ``scale``: metres per mesh unit, e.g. 0.001 for a mesh in mm (1)
- ``up``: the mesh axis that becomes the lattice's axis D (up), as ``[grid] up`` (``"x"``)
- ``name``: the surface's name in the frame files (the file's stem)

A body of labels or of a mesh grows by the cells the surfaces pass through, so that it covers
them; a box body covers what lies in its box. A mesh outside the body's lattice is an error naming
the table's ``file`` and the mesh file.

``[[regions]]`` (optional, repeatable; needs ``stiffness`` as one number, ``tissue`` or
``youngs_modulus`` in ``[material]``): a part of the body with its own material, later regions on
top of earlier ones:

- ``sphere = {center = [d, h, w], radius = r}`` or ``box = {lo = [..], hi = [..]}``: the region
  (rest positions, m)
- a body of springs (``[material] stiffness``): ``stiffness`` (N/m) or ``tissue`` (its Young's
  modulus as springs ``k = E / lattice_modulus(grid)``); a spring gets the harmonic mean of its two
  end nodes' stiffness
- an elastic body (``[material] tissue`` or ``youngs_modulus``): ``youngs_modulus`` (Pa),
  ``poisson_ratio`` and ``tissue`` (as in ``[material]``, its E, nu, Kelvin-Voigt retardation time
  and density; its own ``poisson_ratio`` wins; not with ``youngs_modulus``) set per-node fields of E
  and nu (:class:`torchdeform.Elastic`, a cell takes the mean of its corners); keys a region does not
  give keep the body's values there. ``stiffness`` here, or ``youngs_modulus`` in a body of springs,
  is an error

``[mass]`` (required unless ``[material] tissue`` names a tissue of the library, whose density it
then takes, and that of the regions' tissues on their nodes; exactly one key; it wins over the
tissue's):

- ``mass``: kg per node
- ``density``: kg/m^3, lumped from cell volumes (each node owns its voxel, halved at the box faces)

``[boundary]`` (optional):

- ``fixed``: a face name or a list of them: ``"bottom"``, ``"top"``, ``"d-"``, ``"d+"``,
  ``"h-"``, ``"h+"``, ``"w-"``, ``"w+"``. A face is every node seen from that side: on a mesh body
  ``"bottom"`` is the first node of each column along D, i.e. the whole lower half-shell (half a
  sphere for a ball). A base patch instead: ``fixed = {below = h}``, the nodes within ``h`` metres
  of the body's lowest node along D, or a region ``fixed = {box = {lo = [..], hi = [..]}}`` or
  ``{sphere = {center = [..], radius = r}}`` (rest positions, m)
- ``fixed_nodes = [[i, j, k], ...]``: more fixed nodes
- ``home``: stiffness (N/m) of home springs to every node's rest position (Punak)
- ``anchors = {stiffness = .., every = ..}``: anchor springs (N/m) on the nodes with
  ``(i + j + k) % every == 0`` (Radetzky)
- ``decay``: global drag rate c in 1/s: ``v <- v exp(-c dt)`` each step
- ``gravity = [gd, gh, gw]``: m/s^2

``[[loads]]`` (optional, repeatable):

- ``node = [i, j, k]`` with ``force = [fd, fh, fw]``: a point force (N) on one node
- ``face = "top"`` with ``traction = [td, th, tw]``: a traction (Pa) lumped onto the face's nodes
- ``start``: s, when the load appears (0)
- ``ramp``: s, how long it takes to reach full strength (0)

``[[drags]]`` (optional, repeatable): a group of nodes moved rigidly along a path:

- ``nodes = [[i, j, k], ...]``, ``face = "top"`` or ``box = {lo = [..], hi = [..]}``: the group
  (box: rest positions in metres, bounds included)
- ``path = [[t, [od, oh, ow]], ...]``: offsets (m) from the rest position at increasing times (s),
  linear in between, held after the last

``[[tools]]`` (optional, repeatable): rigid tools touching the tissue (:mod:`torchdeform.interact`):

- ``name``: unique; the keys of the force readings (``tool1``, ``tool2``, ...)
- ``shape``: ``"sphere"`` (``radius``), ``"capsule"`` (``radius``, ``half_length``, ``axis`` =
  ``"d"``, ``"h"`` or ``"w"``), ``"box"`` (``half_extents = [hd, hh, hw]``), ``"half_space"``
  (``normal``, default ``[1, 0, 0]``) or ``"mesh"`` (``file``, a closed mesh relative to the scene
  file, and ``resolution`` of its distance field, default 32); metres
- ``position = [d, h, w]``: a fixed pose, with an optional ``orientation = [rd, rh, rw]`` (a
  rotation vector in radians)
- ``path = [[t, [d, h, w]], ...]`` or ``[[t, [d, h, w], [rd, rh, rw]], ...]``: poses at increasing
  times, linear in between, held after the last
- ``contact``: ``"projection"`` (default; options ``friction``, ``direction`` = ``"normal"`` or
  ``"motion"``, ``hold``, ``haptic_gain``), ``"penalty"`` (``stiffness`` N/m, ``damping``) or
  ``"none"`` (a grasp, or a tool that only cuts or burns)
- ``grasp = {close = t1, open = t2, margin = m}``: forceps: what lies in the shape (plus
  ``margin``) at ``close`` follows the tool until ``open`` (s; ``inf`` for never)
- ``start_inside``: true: the tool may start inside the body (false). A tool with a contact that holds
  rest nodes deeper than half the spacing at t = 0 is otherwise an error (the contact would fling
  them out in the first step); one that never comes within the spacing (plus a grasp's ``margin``)
  of the body over its path warns (positions are metres: a path in millimetres misses the body)

``[strain_limit]`` (optional): every spring's length kept within bounds of its rest length:

- ``min``, ``max``: the bounds, as ratios of the rest length (0.9, 1.1)
- ``passes``: Jacobi passes per step (4)
- ``update_velocity``: velocities follow the corrections (true)

``[[cuts]]`` (optional, repeatable): a blade cutting the springs it crosses (:mod:`.topology`):

- ``origin = [d, h, w]``, ``u``, ``v``: the parallelogram blade ``origin + a u + b v``, ``a, b`` in
  [0, 1] (m); or ``triangle = [[d, h, w], [..], [..]]``; or ``edges = [[[d, h, w], [d, h, w]],
  ...]``, the surface a straight edge sweeps through two or more poses
- ``at``: s, when the blade cuts (0)
- ``tool``, ``edge``, ``start``, ``stop``, ``pieces``: instead of a blade, a scalpel: the edge
  ``[[a], [b]]`` in the frame of a ``[[tools]]`` entry cuts what it sweeps from ``start`` (s, 0) to
  ``stop`` (s, the end of the run), ``pieces`` triangles per step (1)
- ``gape``: in [0, 1): the springs left at the cut's nodes shorten by this fraction, and the cut
  opens (0)

Every cut also cuts the embedded surfaces (label surfaces, ``[[surfaces]]``) with the same blade,
at the node positions of that moment (:meth:`torchdeform.mesh.EmbeddedSurface.cut_patches`): a
blade when it cuts the springs, a scalpel's sweep at every recorded frame and when it stops.

``[[cautery]]`` (optional, repeatable):

- ``tool``: the nodes inside this tool are burnt away, with their springs
- ``at``: once, at this time (s); or ``every`` (1), ``start`` (0), ``stop`` (the end): at every
  ``every``-th step from ``start`` to ``stop``

``[tear]`` (optional):

- ``max_strain`` (``l / l0 - 1`` > 0) or ``max_force`` (N > 0: the strain ``F / (k l0)`` of each
  spring): springs past the limit break
- ``one_per_step``: only the most strained spring breaks per step (false)
- ``start``: s, when tearing starts (0)

``[[coagulate]]`` (optional, repeatable):

- ``at``: s, when the region coagulates (0)
- ``box = {lo = [..], hi = [..]}`` or ``sphere = {center = [..], radius = r}``: the region, as in
  ``[[regions]]``; springs with both ends in it take their current length as rest length
- ``viscosity_factor``: >= 1, their damping is multiplied by it (1)

A tool that only cuts or burns may have ``contact = "none"``. Every time lies in ``[0, steps x
dt]``; a blade (or a scalpel's edge along its path) must reach the body's rest bounding box.

``[integrator]`` (required):

- ``name``: ``"explicit"``, ``"symplectic"`` (default), ``"verlet"``, ``"rk4"``, ``"implicit"``,
  ``"projective"``, ``"adaptive"``, ``"knoche"`` or ``"static"`` (below)
- ``dt``: seconds > 0, or ``"auto"`` (explicit integrators: ``safety`` x the stability bound)
- ``safety``: fraction of the bound used by ``dt = "auto"`` (0.9)
- ``settle``: ``true`` or seconds: before the run, the body settles under gravity alone (no loads,
  tools or drag motion yet; fixed and dragged nodes where they are at t = 0): the static solve
  (:func:`torchdeform.solve_static`, float64) where it converges, else damped steps of this
  integrator for ``settle`` seconds (0.2 for ``true``). The run, and its first recorded frame, start
  from that state at rest; ``summary.json`` says how in ``"settle"`` (false)
- ``steps``: number of steps >= 0 (required)
- ``dtype``: ``"float32"`` (default) or ``"float64"``
- ``device``: ``"cpu"`` (default) or ``"cuda"`` (``--device`` overrides it)
- ``threads``: CPU threads of the run (torch's; small bodies run faster on one, and much faster
  on a busy machine)
- ``engine``: ``"auto"`` (default: the C-kernel or compiled step when the run repays its
  start-up), ``"eager"``, ``"native"`` or ``"compiled"``; the summary's ``engine`` says which ran
  and why
- ``kd``: ``verlet``'s per-step damping in [0, 1) (0)
- ``cg_iters`` (100), ``cg_tol`` (1e-6), ``newton_iters`` (0): ``implicit``'s options
- ``iterations`` (10), ``tol`` (0), ``solver`` (``"auto"``, ``"cholesky"``, ``"cg"``,
  ``"jacobi"``), ``rho`` (0.95), ``relaxation`` (0.9), ``delay`` (1), ``cg_iters`` (50),
  ``cg_tol`` (1e-6): ``projective``'s options
- ``rtol`` (1e-3), ``pair`` (``"bogacki_shampine"``), ``min_step``, ``max_step``: ``adaptive``'s
  options; ``dt`` is then the interval between recorded states, the steps are its own
- ``material`` (w in [0, 1], a number or a ``[D][H][W]`` array), ``eps`` (1e-3), ``gain``
  (3 / D): ``knoche``'s options (it needs ``topology = 6``)
- ``name = "static"``: no time steps (no ``dt``, ``steps``, ``safety``, ``engine``): one static
  solve (:func:`torchdeform.solve_static`, Newton with CG inner solves) for the equilibrium under
  gravity, the loads and the drags; the run writes the rest state and the equilibrium as two frames
  of ``trajectory.npz`` (velocities zero), ``summary.json`` with a ``"static"`` part (``residual``,
  ``converged``, ``iterations``, ``cg_iterations``, ``tol``, ``time_s``), ``energy.png`` and the
  ``[volume]`` and ``[texture]`` outputs of the equilibrium. Its options: ``tol`` (relative residual
  ``|F| / |load|`` in (0, 1); 1e-6, or 1e-3 in float32 where rounding stalls Newton near 5e-4),
  ``max_iter`` (Newton iterations, 50), ``cg_iters`` (500), ``cg_tol`` (1e-3), ``time`` (s: when
  loads and drags are taken; the end of every ramp and drag path); ``dtype`` is ``"float64"`` by
  default. A solve that does not converge writes nothing: one line naming ``integrator.max_iter``,
  exit status 2. No ``[[tools]]``, ``[strain_limit]``, topology sections, ``record_every``,
  ``surfaces``, ``animation`` or ``palpation`` with it

``[output]`` (optional):

- ``record_every``: steps between saved frames (about 100 frames)
- ``name``: title of the run (the file's name)
- ``palpation``: ``true`` (the first tool with a contact) or a tool's name: analyse its presses,
  write ``palpation.png`` and a ``"palpation"`` part of ``summary.json``
- ``surfaces = [t1, t2, ...]``: times (s) at which the closed surface of every connected piece
  (and side of the latest blade) is written as ``surface_<ms>ms_<label>.ply``; or, for a body of
  labels or with ``[[surfaces]]``, ``"embedded"``: the smooth surfaces carried by the lattice (the
  label surfaces: marching cubes at image resolution, Taubin smoothing, decimation; the
  ``[[surfaces]]`` meshes), written at every recorded frame as ``surfaces/frame_NNNN.glb``
  (:func:`torchdeform.mesh.embed.save_surfaces`), cut as the cuts left them by that frame's time
- ``surface_format``: ``"glb"`` (default) or ``"ply"`` (embedded surfaces)
- ``surface_faces``: triangles per label surface after decimation (10,000)
- ``animation``: ``true``: write ``animation.gif``, the textured surface (a body of labels: its
  embedded surfaces, smooth and wet) with the scene's tools, beside the deformed volume render
  when the scene has a ``[volume]``, with the time and the tools' forces (as ``torchdeform run
  --animation``; see :func:`torchdeform.scene.animation.animate`)
- ``image_size``: pixels of each square panel of the animation (512, at most 2048)
- ``camera``: ``[x, y, z]``, where the animation's surface panel looks from (from the body's
  centre, its length fitted); ``camera_up``: the direction upwards in that panel. Defaults: a
  view along ``(1.3, -1.1, 0.9)`` with axis D up; a body of labels (the LPS patient frame) is seen
  from the patient's right, in front and above, ``(-1.2, -0.9, 0.5)``, anterior (``-y``) up

``[volume]`` (optional): a volume filling the grid's bounding box, deformed by the final state;
the run also writes ``volume_before.png``, ``volume_after.png``, ``volume_deformed.npy``:

- ``file``: a volume file (.npy, .npz, .nii, .nrrd; relative to the scene file), ``"phantom:N"``
  or ``"phantom-lumen:N"`` (the phantom with an air-filled bowel loop)
- ``tf``: transfer-function preset or file (``"ct-soft"``)
- ``mode``: ``"dvr"`` (default), ``"mip"`` or ``"average"``
- ``view``: axis view (``"h"``)

``[camera]`` (optional, with ``[volume]`` and ``[[tools]]``): an endoscope riding a tool, looking
through the volume deformed at every recorded frame; the run writes ``endoscope.gif`` and
``endoscope.png`` (:mod:`.camera`):

- ``kind``: ``"endoscope"``; ``tool``: the tool it rides (required; it may have ``contact = "none"``)
- ``look``: a fixed view direction ``[d, h, w]`` (default: along the tool's motion); ``up``
- ``ahead``: m, the lens in front of the tool's centre (0); ``fov``: degrees in (0, 180) (100)
- ``size``: ``[height, width]`` pixels (``[192, 192]``); ``far``: m, the depth of view (all)
- ``distortion``: barrel coefficient ``k1`` (0); ``every``: every k-th recorded frame (1);
  ``step``: voxels between samples (0.5); ``inside``: ``"require"`` (the lens inside the
  volume at every frame) or ``"allow"``

``[texture]`` (optional): a solid texture on the body's material points; the run writes
``textured.png`` of the final surfaces, cut faces showing the interior:

- ``exemplar``: ``"liver"``, ``"liver:N"`` or an exemplar file (.npy, .npz, a folder of slices;
  relative to the scene file) (``"liver:64"``)
- ``block``: block size in voxels (half the exemplar's smallest side)
- ``seed``: random offsets of the blocks (0)
- ``voxel``: texture voxel size in m (a quarter of the smallest spacing)
- ``seams``: ``"3d"`` (default), ``"slices"`` or ``"none"``: block seams blended; the seam measure
  before and after goes into ``summary.json``

``[[bodies]]`` (optional, repeatable; instead of the body sections above): several bodies touching
each other (:mod:`.bodies`): each entry has a ``name`` and the sections of one body as sub-tables
(``[bodies.grid]`` with ``origin``, ``[bodies.material]``, ``[bodies.mass]``, ``[bodies.boundary]``,
``[[bodies.regions]]``, ``[[bodies.tissues]]``, ``[[bodies.loads]]``, ``[[bodies.drags]]``,
``[[bodies.tools]]``, ``[bodies.strain_limit]``); ``[integrator]``, ``[output]`` (``record_every``,
``name``) and ``[contact]`` (``friction``, 0) are global

``model = "chainmail"`` (optional top-level key, before any section): a ChainMail scene instead of
a mass-spring one, with ``[grid]`` (its topology ignored: ChainMail links face neighbours),
``[boundary]`` (``fixed``, ``fixed_nodes``), ``[[drags]]`` (the picked elements and their paths),
``[output]`` (``name``) and ``[chainmail]`` (required; :func:`torchdeform.scene.chainmail.chainmail_scene`):

- ``method``: ``"gibson"`` (default) or ``"enhanced"``
- ``compression`` (0.9), ``stretch`` (1.1), ``shear`` (0.1): the limits as ratios of the spacing
- ``tissue``: instead of the ratios, a name of the fuzzy tissue library or a consistency 0..10,
  with ``reference_stress`` (Pa, 300)
- ``frames``: frames of the run (20)
- ``relax_steps`` (0), ``relax_mode`` (``"centroid"`` or ``"goal"``), ``relax_moved_only``
  (false): relaxation after each frame
- ``on_blocked``: ``"scale"`` (default) or ``"error"``: a move that would shift a fixed element

Every problem is a :class:`~torchdeform.errors.ConfigError` naming the file, the line (found
by a text search, best effort), the dotted key (``integrator.dt``, ``loads[0].force``; array
tables count from 0) and what was expected.

Modules: :mod:`.reader` (files, located errors, typed values and the shared sections: the API a
new model kind builds on), :mod:`.mass_spring`, :mod:`.tools` (``[[tools]]``, ``[strain_limit]``
and the tool outputs of a run), :mod:`.topology` (cuts, cautery, tearing, coagulation and their outputs), :mod:`.chainmail`, :mod:`.bodies`
(several bodies in one scene, and their run), :mod:`.camera` (``[camera]``: the endoscope's view),
:mod:`.run` (load and run),
:mod:`.animation` (a run's frames, textured surface beside the deformed volume, into an animated GIF),
:mod:`.demo` (the built-in demo), :mod:`.commands` (``torchdeform run`` and ``demo``).

Example:
    >>> from torchdeform.scene import cube_scene, run_scene
    >>> scene = cube_scene()
    >>> scene.steps = 20
    >>> scene.volume = None              # skip the volume renders (about a second)
    >>> summary = run_scene(scene, getfixture("tmp_path"), progress=False)
    >>> summary["steps"], summary["frames"]
    (20, 3)
"""

from .chainmail import ChainMailScene, chainmail_scene
from .demo import demo_scene
from .mass_spring import Scene, cube_scene, mass_spring_scene
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
    "cube_scene",
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
