"""The Model facade (layer 4): builds every table once from a body, a material and its
boundary conditions (through the builders of the layers below), then solves, differentiates
and post-processes by the functions beside it: ``inputs``, ``linear``, ``solving``,
``jacobian``, ``post``. Imports the layers below.
"""
