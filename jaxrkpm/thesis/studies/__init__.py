"""The thesis studies behind the ``jaxrkpm`` console script: thin drivers (arguments ->
scenario of :mod:`jaxrkpm.thesis` -> run -> ``summary.json`` + figures), one module per
command, each with ``main(argv)`` and its declaration ``COMMAND`` (:mod:`.command`: its name,
parser, run, experiments).

:mod:`.demo` (the box path on the 9x9 square), :mod:`.compress` (section 5.2 compression to
failure), :mod:`.track` (chapter-5 tracking, 2D and the 3D cube), :mod:`.rig_sim` (the
simulated rig of section 5.3.2), :mod:`.needle` and :mod:`.needle3d` (chapter 6),
:mod:`.cantilever` (Timoshenko verification), :mod:`.sweep` (needle sweeps to disk),
:mod:`.reproduce` (all of them, with the report against the thesis). :mod:`.interface` holds
what they share on the command line and :mod:`.experiments` the reproduce entries' form.
:mod:`jaxrkpm.thesis.cli` finds the commands (:func:`.command.commands`); this package
imports none of them.
"""
