"""The thesis studies behind the ``jaxrkpm`` console script: thin drivers (arguments ->
scenario of :mod:`jaxrkpm.thesis` -> run -> ``summary.json`` + figures), one module per
command, each with ``main(argv)`` and runnable as ``python -m jaxrkpm.thesis.studies.<name>``.

:mod:`.demo` (the box path on the 9x9 square), :mod:`.track` (chapter-5 tracking, 2D and
the 3D cube), :mod:`.compress` (section 5.2 compression to failure), :mod:`.needle`
(chapter 6), :mod:`.rig_sim` (the simulated rig of section 5.3.2), :mod:`.cantilever`
(Timoshenko verification), :mod:`.reproduce` (all of them, with the report against the
thesis). The modules are imported lazily by :mod:`jaxrkpm.thesis.cli`; this package imports none.
"""
