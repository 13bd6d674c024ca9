"""Independent test oracles, sharing no code with the parts of torchdeform that they check.

* :mod:`tests.oracles.edge_list`: every spring of a grid listed one by one (forces, energies,
  Hessians and damping matrices in plain numpy);
* :mod:`tests.oracles.fuzzy`: Mamdani systems described as plain data, built in scikit-fuzzy and
  evaluated in numpy;
* :mod:`torchdeform.bench.accuracy.fem`: linear isotropic elasticity by finite elements (scikit-fem, quadratic
  hexahedra on graded meshes): uniaxial pull, simple shear, a cantilever under gravity, a bonded
  punch.
"""
