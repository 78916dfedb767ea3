"""The learned correction of coarse MPM: an experiment that stopped at its
go/no-go (docs/history/learned-correction.md), kept here, out of the package,
so that it can be repeated.

A small per-particle network adds, as a force inside MPM on the half grid,
what one frame on the scene's grid would have done differently
(:mod:`.teacher`), trained DAgger-style without gradients through the solver
(:mod:`.train`, needs the train extra). ``go_no_go.py`` measures it against
the plain coarse grid and MPM at ``r_p``: on water2d and sand2d it does not
pay. :mod:`.features` (the local features of a coarse particle) is also what
the coarse ladder's rung 2 reads (``benchmarks/coarse_ladder_rung2.py``).

Modules: :mod:`.features`, :mod:`.teacher` (a coarse state split onto the
scene's grid, one fine frame), :mod:`.forcing` (the correction, its labels
and the oracle as forcings of :class:`~hybridmpm.sim.MpmSimulator`),
:mod:`.model` (the network in numpy), :mod:`.train` and ``go_no_go.py``.
Scripts import them as ``experiments.learned_correction.*`` with
``benchmarks/`` on the path (a script in ``benchmarks/`` has it).
"""
