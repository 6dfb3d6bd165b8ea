"""The Model facade (layer 4): builds every table once from a body, a material and its
boundary conditions, solves, differentiates and post-processes. Imports the layers below.
"""
